"""Closed-loop shape control (``dlo control``): drive the rod to a goal shape in the simulator.

From a seeded random start, a registered controller (default: the paper's gradient MPC through
a learned model) acts at every control step. The run directory holds:

=====================  ==========================================================
spec.json              the resolved :class:`ControlSpec` (controller options filled in)
metrics.csv            per step: shape error (mm), reward, latency (ms), controller stats
summary.json           ``initial_error_mm``, ``final_error_mm``, ``score`` (1 - final/initial:
                       the reference of doing nothing), ``best_error_mm``,
                       ``cumulative_reward``, ``latency_ms_median``, ``latency_ms_p95``,
                       ``steps`` and the run's context; with ``adapt_code``, ``code_picks``
                       (each re-pick's step, code and every candidate's score) and
                       ``code_final``
plots/error.png        shape error and controller latency over the steps
=====================  ==========================================================

With ``adapt_code`` (:class:`CodeAdapting`), metrics.csv's ``code`` column is the code each
step planned with (``code_pick_ms``: a re-pick's time). Plus, with ``video``, frames of the
rod and the goal from the backend's renderer, and with ``record``, a 3D recording of every
step for the Rerun viewer (:mod:`dlocli.runs.recording`).
"""

from __future__ import annotations

import csv
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, ClassVar

import numpy as np
from pydantic import Field

from dlocli.bridge.remote import CellLost, RemoteCell
from dlocli.bridge.spec import CellChoice
from dlocli.cancel import CancelToken
from dlocli.controllers.base import (
    Controller,
    LearningAgent,
    controller_spec,
    make_controller,
)
from dlocli.env.metrics import episode_result, shape_error_mm
from dlocli.env.observation import markers_of_state
from dlocli.env.rollout import rollout
from dlocli.env.shape_env import DLOShapeEnv, load_goal, make_env
from dlocli.errors import BadInput
from dlocli.events import Began, Callback, Event
from dlocli.io import atomic_path, prepare_run_dir, versions, write_json_atomic
from dlocli.limits import MAX_COUNT, MAX_PROCESSES
from dlocli.plots import plot_errors
from dlocli.registry import controllers
from dlocli.rundir import owned
from dlocli.runs.checks import check_apart_from_run_dir, check_video_path
from dlocli.runs.control_code import (
    CodeAdapting,
    check_adapt_code,
    code_follower,
    observe_with,
    use_cable_code,
)
from dlocli.runs.recording import check_record_path, open_recording
from dlocli.specs import Device, EnvSpec
from dlocli.threads import torch_threads, warn_if_oversubscribed


