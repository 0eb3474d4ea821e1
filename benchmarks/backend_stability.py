"""Backend stability and grip accuracy under gripper motion, for every registered backend.

    python benchmarks/backend_stability.py [--backends mujoco-flex,pybullet] [--episodes 10]
                                           [--steps 200] [--motion smooth|constant|sign]

Each episode starts from the rest state and moves both grippers (max 0.1 m/s, 0.5 rad/s):
``smooth`` is a random smooth velocity (an AR(1) process, correlation time ~10 control
steps, saturating at the limits); ``constant`` holds one random velocity for the whole
episode; ``sign`` holds full speed on every axis with random signs (the harshest: grippers
rotate ~2 rad and pull apart to the separation limit, so the rod is pulled taut).
Reported per backend: diverged episodes, and the held ends' errors against the grippers:
orientation of the end segments (degrees) and position of the rod end points (mm); for a rod
whose segments are not rigid (the flex rod's edges are held by a stiff constraint), their
stretch too (length / rest length - 1, over every segment and control step).
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from dlocli.backends import runnable_backends
from dlocli.backends.rotations import quat_multiply, quat_rotate
from dlocli.env.shape_env import make_backend
from dlocli.specs import BackendSpec

MAX_TWIST = np.array([0.1] * 3 + [0.5] * 3)  # m/s, rad/s


def velocities(motion: str, rng: np.random.Generator, steps: int) -> np.ndarray:
    """(steps, 2, 6) gripper twists in physical units."""
    if motion == "constant":
        unit = np.broadcast_to(rng.uniform(-1, 1, (2, 6)), (steps, 2, 6))
    elif motion == "sign":
        unit = np.broadcast_to(rng.choice([-1.0, 1.0], (2, 6)), (steps, 2, 6))
    else:
        unit = np.empty((steps, 2, 6))
        state = np.zeros((2, 6))
        for t in range(steps):
            state = np.clip(0.9 * state + 0.3 * rng.uniform(-1, 1, (2, 6)), -1, 1)
            unit[t] = state
    return unit * MAX_TWIST


def grip_errors(backend) -> tuple[np.ndarray, np.ndarray]:
    """(2,) end-segment orientation errors (deg) and (2,) end-point position errors (mm)."""
    pos, quat = backend.segment_positions(), backend.segment_quaternions()
    grip = backend.gripper_poses()
    held = quat[[0, -1]]
    relative = quat_multiply(held * np.array([1.0, -1, -1, -1]), grip[:, 3:])
    angle = np.degrees(2 * np.arccos(np.clip(np.abs(relative[:, 0]), 0.0, 1.0)))
    half = 0.5 * backend.rod.segment_length * quat_rotate(held, np.array([1.0, 0.0, 0.0]))
    ends = np.stack([pos[0] - half[0], pos[-1] + half[1]])
    return angle, 1e3 * np.linalg.norm(ends - grip[:, :3], axis=1)


def run(name: str, motion: str, episodes: int, steps: int, seed: int) -> str:
    backend = make_backend(BackendSpec(name=name))
    rng = np.random.default_rng(seed)
    diverged, angles, offsets, stretch = 0, [], [], []
    stretches = hasattr(backend, "edge_stretch")
    start = time.perf_counter()
    for _ in range(episodes):
        backend.reset(0)
        for twist in velocities(motion, rng, steps):
            if not backend.step(twist):
                diverged += 1
                break
            angle, offset = grip_errors(backend)
            angles.append(angle)
            offsets.append(offset)
            if stretches:
                stretch.append(backend.edge_stretch())
    backend.close()
    angles, offsets = np.concatenate(angles), np.concatenate(offsets)
    edges = ""
    if stretches:
        pct = 100 * np.concatenate(stretch)
        edges = (
            f"edge stretch median {np.median(pct):.3f} 99th {np.percentile(pct, 99):.3f} "
            f"max {pct.max():.3f} %  "
        )
    return (
        f"{name:11} {motion:8} diverged {diverged}/{episodes}  "
        f"end orientation median {np.median(angles):.2f} max {angles.max():.2f} deg  "
        f"end position median {np.median(offsets):.2f} max {offsets.max():.2f} mm  {edges}"
        f"({time.perf_counter() - start:.0f} s)"
    )


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawTextHelpFormatter
    )
    parser.add_argument("--backends", default=",".join(runnable_backends()))
    parser.add_argument("--motion", default="smooth", choices=["smooth", "constant", "sign"])
    parser.add_argument("--episodes", type=int, default=10)
    parser.add_argument("--steps", type=int, default=200)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    for name in args.backends.split(","):
        print(run(name, args.motion, args.episodes, args.steps, args.seed), flush=True)


if __name__ == "__main__":
    main()
