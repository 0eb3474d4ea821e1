"""`dlo sample`: simulated recordings in the forms real data come in, so every documented
command has an input on a fresh clone: a recorded cable for `dlo import` and `dlo calibrate`,
a depth camera's clouds for `dlo track`.

A recording is one episode of the spec's task on its rod: the env's start for the stream
``(seed, index)``, both grippers driven straight towards the poses that made the episode's
goal at the task's speeds (:func:`~dlocli.tracking.measure.policy_action`, "oracle"), the
rod swinging and settling after; the rod is controlled at the recording's frame rate and
every control step is a frame. A cable records ``task.observation``'s markers (default: 10
along the rod and one on each gripper behind it, so two held at each end as DEFORM's arms
hold its cables) with motion-capture noise; clouds record the camera of
``task.observation.camera`` and, per frame, where the robot holds the cable's ends and the
gripper markers (what `dlo track` needs with its default ``--gripper-markers``).

Folder (every file written atomically)::

    spec.json                 the resolved SampleSpec (rate and control period filled in)
    train/take_NNN.pkl|.csv   a cable: (frames, 3, markers) pickled lists, or a CSV
    train/take_NNN.npz        clouds: :mod:`dlocli.tracking.frames` sequences
    eval/...                  the same, for evaluation
    summary.json              counts, and the command that reads the folder

Over an earlier sample (``--overwrite``) the recordings it left and this run did not replace
are deleted once this run's are written, so `dlo import` reads this run's alone.
"""

from __future__ import annotations

import pickle
import shlex
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from dlocli.cancel import CancelToken
from dlocli.data.markers import DEFAULT_RATE_HZ as IMPORT_RATE_HZ
from dlocli.env.observation import MM, MarkerLayout
from dlocli.env.rollout import stream_seed
from dlocli.env.shape_env import DLOShapeEnv, make_env
from dlocli.errors import BadInput
from dlocli.events import Began, Callback, Event, ignore
from dlocli.io import (
    atomic_path,
    prepare_run_dir,
    remove_unwritten,
    write_json_atomic,
    write_text_atomic,
)
from dlocli.limits import refuse_unless_fits
from dlocli.recorded_cables.spec import UNITS
from dlocli.rundir import owned
from dlocli.runs.checks import check_registered
from dlocli.runs.sample_spec import DEFAULT_RATE_HZ, SampleSpec
from dlocli.specs import ObservationSpec
from dlocli.tracking.camera import DepthCamera
from dlocli.tracking.frames import save_frames
from dlocli.tracking.measure import env_layout, policy_action, robot_held, true_markers
from dlocli.tracking.spec import CameraSpec, TrackSpec


def resolved(spec: SampleSpec) -> SampleSpec:
    """``spec`` with its frame rate filled in and the task controlled at it for the
    recordings' length; BadInput if a recording would not fit in memory."""
    rate = spec.rate_hz or DEFAULT_RATE_HZ[spec.kind]
    steps = max(1, round(spec.seconds * rate))
    task = spec.task.model_dump()
    task.update(control_dt=1.0 / rate, episode_steps=steps)
    if spec.kind == "clouds":
        camera = spec.task.observation.camera or CameraSpec()
        task["observation"]["camera"] = {**camera.model_dump(), "rate_hz": rate}
        pixels = camera.width * camera.height
        refuse_unless_fits("a recording's clouds", 12.0 * pixels * (steps + 1),
                           "lower --seconds or the camera's pixels")  # fmt: skip
    return SampleSpec.model_validate({**spec.model_dump(), "rate_hz": rate, "task": task})


