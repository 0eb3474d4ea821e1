"""A cell behind a socket as a backend: the dlocli-cell protocol's REQ side.

Everything above the backend (the env, its task, every controller) runs unchanged; the rod is
stepped by the cell, a served simulator (``dlo serve``) or a robot with a tracker.
"""

from __future__ import annotations

import contextlib
from typing import Any

import numpy as np

from dlocli.backends.base import Backend
from dlocli.bridge import protocol
from dlocli.errors import BadInput, DloError
from dlocli.specs import BackendSpec


class CellLost(DloError):
    """The cell stopped answering mid-run (exit 1): the run stops, its finished steps kept."""


class RemoteCell(Backend):
    """The rod of ``spec`` stepped by the cell at ``address``."""

    name = "cell"

    def __init__(
        self, spec: BackendSpec, control_dt: float, address: str, timeout_s: float = 2.0
    ) -> None:
        import zmq

        self.address, self.timeout_s = address, timeout_s
        super().__init__(spec, control_dt)
        self.name = spec.name  # the rod is the spec's: the cell checks it is its own
        self._context = zmq.Context()
        self._socket: Any = None
        self._answered = False
        self.state: dict[str, Any] = {}
        #: what the cell said of itself when it welcomed this controller
        self.cell: dict[str, Any] = {}
        try:
            self._connect()  # a cell that is not there is refused before any run starts
        except BaseException:
            self.close()
            raise

    # ------------------------------------------------------------------ the socket
    def _connect(self) -> None:
        import zmq

        self._socket = self._context.socket(zmq.REQ)
        self._socket.setsockopt(zmq.LINGER, 0)
        self._socket.setsockopt(zmq.RCVTIMEO, int(1000 * self.timeout_s))
        self._socket.setsockopt(zmq.SNDTIMEO, int(1000 * self.timeout_s))
        self._socket.connect(self.address)
        welcome = self._request("hello", protocol=protocol.PROTOCOL, version=protocol.VERSION,
                                backend=self.spec.model_dump(mode="json"),
                                control_dt=self.control_dt)  # fmt: skip
        self.cell = welcome.get("cell") or {}
        if self.cell.get("n_segments") != self.n_segments:
            raise BadInput(
                f"the cell at {self.address} has {self.cell.get('n_segments')} segments, the "
                f"spec {self.n_segments}: set backend.rod.n_segments to the cell's"
            )

    def _request(self, kind: str, **fields: Any) -> dict[str, Any]:
        import zmq

        try:
            self._socket.send(protocol.encode(kind, **fields))
            reply = protocol.decode(self._socket.recv())
        except zmq.Again:
            self._drop_socket()
            raise self._silence() from None
        self._answered = True
        if reply["type"] == "error":
            raise BadInput(f"the cell at {self.address} refused {kind}: {reply.get('message')}")
        return reply

    def _silence(self) -> DloError:
        if not self._answered:
            return BadInput(
                f"no cell answers at {self.address} within {self.timeout_s:g} s "
                "(--cell-timeout-s): start one with `dlo serve --address ADDRESS` or check the "
                "address"
            )
        return CellLost(
            f"the cell at {self.address} stopped answering (no reply within {self.timeout_s:g} "
            "s); the run stopped and its finished steps are kept"
        )

    def _drop_socket(self) -> None:
        if self._socket is not None:
            self._socket.close()
            self._socket = None

    def _limits(self) -> dict[str, Any]:
        return {
            "workspace_low": self.limits.low,
            "workspace_high": self.limits.high,
            "min_separation": self.limits.min_separation,
            "max_separation": self.limits.max_separation,
        }

    def _take(self, reply: dict[str, Any]) -> None:
        n = self.n_segments
        self.state = {
            "positions": protocol.array(reply, "positions", (n, 3)),
            "quaternions": protocol.array(reply, "quaternions", (n, 4)),
            "grippers": protocol.array(reply, "grippers", (2, 7)),
            "late": int(reply.get("late", 0)),
            "dropped": int(reply.get("dropped", 0)),
            "step": int(reply.get("step", 0)),
        }
        self.diverged = bool(reply.get("diverged", False))
        self.tracked = bool(reply.get("tracked", True))
        self._gripper_poses = self.state["grippers"]

    # ------------------------------------------------------------------ the backend
    def reset(self, seed: int | None = None) -> None:
        # the limits go with every reset: the env sets them after building its backend
        self._take(self._request("reset", seed=seed, limits=self._limits()))

    def _move(self, velocities: np.ndarray) -> None:
        # the cell keeps its grippers inside the limits (sent with the reset)
        self._take(self._request("step", step=self.state.get("step", 0) + 1,
                                 velocities=velocities))  # fmt: skip

    def segment_positions(self) -> np.ndarray:
        return self.state["positions"].copy()

    def segment_quaternions(self) -> np.ndarray:
        return self.state["quaternions"].copy()

    def get_state(self) -> np.ndarray:
        return np.asarray(self._request("get_state")["state"], dtype=np.float64)

    def set_state(self, state: np.ndarray) -> None:
        self._take(self._request("set_state", state=np.asarray(state, dtype=np.float64)))

    def render(
        self, width: int = 480, height: int = 360, goal: np.ndarray | None = None
    ) -> np.ndarray:
        raise BadInput("the rod is in a cell: it has no picture here (drop --video)")

    def close(self) -> None:
        """Leave the grippers stopped, say goodbye (if the cell still answers), let go."""
        if self._socket is not None and self._answered:
            with contextlib.suppress(DloError):
                self._request("stop")
                self._request("bye")
        self._drop_socket()
        self._context.term()

    # the cell does the physics; these hooks of a simulator in this process have no role here
    def _reset_physics(self, seed: int | None) -> None:
        raise NotImplementedError

    def _advance(self, start: np.ndarray, end: np.ndarray) -> bool:
        raise NotImplementedError

    def _get_physics_state(self) -> np.ndarray:
        raise NotImplementedError

    def _set_physics_state(self, state: np.ndarray) -> None:
        raise NotImplementedError
