"""A run's 3D recording for the Rerun viewer (``--record RUN.rrd``; the ``view`` extra).

Everything is logged on one timeline, ``step`` (0: right after the reset, t: after the t-th
command), under these entities (metres, the simulator's world frame):

========================  ============================================================
world/rod                 the rod's true segment centres, a line strip
world/goal                the goal shape (logged at each episode's start)
world/grippers            the grippers' poses, small boxes
world/markers/seen        the markers as the controller saw them (markers observation)
world/markers/hidden      the markers the tracker did not see at that step (their report)
world/camera/cloud        the depth camera's latest point cloud (pointcloud observation)
world/plan/grippers       a planner's planned gripper path (at each re-plan)
world/plan/predicted      its model's predicted shapes along the plan it last evaluated
world/workspace           the task's workspace box (static)
world/recorded|predicted  `dlo eval` on recorded markers: them and the model's open-loop
                          prediction (metrics/prediction_error_mm: its free markers' error)
world/envelope/SIDE       the envelope's box of the left or right gripper, if set (static)
metrics/shape_error_mm    the shape error (mm), as in metrics.csv
metrics/reward            the step's reward
envelope/clipped          the envelope's counts of clipped commands so far, one per limit
========================  ============================================================

A run only keeps its steps' arrays; a writer process (:mod:`dlocli.runs.recording_writer`),
started when the path is checked, imports Rerun meanwhile and writes the file when the run
ends (atomically: it appears whole). Read it with ``rerun RUN.rrd`` or Rerun's own API.
"""

from __future__ import annotations

import importlib.util
import io
import subprocess
import sys
from contextlib import ExitStack
from pathlib import Path
from typing import Any

import numpy as np

from dlocli.env.envelope import LIMITS
from dlocli.env.metrics import shape_error_mm
from dlocli.env.shapes import max_twist
from dlocli.errors import BadInput, DloError
from dlocli.extras import EXTRAS, require
from dlocli.io import atomic_path, check_writable

#: how long a run waits for its recording to be written once it has sent its steps
WRITE_TIMEOUT_S = 600.0


def check_record_path(path: Path | None, overwrite: bool, flag: str = "--record") -> None:
    """BadInput unless ``path`` is None or a writable new (or, with ``overwrite``, any) .rrd
    file, with the ``view`` extra installed: checked before the run starts, which also
    starts the process that will write it."""
    if path is None:
        return
    if importlib.util.find_spec(EXTRAS["view"]) is None:
        require("view", flag, "drop the flag")  # says which extra, in one line
    if Path(path).suffix != ".rrd":
        raise BadInput(f"{flag} {path} must end in .rrd (a Rerun recording)")
    check_writable(Path(path), flag, overwrite)
    global _started
    if _started is None:
        _started = _start_writer()


#: the writer started by the last check, importing Rerun while the run gets ready
_started: subprocess.Popen[bytes] | None = None


def _start_writer() -> subprocess.Popen[bytes]:
    # its own session: a Ctrl-C to the run leaves it to write what the run kept
    return subprocess.Popen(
        [sys.executable, "-m", "dlocli.runs.recording_writer"], stdin=subprocess.PIPE,
        stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, start_new_session=True,
    )  # fmt: skip


def open_recording(path: Path | None, name: str) -> RunRecording | NoRecording:
    """The recording to ``path``, or one that logs nothing when ``path`` is None."""
    return NoRecording() if path is None else RunRecording(Path(path), name)


class NoRecording:
    """A run without ``--record``: every call does nothing."""

    def episode(self, env: Any, step: int) -> None: ...
    def observed(self, env: Any, step: int, obs: np.ndarray) -> None: ...
    def planned(self, env: Any, step: int, controller: Any) -> None: ...
    def stepped(self, env: Any, step: int, reward: float, info: dict[str, Any]) -> None: ...
    def close(self) -> None: ...