def run_sample(
    spec: SampleSpec,
    overwrite: bool = False,
    progress: Callback | None = None,
    cancel: CancelToken | None = None,
) -> dict[str, Any]:
    """Write ``spec.train`` + ``spec.eval`` simulated recordings into ``spec.out`` (module
    docstring); return the summary. ``progress`` gets a Began (unit "recording"), then an
    Event after each recording (``values``: its ``split`` and ``file``). ``cancel`` stops it
    between frames: the recording under way is dropped, those finished are kept with the spec
    and a summary of them marked ``stopped``, before the stop is raised again (none finished:
    nothing is written, an earlier run's files there are left as they were)."""
    check_registered(spec)
    spec = resolved(spec)
    progress, cancel = progress or ignore, cancel or CancelToken()
    env = make_env(spec.backend, spec.task, goal="random", seed=spec.seed, render_mode=None)
    try:
        layout = env_layout(env, _recorded(spec))  # a bad layout is refused before writing
        with owned(spec.out):
            out = prepare_run_dir(spec.out, overwrite)
            made: dict[str, list[Path]] = {"train": [], "eval": []}
            try:
                _write_recordings(env, spec, layout, out, made, progress, cancel)
            except KeyboardInterrupt as stop:  # the recordings finished are kept
                if any(made.values()):
                    remove_unwritten(out, [f"{split}/take_*" for split in made], _written(made))
                    summary = _summary(spec, layout.held, made, type(stop).__name__)
                    write_json_atomic(out / "summary.json", summary)
                raise
            remove_unwritten(out, [f"{split}/take_*" for split in made], _written(made))
            summary = _summary(spec, layout.held, made)
            write_json_atomic(out / "summary.json", summary)
    finally:
        env.close()
    return summary


def _recorded(spec: SampleSpec) -> ObservationSpec:
    """The markers a recording holds: a cable's, or where the robot holds the cable whose
    clouds are recorded (its ends and the gripper markers, and one between them that the
    layout asks for and the recording leaves out)."""
    if spec.kind == "cable":
        return spec.task.observation
    behind = spec.task.observation.gripper_markers
    arcs = (-behind, 0.0, 0.5, 1.0, 1.0 + behind) if behind > 0 else (0.0, 0.5, 1.0)
    return ObservationSpec(marker_arc_lengths=arcs, gripper_markers=0.0)


def _write_recordings(
    env: DLOShapeEnv,
    spec: SampleSpec,
    layout: MarkerLayout,
    out: Path,
    made: dict[str, list[Path]],
    progress: Callback,
    cancel: CancelToken,
) -> None:
    """Each recording into ``out`` (``made`` lists them per split), the spec before the
    first; ``cancel`` checked before the first and at every frame."""
    total = spec.train + spec.eval
    progress(Began("recording", 0, total))
    cancel.raise_if_cancelled()
    write_json_atomic(out / "spec.json", spec.model_dump(mode="json"))
    write = _write_cable if spec.kind == "cable" else _write_clouds
    for index in range(total):
        split = "train" if index < spec.train else "eval"
        path = write(env, spec, layout, index, out / split / f"take_{index:03d}", cancel)
        made[split].append(path)
        progress(Event("recording", index + 1, total, {"split": split, "file": path.name}))


def _written(made: dict[str, list[Path]]) -> set[Path]:
    """The recordings this run wrote, all splits."""
    return {path for paths in made.values() for path in paths}


def _episode(
    env: DLOShapeEnv,
    spec: SampleSpec,
    index: int,
    record: Callable[[int], None],
    cancel: CancelToken,
) -> None:
    """Run recording ``index``'s episode, calling ``record(step)`` at every frame
    (``cancel`` checked before each)."""
    env.reset(seed=stream_seed(spec.seed, index))
    rng = np.random.default_rng([spec.seed, index, 7])
    for step in range(spec.task.episode_steps + 1):
        cancel.raise_if_cancelled()
        record(step)
        if step < spec.task.episode_steps:
            env.step(policy_action(env, "oracle", rng))


