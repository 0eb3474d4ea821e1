"""A run's 3D recording for the Rerun viewer (``--record RUN.rrd``; the ``view`` extra).

Everything is logged on one timeline, ``step`` (0: right after the reset, t: after the t-th
command), under these entities (metres, the simulator's world frame):

========================  ============================================================
world/rod                 the rod's true segment centres, a line strip
world/goal                the goal shape (logged at each episode's start)
world/grippers            the grippers' poses, small boxes
world/markers/seen        the markers as the controller saw them (markers observation)
world/markers/hidden      the markers the tracker did not see at that step (their report)
world/plan/grippers       a planner's planned gripper path (at each re-plan)
world/plan/predicted      its model's predicted shapes along the plan (at each re-plan)
world/workspace           the task's workspace box (static)
world/recorded|predicted  `dlo eval` on recorded markers: them and the model's open-loop
                          prediction (metrics/prediction_error_mm: its free markers' error)
world/envelope/left|right the envelope's gripper boxes, when set (static)
metrics/shape_error_mm    the shape error (mm), as in metrics.csv
metrics/reward            the step's reward
envelope/clipped          the envelope's counts of clipped commands so far, one per limit
========================  ============================================================

A recording is written beside the run (atomically: the file appears whole when the run
ends) and read afterwards with ``rerun RUN.rrd`` or Rerun's own API.
"""

from __future__ import annotations

import importlib.util
import os
import threading
from contextlib import ExitStack
from pathlib import Path
from typing import Any

import numpy as np

from dlocli.env.envelope import LIMITS
from dlocli.env.metrics import shape_error_mm
from dlocli.env.shapes import max_twist
from dlocli.errors import BadInput
from dlocli.extras import EXTRAS, require
from dlocli.io import atomic_path, check_writable

TIMELINE = "step"
APPLICATION = "dlocli"
#: RGB colours: the rod, the goal, the grippers, seen and hidden markers, the plan
ROD, GOAL, GRIPPERS = (70, 130, 230), (60, 200, 90), (240, 150, 40)
SEEN, HIDDEN, PLAN = (250, 220, 40), (150, 150, 150), (220, 60, 220)
GRIPPER_HALF_SIZE = 0.01  # m


def check_record_path(path: Path | None, overwrite: bool, flag: str = "--record") -> None:
    """BadInput unless ``path`` is None or a writable new (or, with ``overwrite``, any) .rrd
    file, with the ``view`` extra installed: checked before the run starts."""
    if path is None:
        return
    if importlib.util.find_spec(EXTRAS["view"]) is None:
        require("view", flag, "drop the flag")  # says which extra, in one line
    if Path(path).suffix != ".rrd":
        raise BadInput(f"{flag} {path} must end in .rrd (a Rerun recording)")
    check_writable(Path(path), flag, overwrite)
    _warm_up()


#: Rerun imported while the run builds its env and model (a second on a loaded CPU, much of
#: it in the first calls), so recording adds little to the run's time
_warming: threading.Thread | None = None


def _warm_up() -> None:
    global _warming
    if _warming is None:
        _warming = threading.Thread(target=_first_calls, name="rerun-import")
        _warming.start()