class RunRecording(NoRecording):
    """A run's steps, kept for its Rerun recording (see the module docstring): a step only
    copies its arrays (microseconds, ``benchmarks/recording_overhead.py``)."""

    def __init__(self, path: Path, name: str) -> None:
        global _started
        self.path, self.name = path, name
        self._writer, _started = _started or _start_writer(), None
        #: entity -> (steps, one array of rows per step)
        self._buffers: dict[str, tuple[list[int], list[np.ndarray]]] = {}
        self._boxes: dict[str, np.ndarray] = {}  # static: entity -> (2, 3) low, high

    def _add(self, entity: str, step: int, rows: Any) -> None:
        steps, values = self._buffers.setdefault(entity, ([], []))
        steps.append(step)
        values.append(np.array(rows, dtype=np.float32))  # a copy: the env reuses its arrays

    # ------------------------------------------------------------------ per step
    def episode(self, env: Any, step: int) -> None:
        """An episode starts at ``step``: the goal, the boxes once, the rod at rest."""
        if not self._boxes:
            limits = env.backend.limits
            self._boxes["world/workspace"] = np.array([limits.low, limits.high], dtype=float)
            for side, box in zip(("left", "right"), env.envelope.boxes, strict=True):
                if box is not None:
                    self._boxes[f"world/envelope/{side}"] = np.array(box, dtype=float)
        self._add("world/goal", step, np.asarray(env.goal)[None])
        self._add_state(env, step)

    def observed(self, env: Any, step: int, obs: np.ndarray) -> None:
        """What the controller observes at ``step``: the markers it saw and the hidden ones."""
        if getattr(env, "tracker", None) is None:
            return
        parts = env.split_observation(obs)
        visible = parts["visible"][:, 0] > 0.5
        self._add("world/markers/seen", step, parts["markers"][visible])
        self._add("world/markers/hidden", step, parts["markers"][~visible])
        cloud = getattr(env.tracker, "last_cloud", None)
        if cloud is not None:
            self._add("world/camera/cloud", step, cloud.points)

    def planned(self, env: Any, step: int, controller: Any) -> None:
        """A planner's plan from ``step``, when it re-planned there (a model planner only)."""
        stats = getattr(controller, "last_stats", {})
        plan_of = getattr(controller, "planned_path", None)
        if plan_of is None or not stats.get("replanned"):
            return
        commands, predicted = plan_of()
        if commands is None:
            return
        # the planned gripper path: the commands integrated from the grippers' positions
        speeds = commands[..., :3] * max_twist(env.task_spec)[:3] * env.task_spec.control_dt
        starts = env.backend.gripper_poses()[:, :3]
        paths = np.concatenate([starts[None], starts[None] + np.cumsum(speeds, axis=0)])
        moving = np.asarray(env.task.moving, dtype=bool)
        self._add("world/plan/grippers", step, paths.transpose(1, 0, 2)[moving])
        if predicted is not None:
            self._add("world/plan/predicted", step, predicted)

    def stepped(self, env: Any, step: int, reward: float, info: dict[str, Any]) -> None:
        """After the command of ``step``: the true state, error, reward and clip counts."""
        self._add_state(env, step)
        self._add("metrics/shape_error_mm", step, [info["shape_error_mm"]])
        self._add("metrics/reward", step, [reward])
        counts = env.envelope.counts
        self._add("envelope/clipped", step, [counts[name] for name in LIMITS])

    def _add_state(self, env: Any, step: int) -> None:
        state = env.state_parts()  # the last finite state, also when the step diverged
        self._add("world/rod", step, state["positions"][None])
        self._add("world/grippers", step, state["grippers"])

    def add_episode(self, episode: Any, start: int) -> int:
        """A saved episode (:class:`dlocli.data.Episode`) from ``start`` on the timeline:
        what a run's datasets hold (no plan, no envelope); the step after its last."""
        self._add("world/goal", start, np.asarray(episode.goal)[None])
        for t in range(len(episode.positions)):
            self._add("world/rod", start + t, episode.positions[t][None])
            self._add("world/grippers", start + t, episode.grippers[t])
            if episode.markers is not None and episode.visible is not None:
                seen = np.asarray(episode.visible[t], dtype=bool)
                self._add("world/markers/seen", start + t, episode.markers[t][seen])
                self._add("world/markers/hidden", start + t, episode.markers[t][~seen])
            if t > 0:
                error = shape_error_mm(episode.positions[t], episode.goal)
                self._add("metrics/shape_error_mm", start + t, [error])
                self._add("metrics/reward", start + t, [episode.rewards[t - 1]])
        return start + len(episode.positions)

    def add_prediction(
        self, recorded: np.ndarray, predicted: np.ndarray, held: np.ndarray, start: int
    ) -> int:
        """A recorded marker episode (T+1, M, 3) beside a model's open-loop prediction of it
        from ``start`` on the timeline, with the free markers' mean error (mm) per frame; the
        step after its last."""
        free = ~np.asarray(held, dtype=bool)
        errors = 1000.0 * np.linalg.norm(predicted[:, free] - recorded[:, free], axis=-1)
        for t in range(len(recorded)):
            self._add("world/recorded", start + t, recorded[t][None])
            self._add("world/predicted", start + t, predicted[t][None])
            self._add("metrics/prediction_error_mm", start + t, [errors[t].mean()])
        return start + len(recorded)

    # ------------------------------------------------------------------ to the file
    def payload(self, temporary: Path) -> dict[str, np.ndarray]:
        """What the writer reads: the path, name and limits' names, each box, and per entity
        its steps, its rows concatenated and how many rows each step has."""
        arrays = {"path": np.array(str(temporary)), "name": np.array(self.name),
                  "limits": np.array(LIMITS)}  # fmt: skip
        arrays |= {f"box:{entity}": box for entity, box in self._boxes.items()}
        for entity, (steps, values) in self._buffers.items():
            arrays[f"{entity}/steps"] = np.array(steps, dtype=np.int64)
            arrays[f"{entity}/lengths"] = np.array([len(v) for v in values], dtype=np.int64)
            arrays[f"{entity}/rows"] = np.concatenate(values)
        return arrays

    def close(self) -> None:
        """Hand the steps to the writer and move its file to the recording's path."""
        with ExitStack() as files:
            temporary = files.enter_context(atomic_path(self.path))
            sent = io.BytesIO()
            np.savez(sent, **self.payload(temporary))
            try:
                _, said = self._writer.communicate(sent.getvalue(), timeout=WRITE_TIMEOUT_S)
            except subprocess.TimeoutExpired:
                self._writer.kill()
                raise DloError(f"the recording {self.path} took over {WRITE_TIMEOUT_S:.0f} s "
                               "to write; the run's other results are kept") from None  # fmt: skip
            if self._writer.returncode != 0:
                lines = said.decode(errors="replace").strip().splitlines() or ["no message"]
                raise DloError(f"the recording {self.path} could not be written: {lines[-1]}")