def _write_cable(
    env: DLOShapeEnv,
    spec: SampleSpec,
    layout: MarkerLayout,
    index: int,
    path: Path,
    cancel: CancelToken,
) -> Path:
    frames: list[np.ndarray] = []
    _episode(env, spec, index, lambda step: frames.append(true_markers(env, layout)), cancel)
    markers = np.stack(frames)
    noise = np.random.default_rng([spec.seed, index, 11]).standard_normal(markers.shape)
    markers = (markers + spec.noise_mm * MM * noise) / UNITS[spec.units]
    if not np.isfinite(markers).all():
        raise BadInput(f"recording {index} diverged; lower --seconds or pick another --seed")
    if spec.format == "pkl":  # DEFORM's: a plain nested list (frames, 3, markers)
        path = path.with_suffix(".pkl")
        data = pickle.dumps(markers.transpose(0, 2, 1).tolist(), protocol=4)
        with atomic_path(path) as tmp:
            tmp.write_bytes(data)
        return path
    path = path.with_suffix(".csv")
    header = ["frame", "time"] + [f"m{j}_{a}" for j in range(markers.shape[1]) for a in "xyz"]
    digits = {"m": 6, "cm": 4, "mm": 3}[spec.units]  # micrometres
    dt = spec.task.control_dt
    rows = [",".join(header)] + [
        ",".join([str(k), f"{k * dt:.6f}", *(f"{v:.{digits}f}" for v in frame.ravel())])
        for k, frame in enumerate(markers)
    ]
    write_text_atomic(path, "\n".join(rows) + "\n")
    return path


def _write_clouds(
    env: DLOShapeEnv,
    spec: SampleSpec,
    layout: MarkerLayout,
    index: int,
    path: Path,
    cancel: CancelToken,
) -> Path:
    camera_spec = spec.task.observation.camera
    assert camera_spec is not None  # resolved() sets it
    camera = DepthCamera(camera_spec, env.backend.rod.length)
    rng = np.random.default_rng([spec.seed, index, 13])
    frames, held = [], []

    def record(step: int) -> None:
        frames.append(camera.capture(env.backend, rng, time=step * spec.task.control_dt))
        held.append(robot_held(env, layout))

    _episode(env, spec, index, record, cancel)
    if len(frames[0].points) == 0:
        raise BadInput(
            f"the camera sees none of the cable in recording {index}; point it at the rod "
            "(task.observation.camera position and look_at)"
        )
    path = path.with_suffix(".npz")
    save_frames(path, frames, np.stack(held))
    return path


def _summary(
    spec: SampleSpec, held: np.ndarray, made: dict[str, list[Path]], stopped: str | None = None
) -> dict[str, Any]:
    """Counts (``made``: the recordings written per split), and the command that reads the
    folder as it was written (``held``: the recorded markers the grippers hold; ``stopped``:
    what ended the run before every recording was written)."""
    out = str(spec.out)
    markers: int | None = None
    if spec.kind == "cable":
        reads = ["dlo", "import", "--source", out]
        if spec.format == "pkl" and spec.rate_hz != IMPORT_RATE_HZ:
            reads += ["--rate-hz", f"{spec.rate_hz:g}"]
        if spec.units != "m":
            reads += ["--units", spec.units]
        indices = np.flatnonzero(held)
        markers = len(held)
        if indices.tolist() != [0, 1, markers - 2, markers - 1]:  # not DEFORM's two per end
            reads += ["--held", ",".join(str(i - markers if i > markers // 2 else i)
                                         for i in indices)]  # fmt: skip
    else:
        reads = ["dlo", "track", "--source", out]
        behind = spec.task.observation.gripper_markers
        if behind != TrackSpec.model_fields["gripper_markers"].default:
            reads += ["--gripper-markers", f"{behind:g}"]
        if spec.backend.rod.length != TrackSpec.model_fields["length"].default:
            reads += ["--length", f"{spec.backend.rod.length:g}"]
    summary: dict[str, Any] = {
        "kind": spec.kind,
        "train_recordings": len(made["train"]),
        "eval_recordings": len(made["eval"]),
        "frames_per_recording": spec.task.episode_steps + 1,
        "rate_hz": spec.rate_hz,
        "backend": spec.backend.name,
        "next": shlex.join([*reads, "--out", "runs/NAME"]),
        "out": out,
    }
    if markers is not None:
        summary["markers"] = markers
    if stopped is not None:
        summary["stopped"] = stopped
    return summary