class ControlSpec(EnvSpec, CellChoice):
    """`dlo control`: closed-loop control to a goal shape. The goal is ``task.goal_file``."""

    moved: ClassVar[dict[str, str]] = {"model": "checkpoint", "steps": "task.episode_steps"}
    cli_flags: ClassVar[tuple[str, ...]] = (
        "task.goal_file", "checkpoint", "policy", "controller", "out", "backend.name",
        "task.name", "task.shapes", "task.episode_steps", "seed", "device", "threads", "video",
        "video_every", "record", "cell", "cell_timeout_s", "cell_keys",
        "task.envelope.max_linear_speed", "task.envelope.max_angular_speed",
        "task.envelope.max_linear_acceleration",
        "task.envelope.max_angular_acceleration", "task.envelope.stop_after_lost_s",
        "task.observation.kind", "task.observation.markers", "task.observation.noise_mm",
        "task.observation.latency_steps", "task.observation.dropout",
        "task.observation.occlusion_probability", "task.observation.gripper_markers",
        "task.observation.marker_arc_lengths", "task.control_dt", "cable", "adapt_code",
        "adapt_every", "adapt_window",
    )  # fmt: skip
    cli_required: ClassVar[tuple[str, ...]] = ("task.goal_file",)

    checkpoint: Path | None = Field(
        None, description="Trained dynamics model: a .pt file or a `dlo train` run directory."
    )
    cable: Path | None = Field(
        None,
        description="The recorded cable (its marker dataset from `dlo import`) whose learned "
        "code a model with cable codes plans with; without it, the mean of its codes.",
    )
    adapt_code: bool = Field(
        False,
        description="Infer the cable's code while it runs (a model with cable codes, a cable "
        "it may never have seen): start from the mean code, and every --adapt-every steps plan "
        "with the trained cable's code, or their mean, that best predicts the last "
        "--adapt-window observed frames (the pick of `dlo adapt`). Not with --cable.",
    )
    adapt_every: int = Field(
        50, gt=0, le=MAX_COUNT, description="--adapt-code: control steps between re-picks."
    )
    adapt_window: int = Field(
        100,
        ge=16,  # dlocli.models.code_follow.MIN_WINDOW (that module imports torch)
        le=MAX_COUNT,
        description="--adapt-code: the most recent observed frames a re-pick is scored on.",
    )
    policy: Path | None = Field(
        None,
        description="A trained sac or td3 policy: the `policy` directory of a `dlo bench` job "
        "(OUT/work/.../sac-s0/policy). Its pickled parts are never loaded.",
    )
    device: Device = "auto"
    threads: int = Field(
        1,
        ge=1,
        le=MAX_PROCESSES,
        description="Torch CPU threads while controlling (1 is fastest at the planners' "
        "small batches and robust on a shared CPU).",
    )
    controller: str = Field("mpc", description="Controller (see `dlo list`).")
    controller_options: dict[str, Any] = Field(
        default_factory=dict,
        description="The controller's options, fields of its spec (e.g. {iterations: 50, "
        "warm_start: false} for mpc); spec.json holds them all, resolved.",
    )
    video: Path | None = Field(
        None, description="Write frames of the rod and the goal to this .mp4 or .gif."
    )
    video_every: int = Field(
        2, gt=0, le=MAX_COUNT, description="Record every k-th control step in the video."
    )
    record: Path | None = Field(
        None,
        description="Write a 3D recording of every step (rod, goal, grippers, markers, plan, "
        "envelope, error) to this .rrd file for the Rerun viewer (the 'view' extra).",
    )
    out: Path = Field(Path("runs/control"), description="Run directory.")


# --------------------------------------------------------------------------- input checks
def check_inputs_used(spec: ControlSpec) -> None:
    """BadInput if the controller would ignore a given model or policy, or needs a policy
    it was not given (a learning agent never runs untrained here)."""
    cls = controllers.get(spec.controller)
    learns = issubclass(cls, LearningAgent)
    if learns and spec.policy is None:
        raise BadInput(
            f"controller '{spec.controller}' learns by interacting and is untrained here; pass "
            f"--policy DIR (saved by `dlo bench` in OUT/work/.../{spec.controller}-sSEED/policy)"
        )
    if spec.policy is not None and not learns:
        raise BadInput(f"--policy is for sac and td3, not '{spec.controller}'; drop it")
    if spec.cable is not None and spec.checkpoint is None:
        raise BadInput("--cable picks a learned model's cable code: pass --checkpoint or drop it")
    if spec.adapt_code and spec.cable is not None:
        raise BadInput(
            "--adapt-code infers the cable's code while it runs, --cable gives it: drop one"
        )
    if spec.adapt_code and spec.checkpoint is None:
        raise BadInput(
            "--adapt-code infers a learned model's cable code: pass --checkpoint or drop it"
        )
    if spec.checkpoint is not None and "model" not in cls.needs:
        raise BadInput(
            f"controller '{spec.controller}' uses no dynamics model; drop --checkpoint "
            "(or pass --controller mpc)"
        )


def load_control_model(spec: ControlSpec) -> Any:
    """The spec's model on its device, or None if there is none; BadInput if it learned at
    another control rate."""
    if spec.checkpoint is None:
        return None
    from dlocli.models.base import check_control_rate, resolve_device
    from dlocli.models.checkpoints import load_planning_model

    model = load_planning_model(spec.checkpoint, resolve_device(spec.device))
    check_control_rate(model, spec.task.control_dt, f"model {spec.checkpoint}", "the task runs",
                       "re-train it on data at {used_hz} Hz, or pass --control-dt {dt} (task."
                       "control_dt) to control at the model's rate")  # fmt: skip
    use_cable_code(model, spec)
    check_adapt_code(model, spec)
    return model


def check_model_segments(model: Any, spec: ControlSpec, n_segments: int) -> None:
    """BadInput if a rod model is for another segment count than the rod's (a marker model
    is checked by its view)."""
    found = None if model is None else model.n_segments
    if getattr(model, "form", "rod") == "rod" and found not in (None, n_segments):
        raise BadInput(
            f"model {spec.checkpoint} is for {found} segments but the rod has {n_segments}; "
            f"train one on {n_segments}-segment data or set backend.rod.n_segments={found}"
        )


