"""The depth camera and the tracker on simulated episodes (issue 54, parts 1 and 2).

    python benchmarks/tracking.py [--backends mujoco,pybullet] [--seeds 3] [--steps 200]
                                  [--marker-model CHECKPOINT]

1. Ray casting: milliseconds per frame of ``DepthCamera.capture`` (rays, table, faults) by
   resolution and backend, and the cable points a frame holds, at the start of seed 0.
2. Tracking error per free marker (mm, mean and 95th percentile over frames, markers and
   seeds) on the paper-scale single task: the env's random start and goal for each seed,
   the right gripper driven straight to the goal's pose (``oracle``), 200 control steps,
   the camera at its rate; the held markers are placed from the gripper poses. Conditions:
   clean (no noise, stray points or invalid pixels, the grippers out of view), noisy (the
   camera's defaults), grippers (clean, the grippers in view, hiding the cable's ends), and
   hidden (clean, segments 7 to 13 of 20, a third of the cable, out of view for 1 s from
   t = 1 s; also its error over the hidden frames alone).
3. Frames per second of the tracker alone at 2,000 points, on one thread: a noisy camera of
   800 x 600 pixels, each frame's cloud drawn down to 2,000 points.

The trackers predict with the cable's continuity, or with ``--marker-model``, a marker model
trained on the same markers at the camera's rate (``MarkerModelPrior``).
"""

from __future__ import annotations

import os

for _name in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
    os.environ.setdefault(_name, "1")  # one core: before numpy starts its BLAS threads

import argparse  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

from dlocli.env.shape_env import make_env  # noqa: E402
from dlocli.specs import TaskSpec  # noqa: E402
from dlocli.tracking.camera import CloudFrame, DepthCamera  # noqa: E402
from dlocli.tracking.measure import (  # noqa: E402
    HiddenSpan,
    env_layout,
    policy_action,
    robot_held,
    track_episode,
)
from dlocli.tracking.model_prior import MarkerModelPrior  # noqa: E402
from dlocli.tracking.spec import CameraSpec  # noqa: E402
from dlocli.tracking.tracker import CableTracker  # noqa: E402

RESOLUTIONS = ((160, 120), (320, 240), (640, 480))
HIDDEN = HiddenSpan(first=7, last=13, start=25, frames=25)  # 1 s at 25 frames per second


def cameras(rod_length: float) -> dict[str, DepthCamera]:
    clean = CameraSpec().clean()
    return {
        "clean": DepthCamera(clean.model_copy(update={"see_grippers": False}), rod_length),
        "noisy": DepthCamera(CameraSpec(), rod_length),
        "grippers": DepthCamera(clean, rod_length),
        "hidden": DepthCamera(clean.model_copy(update={"see_grippers": False}), rod_length),
    }


def ray_times(env, repeats: int = 10) -> list[str]:
    env.reset(seed=0)
    rows = []
    for width, height in RESOLUTIONS:
        camera = DepthCamera(CameraSpec(width=width, height=height), env.backend.rod.length)
        rng = np.random.default_rng(0)
        frame = camera.capture(env.backend, rng)
        seconds = []
        for _ in range(repeats):
            start = time.perf_counter()
            camera.capture(env.backend, rng)
            seconds.append(time.perf_counter() - start)
        rows.append(f"  {width}x{height:<4} {1e3 * np.median(seconds):8.1f} ms "
                    f"{len(frame.points):6d} points")  # fmt: skip
    return rows


def errors(env, condition: str, camera: DepthCamera, seeds: int, steps: int, model=None) -> str:
    layout = env_layout(env)
    runs = []
    for seed in range(seeds):
        prior = None if model is None else MarkerModelPrior.load(model, layout.held)
        tracker = CableTracker.for_layout(layout, env.backend.rod.radius, prior=prior)
        hidden = HIDDEN if condition == "hidden" else None
        runs.append(track_episode(env, camera, tracker, layout, seed, steps, hidden=hidden))
    every = np.concatenate([run.errors.ravel() for run in runs])
    line = f"  {condition:9s} {every.mean():7.2f} {np.percentile(every, 95):7.2f}"
    points = np.mean([run.points.mean() for run in runs])
    seconds = np.median(np.concatenate([run.seconds[1:] for run in runs]))
    line += f" {points:7.0f} {1e3 * seconds:9.1f}"
    if condition == "hidden":
        during = np.concatenate([run.errors[run.hidden].ravel() for run in runs])
        line += f"   hidden frames: mean {during.mean():.2f}, p95 {np.percentile(during, 95):.2f}"
    return line


def frames_at(env, camera: DepthCamera, count: int, points: int, seed: int = 0):
    """``count`` frames of an oracle episode, each drawn down to ``points`` points, with
    the held markers where the robot put them."""
    layout = env_layout(env)
    env.reset(seed=seed)
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(count):
        frame = camera.capture(env.backend, rng)
        keep = rng.choice(len(frame.points), size=points, replace=len(frame.points) < points)
        out.append((CloudFrame(frame.points[keep], frame.extrinsics, frame.intrinsics),
                    robot_held(env, layout)))  # fmt: skip
        for _ in range(2):  # 25 frames per second at 50 control steps per second
            env.step(policy_action(env, "oracle", rng))
    return layout, out


def frames_per_second(env, points: int = 2000, count: int = 60) -> str:
    camera = DepthCamera(CameraSpec(width=800, height=600), env.backend.rod.length)
    layout, frames = frames_at(env, camera, count, points)
    tracker = CableTracker.for_layout(layout, env.backend.rod.radius)
    tracker.start(*frames[0])
    wall, cpu = [], []
    for frame, held in frames[1:]:
        w, c = time.perf_counter(), time.process_time()
        tracker.step(frame, held)
        wall.append(time.perf_counter() - w)
        cpu.append(time.process_time() - c)
    return (f"  {points} points, {count - 1} frames: median {1e3 * np.median(wall):.1f} ms "
            f"(cpu {1e3 * np.median(cpu):.1f} ms), p95 {1e3 * np.percentile(wall, 95):.1f} ms "
            f"-> {1.0 / np.median(wall):.0f} frames per second "
            f"({1.0 / np.median(cpu):.0f} by cpu time)")  # fmt: skip


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--backends", default="mujoco,pybullet")
    parser.add_argument("--seeds", type=int, default=3)
    parser.add_argument("--steps", type=int, default=200)
    parser.add_argument("--marker-model", type=Path, default=None, help="the trackers' prior")
    args = parser.parse_args()
    for backend in args.backends.split(","):
        env = make_env(backend, TaskSpec(name="single", goal="random"), seed=0,
                       render_mode=None)  # fmt: skip
        print(f"{backend}: camera capture per frame (rays, table, faults), start of seed 0")
        print("\n".join(ray_times(env)))
        print(f"{backend}: tracking error of the free markers, mm ({args.seeds} seeds x "
              f"{args.steps} steps, oracle motion, 160x120 at 25 Hz)")  # fmt: skip
        print(f"  {'condition':9s} {'mean':>7s} {'p95':>7s} {'points':>7s} {'track ms':>9s}")
        for condition, camera in cameras(env.backend.rod.length).items():
            line = errors(env, condition, camera, args.seeds, args.steps, args.marker_model)
            print(line, flush=True)
        print(f"{backend}: the tracker alone, one thread")
        print(frames_per_second(env))
        env.close()


if __name__ == "__main__":
    main()
