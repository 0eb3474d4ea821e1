"""How well the tracker follows a simulated cable: an episode of the env watched by the
depth camera, each frame's tracked markers against the simulator's true ones.

The episode is the bench's: the env's start and goal for a seed, the grippers driven
straight towards the poses that made the goal ("oracle") or moved at random. The robot
knows its grippers: the held markers are placed from their poses, as the markers
observation does; the error is measured on the free markers, which the tracker finds.
"""

from __future__ import annotations

from dataclasses import dataclass
from time import perf_counter

import numpy as np

from dlocli.env.observation import MarkerLayout, held_markers, marker_layout, markers_of_state
from dlocli.env.shape_env import DLOShapeEnv
from dlocli.env.shapes import gripper_twists_towards, max_twist
from dlocli.specs import ObservationSpec
from dlocli.tracking.camera import DepthCamera
from dlocli.tracking.tracker import CableTracker

MM = 1e-3


@dataclass
class HiddenSpan:
    """A part of the cable out of view: the segments from ``first`` to ``last`` (included)
    hidden in the frames from ``start`` for ``frames`` frames."""

    first: int
    last: int
    start: int
    frames: int

    def hides(self, frame: int) -> bool:
        return self.start <= frame < self.start + self.frames


@dataclass
class TrackedEpisode:
    """Per frame (F): ``errors`` (F, free markers) in mm, ``points`` (F,) cloud sizes,
    ``visible`` (F, M) the tracker's visibility flags, ``hidden`` (F,) whether a span was
    hidden, and ``seconds`` (F,) the tracker's time per frame."""

    errors: np.ndarray
    points: np.ndarray
    visible: np.ndarray
    hidden: np.ndarray
    seconds: np.ndarray


def env_layout(env: DLOShapeEnv, observation: ObservationSpec | None = None) -> MarkerLayout:
    """The markers of ``observation`` (default: the markers observation's) on the env's rod."""
    backend = env.backend
    held = (bool(backend.moving[0]), bool(backend.moving[1]))
    return marker_layout(observation or ObservationSpec(), backend.rod.length,
                         backend.n_segments, held)  # fmt: skip


def true_markers(env: DLOShapeEnv, layout: MarkerLayout) -> np.ndarray:
    """(M,3) where the markers are now, from the simulator's state."""
    backend = env.backend
    return markers_of_state(layout, backend.segment_positions(),
                            backend.segment_quaternions(), backend.gripper_poses())  # fmt: skip


def robot_held(env: DLOShapeEnv, layout: MarkerLayout) -> np.ndarray:
    """(H,3) the held markers where the robot's gripper poses put them."""
    return held_markers(layout, env.backend.gripper_poses())[layout.held]


def policy_action(env: DLOShapeEnv, policy: str, rng: np.random.Generator) -> np.ndarray:
    """The next action of "oracle" (towards the goal's gripper poses) or "random"."""
    if policy == "random":
        return rng.uniform(-1.0, 1.0, env.action_space.shape)
    twists = gripper_twists_towards(env.backend.gripper_poses(), env.goal_gripper_poses,
                                    env.task_spec, env.task.moving)  # fmt: skip
    return env.task.from_grippers(twists / max_twist(env.task_spec))


def track_episode(
    env: DLOShapeEnv,
    camera: DepthCamera,
    tracker: CableTracker,
    layout: MarkerLayout,
    seed: int,
    steps: int,
    policy: str = "oracle",
    hidden: HiddenSpan | None = None,
) -> TrackedEpisode:
    """Run ``steps`` control steps from ``env.reset(seed)``, a camera frame at its rate,
    and track every frame; the errors of the free markers against the true ones."""
    env.reset(seed=seed)
    rng = np.random.default_rng([seed, 7])
    every = max(1, round(1.0 / (camera.spec.rate_hz * env.task_spec.control_dt)))
    segments = np.zeros(env.backend.n_segments, dtype=bool)
    if hidden is not None:
        segments[hidden.first : hidden.last + 1] = True
    rows: dict[str, list] = {k: [] for k in ("errors", "points", "visible", "hidden", "seconds")}
    for step in range(steps + 1):
        if step % every == 0:
            index = step // every
            frame = camera.capture(env.backend, rng, step * env.task_spec.control_dt)
            covered = hidden is not None and hidden.hides(index)
            if covered:
                frame = frame.without_segments(segments)
            start = perf_counter()
            report = (tracker.start if index == 0 else tracker.step)(frame, robot_held(env, layout))
            rows["seconds"].append(perf_counter() - start)
            error = np.linalg.norm(report.markers - true_markers(env, layout), axis=1) / MM
            rows["errors"].append(error[~layout.held])
            rows["points"].append(len(frame.points))
            rows["visible"].append(report.visible)
            rows["hidden"].append(covered)
        if step < steps:
            env.step(policy_action(env, policy, rng))
    return TrackedEpisode(**{k: np.array(v) for k, v in rows.items()})