def prepare(
    spec: ControlSpec, overwrite: bool = False, cancel: CancelToken | None = None
) -> tuple[DLOShapeEnv, Controller, ControlSpec]:
    """Check every input (outputs replaced only with ``overwrite``), build env (stopped by
    ``cancel`` between its physics steps) and controller; the spec comes back fully
    resolved."""
    if spec.task.goal_file is None:
        raise BadInput(
            "no goal: pass --goal shape.npy, a (N,3) float .npy in metres "
            "(make one with `dlo goal`)"
        )
    check_apart_from_run_dir(spec.video, "--video", spec.out)
    check_apart_from_run_dir(spec.record, "--record", spec.out)
    check_video_path(spec.video, overwrite)
    check_record_path(spec.record, overwrite)
    if spec.video is not None and spec.cell is not None:
        raise BadInput("--video needs the simulator in this process: drop --video or --cell")
    options = controller_spec(spec.controller, spec.controller_options, spec.backend.name)
    load_goal(spec.task.goal_file, spec.backend.rod.n_segments)  # refused before anything
    check_inputs_used(spec)
    controllers.get(spec.controller).warm_up()  # its slow imports before a cell is claimed
    model = load_control_model(spec)
    env = make_env(spec.backend, spec.task, goal=spec.task.goal_file, seed=spec.seed, cell=spec,
                   cancel=cancel)  # fmt: skip
    try:
        check_model_segments(model, spec, env.n_segments)
        observe_with(model, env)
        controller = make_controller(
            spec.controller, env, options=options, seed=spec.seed, model=model
        )
        if spec.policy is not None:
            controller.load_policy(spec.policy)
        if spec.adapt_code:
            controller = CodeAdapting(controller, env, code_follower(model, spec))
    except BaseException:
        env.close()
        raise
    resolved = spec.model_copy(
        update={"controller_options": options.model_dump() if options else {}}
    )
    return env, controller, resolved


# --------------------------------------------------------------------------- closed loop
def run_control(
    spec: ControlSpec,
    progress: Callback | None = None,
    *,
    overwrite: bool = False,
    cancel: CancelToken | None = None,
) -> dict[str, Any]:
    """Run the closed loop of ``spec``, write the run directory, return the summary.

    ``progress`` gets a Began of the episode's steps as its first step ends (the env reset),
    then an Event after every step, whose ``values`` are that step's record (step,
    shape_error_mm, reward, latency_ms and the controller's stats). ``cancel`` stops the env
    between its physics steps.
    """
    env, controller, spec = prepare(spec, overwrite, cancel)
    with owned(spec.out):
        return _run_closed_loop(env, controller, spec, progress, overwrite)


def _run_closed_loop(
    env: DLOShapeEnv,
    controller: Controller,
    spec: ControlSpec,
    progress: Callback | None,
    overwrite: bool,
) -> dict[str, Any]:
    try:
        out = prepare_run_dir(spec.out, overwrite)
        write_json_atomic(out / "spec.json", spec.model_dump(mode="json"))
        start = time.perf_counter()
        warn_if_oversubscribed(spec.threads, processes=1)
        with torch_threads(spec.threads):
            loop = closed_loop(env, controller, spec, progress)
        wall = time.perf_counter() - start
        counts = loop.measured | env.envelope.summary()
    finally:
        env.close()
    if loop.lost is not None and not loop.records:  # lost before the first step: nothing kept
        raise loop.lost.before_first_step()
    summary = summarise(loop.records, loop.initial_error, spec, loop.diverged, wall) | counts
    write_metrics(out / "metrics.csv", loop.records)
    plot_errors(out / "plots" / "error.png", loop.records, loop.initial_error, spec.controller)
    if spec.video is not None:
        write_video(spec.video, loop.frames, fps=env.metadata["render_fps"] / spec.video_every)
        summary["video"] = str(spec.video)
    if spec.record is not None:
        summary["recording"] = str(spec.record)
    if loop.lost is not None:
        summary["stopped"] = str(loop.lost)
    if isinstance(controller, CodeAdapting):
        summary |= controller.summary()
    write_json_atomic(out / "summary.json", summary)
    if loop.lost is not None:
        raise loop.lost
    return summary