def _first_calls() -> None:
    try:
        import rerun as rr

        stream = rr.RecordingStream(APPLICATION)
        stream.save(os.devnull)
        stream.log("world", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
        columns = rr.LineStrips3D.columns(strips=[np.zeros((2, 3))]).partition([1])
        stream.send_columns("world/rod", [rr.TimeColumn(TIMELINE, sequence=[0])], columns)
        stream.disconnect()
    except Exception:  # noqa: BLE001 - the recording's own import reports it
        pass


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
    """Logs a run's control steps to a Rerun recording file (see the module docstring).

    A step only copies its arrays into per-entity buffers; :meth:`flush` sends them to Rerun
    as columns (one call per entity, not per step), which keeps a step's cost to microseconds
    (``benchmarks/recording_overhead.py``)."""

    def __init__(self, path: Path, name: str) -> None:
        import uuid

        if _warming is not None:
            _warming.join()
        import rerun as rr

        self.rr, self.path = rr, path
        self._files = ExitStack()
        temporary = self._files.enter_context(atomic_path(path))
        self.stream = rr.RecordingStream(APPLICATION, recording_id=uuid.uuid4())
        self.stream.save(temporary)
        self.stream.send_recording_name(name)
        self.stream.log("world", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
        #: entity -> (steps, one array of rows per step)
        self._buffers: dict[str, tuple[list[int], list[np.ndarray]]] = {}
        self._static_logged = False
        self._styled: set[str] = set()

    def _add(self, entity: str, step: int, rows: np.ndarray) -> None:
        steps, values = self._buffers.setdefault(entity, ([], []))
        steps.append(step)
        values.append(np.array(rows, dtype=np.float32))  # a copy: the env reuses its arrays

    # ------------------------------------------------------------------ per step
    def episode(self, env: Any, step: int) -> None:
        """An episode starts at ``step``: the goal, the boxes once, the rod at rest."""
        if not self._static_logged:
            rr, log = self.rr, self.stream.log
            limits = env.backend.limits
            log("world/workspace", _box(rr, limits.low, limits.high, (120, 120, 120)), static=True)
            for side, box in zip(("left", "right"), env.envelope.boxes, strict=True):
                if box is not None:
                    log(f"world/envelope/{side}", _box(rr, *box, (230, 80, 60)), static=True)
            self._static_logged = True
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
    def flush(self) -> None:
        """Send the buffered steps to the recording as columns."""
        rr = self.rr
        for entity, (steps, values) in self._buffers.items():
            if not steps:
                continue
            lengths = [len(v) for v in values]
            rows = np.concatenate(values)
            if entity.startswith(("metrics/", "envelope/")):
                columns = rr.Scalars.columns(scalars=rows)
            elif entity == "world/grippers":
                # ours are w x y z, Rerun's x y z w
                columns = rr.Boxes3D.columns(centers=rows[:, :3], quaternions=rows[:, [4, 5, 6, 3]])
            elif entity.startswith("world/markers/"):
                columns = rr.Points3D.columns(positions=rows)
            else:
                columns = rr.LineStrips3D.columns(strips=list(rows))
            if entity not in self._styled:  # what every step shares, once
                self.stream.log(entity, _style(rr, entity), static=True)
                self._styled.add(entity)
            indexes = [rr.TimeColumn(TIMELINE, sequence=steps)]
            self.stream.send_columns(entity, indexes=indexes, columns=columns.partition(lengths))
            steps.clear()
            values.clear()

    def close(self) -> None:
        """Send what is buffered, write the file's end and move it to its path."""
        self.flush()
        self.stream.flush()
        self.stream.disconnect()
        self._files.close()


def _style(rr: Any, entity: str) -> Any:
    """The colours and sizes of ``entity``'s every row."""
    if entity == "envelope/clipped":
        return rr.SeriesLines(names=list(LIMITS))
    if entity.startswith("metrics/"):
        return rr.SeriesLines(names=[entity.split("/")[-1]])
    if entity == "world/grippers":
        return rr.Boxes3D.from_fields(half_sizes=[[GRIPPER_HALF_SIZE] * 3], colors=[GRIPPERS])
    if entity.startswith("world/markers/"):
        return rr.Points3D.from_fields(colors=[SEEN if entity.endswith("seen") else HIDDEN])
    if entity.startswith("world/plan/") or entity == "world/predicted":
        return rr.LineStrips3D.from_fields(colors=[PLAN], radii=[0.001])
    return rr.LineStrips3D.from_fields(colors=[GOAL if entity == "world/goal" else ROD])


def _box(rr: Any, low: Any, high: Any, color: tuple[int, int, int]) -> Any:
    low, high = np.asarray(low, dtype=float), np.asarray(high, dtype=float)
    return rr.Boxes3D(mins=[low], sizes=[high - low], colors=[color], fill_mode="majorwireframe")
