"""A cell behind a socket as a backend: the dlocli-cell protocol's REQ side.

Everything above the backend (the env, its task, every controller) runs unchanged; the rod is
stepped by the cell, a served simulator (``dlo serve``) or a robot with a tracker.
"""

from __future__ import annotations

import contextlib
from pathlib import Path
from typing import Any

import numpy as np

from dlocli.backends.base import Backend
from dlocli.bridge import messages, protocol
from dlocli.bridge.keys import require_keys_off_loopback, secure_controller
from dlocli.errors import BadInput, DloError
from dlocli.specs import BackendSpec


class CellLost(DloError):
    """The cell failed mid-run (exit 1): it stopped answering, another controller took it, or
    it answered nonsense. The run stops, its finished steps kept."""

    def __init__(self, what: str, steps_kept: bool = True) -> None:
        self.what = what
        ending = (
            "the run stopped and its finished steps are kept"
            if steps_kept
            else "the run stopped before its first step; nothing was written"
        )
        super().__init__(f"{what}; {ending}")

    def before_first_step(self) -> CellLost:
        """The same loss, said of a run that had not finished a step."""
        return CellLost(self.what, steps_kept=False)


class RemoteCell(Backend):
    """The rod of ``spec`` stepped by the cell at ``address`` (``keys``: the CURVE keys
    folder, required off loopback)."""

    name = "cell"

    def __init__(
        self,
        spec: BackendSpec,
        control_dt: float,
        address: str,
        timeout_s: float = 2.0,
        keys: Path | None = None,
    ) -> None:
        import zmq

        require_keys_off_loopback(address, keys, "--cell", "--cell-keys")
        self.address, self.timeout_s, self.keys = address, timeout_s, keys
        super().__init__(spec, control_dt)
        self.name = spec.name  # the rod is the spec's: the cell checks it is its own
        self._context = zmq.Context()
        self._socket: Any = None
        self._answered = False
        self._session = ""
        self.state: dict[str, Any] = {}
        #: what the cell said of itself when it welcomed this controller
        self.cell: messages.CellInfo | None = None
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
        self._socket.setsockopt(zmq.MAXMSGSIZE, protocol.MAX_REPLY_BYTES)
        self._socket.setsockopt(zmq.SNDTIMEO, int(1000 * self.timeout_s))
        if self.keys is not None:
            secure_controller(self._socket, self.keys)
        self._socket.connect(self.address)
        welcome = self._request("hello", protocol=protocol.PROTOCOL, version=protocol.VERSION,
                                backend=self.spec.model_dump(mode="json"),
                                control_dt=self.control_dt)  # fmt: skip
        if not isinstance(welcome, messages.Welcome):
            raise self._fault(f"it answered hello with {welcome.type}")
        if (welcome.protocol, welcome.version) != (protocol.PROTOCOL, protocol.VERSION):
            raise BadInput(
                f"the cell at {self.address} speaks {welcome.protocol} version "
                f"{welcome.version}, this controller {protocol.VERSION}: update the cell "
                "(examples/bridge/robot_cell.py shows version 2)"
            )
        self.cell, self._session = welcome.cell, welcome.session
        if self.cell.n_segments != self.n_segments:
            raise BadInput(
                f"the cell at {self.address} has {self.cell.n_segments} segments, the "
                f"spec {self.n_segments}: set backend.rod.n_segments to the cell's"
            )

    def _request(
        self, kind: str, timeout_s: float | None = None, **fields: Any
    ) -> messages.AnyReply:
        """Send one request, wait up to ``timeout_s`` (default: --cell-timeout-s) for its
        reply, checked; a refusal raises."""
        if kind != "hello":
            fields["session"] = self._session
        wait = self.timeout_s if timeout_s is None else max(timeout_s, self.timeout_s)
        try:
            self._socket.send(protocol.encode(kind, **fields))
            answered = self._socket.poll(int(1000 * wait))
            message = self._socket.recv() if answered else None
        except Exception as exc:  # the socket itself failed (zmq.ZMQError, zmq.Again)
            raise self._fault(f"its socket failed: {exc}") from None
        if message is None:
            raise self._silence(wait)
        try:
            reply = messages.parse_reply(message)
        except BadInput as exc:
            raise self._fault(str(exc)) from None
        self._answered = True
        if isinstance(reply, messages.Error):
            raise self._refusal(kind, reply)
        return reply

    def _refusal(self, kind: str, error: messages.Error) -> DloError:
        if error.code in ("busy", "no_session") and self._session:
            return CellLost(
                f"the cell at {self.address} is no longer this controller's ({error.message})"
            )
        if error.code == "busy" and kind == "hello":
            return BadInput(
                f"the cell at {self.address} is busy ({error.message.removeprefix('busy: ')}): "
                "wait for that controller to end (or stop it) and run again"
            )
        if error.code in ("busy", "cell_fault") or self._answered and kind == "step":
            return CellLost(f"the cell at {self.address} refused {kind}: {error.message}")
        return BadInput(f"the cell at {self.address} refused {kind}: {error.message}")

    def _silence(self, waited_s: float) -> DloError:
        self._drop_socket()
        if not self._answered:
            return BadInput(
                f"no cell answers at {self.address} within {waited_s:g} s "
                "(--cell-timeout-s): start one with `dlo serve --address ADDRESS` or check the "
                "address (and, if the cell has keys, that --cell-keys is the folder it was "
                "given as --keys)"
            )
        return CellLost(
            f"the cell at {self.address} stopped answering (no reply within {waited_s:g} s)"
        )

    def _fault(self, what: str) -> DloError:
        """A reply that breaks the protocol: before the run, bad input; during it, the end."""
        self._drop_socket()
        line = f"the cell at {self.address} broke the protocol: {what}"
        if not self._answered:
            return BadInput(f"{line}; is it a dlocli-cell version {protocol.VERSION} cell?")
        return CellLost(line)

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

    def _take(self, reply: messages.AnyReply, expected_step: int | None) -> None:
        """A state reply's numbers; CellLost if the cell's step count shows that someone
        else reset or stepped it since this controller's last request."""
        if not isinstance(reply, messages.State):
            raise self._fault(f"a {reply.type} where a state belongs")
        try:
            arrays = messages.state_arrays(reply, self.n_segments)
        except BadInput as exc:
            raise self._fault(str(exc)) from None
        if expected_step is not None:
            self._check_own(reply.step, expected_step)
        self.state = arrays | {"late": reply.late, "dropped": reply.dropped, "step": reply.step}
        self.diverged, self.tracked = reply.diverged, reply.tracked
        self._gripper_poses = arrays["grippers"]

    def _check_own(self, step: int, expected: int) -> None:
        realtime = self.cell is not None and self.cell.realtime
        # a real-time cell steps periods with the held command while none comes: it may be ahead
        if step == expected or (realtime and step > expected):
            return
        raise CellLost(
            f"the cell at {self.address} was reset or stepped by someone else (its step "
            f"{step}, this controller's {expected})"
        )

    # ------------------------------------------------------------------ the backend
    def reset(self, seed: int | None = None) -> None:
        # the limits go with every reset: the env sets them after building its backend
        timeout = self.cell.reset_timeout_s if self.cell is not None else None
        self._take(self._request("reset", timeout, seed=seed, limits=self._limits()), 0)

    def _move(self, velocities: np.ndarray) -> None:
        # the cell keeps its grippers inside the limits (sent with the reset)
        expected = self.state.get("step", 0) + 1
        self._take(self._request("step", step=expected, velocities=velocities), expected)

    def segment_positions(self) -> np.ndarray:
        return self.state["positions"].copy()

    def segment_quaternions(self) -> np.ndarray:
        return self.state["quaternions"].copy()

    def camera_spec(self) -> dict[str, Any] | None:
        """The cell's depth camera (a camera spec), or None if it has none."""
        return None if self.cell is None else self.cell.camera

    def capture_cloud(self, seed: int, time: float) -> dict[str, np.ndarray | float]:
        """The cell camera's frame now: points (P,3), extrinsics (4,4), intrinsics (3,3),
        time (s), segments (P,) (-1 where unknown); ``seed`` seeds a simulated camera's noise
        for the episode."""
        cloud = self._request("capture", seed=seed, time=time)
        if not isinstance(cloud, messages.Cloud):
            raise self._fault(f"a {cloud.type} where a cloud belongs")
        points = np.array(cloud.points, dtype=np.float64).reshape(-1, 3)
        segments = cloud.segments if cloud.segments is not None else [-1] * len(points)
        if len(segments) != len(points):
            raise self._fault(f"a cloud of {len(points)} points with {len(segments)} segments")
        return {
            "points": points,
            "extrinsics": np.array(cloud.extrinsics, dtype=np.float64),
            "intrinsics": np.array(cloud.intrinsics, dtype=np.float64),
            "time": cloud.time,
            "segments": np.array(segments, dtype=np.int32),
        }

    def get_state(self) -> np.ndarray:
        snapshot = self._request("get_state")
        if not isinstance(snapshot, messages.Snapshot):
            raise self._fault(f"a {snapshot.type} where a snapshot belongs")
        return np.array(snapshot.state, dtype=np.float64)

    def set_state(self, state: np.ndarray) -> None:
        self._take(self._request("set_state", state=np.asarray(state, dtype=np.float64)), None)

    def render(
        self, width: int = 480, height: int = 360, goal: np.ndarray | None = None
    ) -> np.ndarray:
        raise BadInput("the rod is in a cell: it has no picture here (drop --video)")

    def close(self) -> None:
        """Leave the grippers stopped, say goodbye (if this controller has a session and the
        cell still answers), let go."""
        if self._socket is not None and self._session:
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