def cell_counts(env: DLOShapeEnv, late_before: int = 0) -> dict[str, int]:
    """What a cell (``--cell``) counted: the controller's commands that came after their
    period's tick (a real-time cell; less ``late_before``, those up to the controller's first
    step: the reset's motion and settling, the first plan), and commands lost since the
    reset; nothing for a simulator in this process."""
    if not isinstance(env.backend, RemoteCell) or not env.backend.state:
        return {}
    state = env.backend.state
    return {"cell_late_steps": state["late"] - late_before,
            "cell_dropped_commands": state["dropped"]}  # fmt: skip


@dataclass
class Loop:
    """A closed loop's per-step records, initial shape error (mm), video frames, whether the
    rod diverged, the error that ended it early (a lost cell), if any, and what the summary
    reports of it beside: ``steps_wall_s`` (from the first act after the reset to the last
    step's end), the cell's counts, the tracking error."""

    records: list[dict[str, float]]
    initial_error: float
    frames: list[np.ndarray]
    diverged: bool
    lost: CellLost | None = None
    measured: dict[str, Any] = field(default_factory=dict)


def _returned_cost(controller: Controller) -> dict[str, float]:
    """A planner's re-plan's ``cost_final``: the predicted cost of the plan it returned."""
    returned = getattr(controller, "returned_cost", None)
    if returned is None or not controller.last_stats.get("replanned"):
        return {}
    cost = returned()
    return {} if cost is None else {"cost_final": cost}


def closed_loop(
    env: DLOShapeEnv, controller: Controller, spec: ControlSpec, progress: Callback | None
) -> Loop:
    """Step ``env`` with ``controller`` from a seeded random start (:func:`dlocli.env.rollout`)."""
    timed = _Recorded(controller, env, spec, open_recording(spec.record, spec.out.name))

    def on_step(step: int, reward: float, info: dict[str, Any]) -> None:
        timed.steps_ended = time.perf_counter()
        if step == 1:  # a real-time cell's late commands count from here: before, its clock
            # ran through the reset's motion and settling and the first plan
            timed.cell_late_before = cell_counts(env).get("cell_late_steps", 0)
        record = {
            "step": step,
            "shape_error_mm": float(info["shape_error_mm"]),
            "reward": float(reward),
            "latency_ms": controller.last_latency_ms,
            "cpu_ms": timed.cpu_ms,
            **controller.last_stats,
            **_returned_cost(controller),
        }
        timed.records.append(record)
        timed.recording.stepped(env, step, reward, info)
        if spec.video is not None and step % spec.video_every == 0:
            timed.frames.append(env.render())
        if progress is not None:
            if step == 1:  # the rod is reset: the steps' clock starts
                progress(Began("step", 0, spec.task.episode_steps))
            progress(Event("step", step, spec.task.episode_steps, record))

    try:
        episode = rollout(env, timed, spec.seed, lambda e: on_step(int(e.done), **e.values))
    except CellLost as lost:
        return Loop(timed.records, timed.initial_error, timed.frames, False, lost, timed.measured())
    finally:
        timed.recording.close()
    initial_error = float(shape_error_mm(episode.positions[0], episode.goal))
    return Loop(timed.records, initial_error, timed.frames, episode.diverged,
                measured=timed.measured() | tracking_error(env, episode))  # fmt: skip


def tracking_error(env: DLOShapeEnv, episode: Any) -> dict[str, float]:
    """Markers observed (tracked, or tracked in a camera's clouds) on a simulated rod: the mean
    distance (mm) of the free markers the controller was told from the true ones over the
    episode; nothing otherwise (a robot's state is its own tracker's: no truth to compare)."""
    layout = getattr(env, "marker_layout", None)
    remote = isinstance(env.backend, RemoteCell)
    if layout is None or episode.markers is None or (
            remote and (env.backend.cell is None or env.backend.cell.backend is None)):  # fmt: skip
        return {}
    true = markers_of_state(layout, episode.positions, episode.quaternions, episode.grippers)
    steps = min(len(true), len(episode.markers))
    error = np.linalg.norm(episode.markers[:steps] - true[:steps], axis=-1) * 1e3  # (T, M)
    return {"tracking_error_mm": round(float(error[:, ~layout.held].mean()), 3)}


class _Recorded:
    """``controller`` as a policy that also times its CPU use and keeps the run's records,
    video frames (the first frame right after the reset) and recording."""

    def __init__(
        self, controller: Controller, env: DLOShapeEnv, spec: ControlSpec, recording: Any
    ) -> None:
        self.controller, self.env, self.spec = controller, env, spec
        self.recording = recording
        self.records: list[dict[str, float]] = []
        self.frames: list[np.ndarray] = []
        self.cpu_ms = 0.0
        self.initial_error = float("nan")
        self.steps_started = self.steps_ended = 0.0
        self.cell_late_before = 0

    def reset(self, goal: np.ndarray) -> None:
        self.initial_error = float(shape_error_mm(self.env.backend.segment_positions(), goal))
        self.controller.reset(goal)
        self.recording.episode(self.env, 0)
        if self.spec.video is not None:
            self.frames.append(self.env.render())
        self.steps_started = time.perf_counter()

    def measured(self) -> dict[str, Any]:
        """The steps' wall seconds and the cell's counts, for the summary."""
        steps_s = max(self.steps_ended - self.steps_started, 0.0)  # 0 before the first step
        return cell_counts(self.env, self.cell_late_before) | {"steps_wall_s": round(steps_s, 2)}

    def act(self, obs: np.ndarray) -> np.ndarray:
        step = len(self.records)  # the observation's step
        self.recording.observed(self.env, step, obs)
        cpu = time.process_time()
        action = self.controller.act(obs)
        self.cpu_ms = 1000.0 * (time.process_time() - cpu)
        self.recording.planned(self.env, step, self.controller)
        return action


def summarise(
    records: list[dict[str, float]],
    initial_error: float,
    spec: ControlSpec,
    diverged: bool,
    wall_s: float,
) -> dict[str, Any]:
    """The run's summary: errors in mm, latencies in ms, and what produced them."""
    errors = np.array([r["shape_error_mm"] for r in records])
    latency = np.array([r["latency_ms"] for r in records])
    reward = float(sum(r["reward"] for r in records))
    result = episode_result(
        initial_error,
        errors[-1],
        reward,
        len(records),
        spec.task.episode_steps,
        diverged=diverged,
    )
    return {
        "initial_error_mm": round(initial_error, 3),
        "final_error_mm": round(float(errors[-1]), 3),
        "score": round(result["score"], 4),
        "best_error_mm": round(float(min(errors.min(), initial_error)), 3),
        "cumulative_reward": round(result["cumulative_reward"], 4),
        "latency_ms_median": round(float(np.median(latency)), 3),
        "latency_ms_p95": round(float(np.percentile(latency, 95)), 3),
        # steps whose command took longer than a control period to compute
        "late_steps": int(np.sum(latency > 1000.0 * spec.task.control_dt)),
        "cpu_ms_median": round(float(np.median([r["cpu_ms"] for r in records])), 3),
        "steps": len(records),
        "diverged": diverged,
        "controller": spec.controller,
        "goal": str(spec.task.goal_file),
        "checkpoint": None if spec.checkpoint is None else str(spec.checkpoint),
        "cable": None if spec.cable is None else str(spec.cable),
        "adapt_code": spec.adapt_code,
        "seed": spec.seed,
        # the closed loop: reset and settling, the controller's reset, every step (planning)
        "wall_s": round(wall_s, 2),
        "versions": versions(),
    }


# --------------------------------------------------------------------------- outputs
def write_metrics(path: Path, records: list[dict[str, float]]) -> None:
    """Per-step records as CSV (columns: the union of the records' keys, in first-seen order)."""
    columns = list(dict.fromkeys(key for record in records for key in record))
    with atomic_path(path) as tmp, open(tmp, "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=columns, restval="")
        writer.writeheader()
        writer.writerows(records)


def write_video(path: Path, frames: list[np.ndarray], fps: float) -> None:
    """Frames (H, W, 3) uint8 to a .gif or .mp4 (suffix checked by :func:`check_video_path`)."""
    import imageio.v2 as imageio

    with atomic_path(path) as tmp:
        if path.suffix == ".gif":
            imageio.mimwrite(tmp, frames, format="GIF", duration=1000.0 / fps, loop=0)
        else:
            imageio.mimwrite(tmp, frames, format="FFMPEG", fps=fps)
