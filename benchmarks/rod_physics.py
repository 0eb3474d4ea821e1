"""The rod against textbook mechanics, per backend: simulated / reference at N = 20.

References are computed here: Euler-Bernoulli's self-weight cantilever ``w L^4 / 8 EI``; the
large-deflection cantilever under its own weight (the elastica ``EI theta'' = -w (L - s) cos
theta``, theta(0) = 0, theta'(L) = 0, solved with scipy's ``solve_bvp``) at load parameters
``alpha = w L^3 / EI`` in {0.5, 1, 2, 5, 10} (set through the density); and the first
bending frequency ``1.875^2 / 2 pi sqrt(EI / rho A L^4)`` with every damping off, from the
free lateral (y) vibration of the tip, perpendicular to gravity. Every check uses a 0.2 m
rod of the paper's material held by the left gripper only (a cantilever) through the public
backend spec. Tip load and twist need loads the backend contract does not offer (yet).

    python benchmarks/rod_physics.py > benchmarks/results/rod_physics.txt
"""

from __future__ import annotations

import math
import sys

import numpy as np
from scipy.integrate import solve_bvp

from dlocli.backends.rotations import quat_rotate
from dlocli.env.shape_env import make_backend
from dlocli.registry import backends
from dlocli.specs import BackendSpec, RodSpec

GRAVITY = 9.81
LENGTH = 0.2  # m: the paper rod's self-weight deflection is small at this length
SEGMENTS = 20
ALPHAS = (0.5, 1.0, 2.0, 5.0, 10.0)
SETTLE_STEPS = 500  # control steps (10 s) at most to come to rest
REST_SPEED = 1e-5  # m/s of the tip
VIBRATION_SECONDS = 2.0
UNDAMPED_DT = {"mujoco": 5e-5}  # s: undamped, MuJoCo's explicit elasticity at 1 cm segments
KICK = 0.05  # m/s of the clamp along y for one control step: excites the first mode
FIRST_MODE = 1.8751  # beta_1 L of a clamped-free beam


# ----------------------------------------------------------------------------- references
def self_weight_deflection(rod: RodSpec) -> float:
    """Euler-Bernoulli tip deflection (m) of a cantilever under its own weight."""
    return rod.density * rod.area * GRAVITY * rod.length**4 / (8 * rod.bending_stiffness)


def elastica_deflection(alpha: float, length: float) -> float:
    """Tip drop (m) of a cantilever of load parameter ``w L^3 / EI``, solved as a BVP."""

    def slope(s: np.ndarray, y: np.ndarray) -> np.ndarray:  # y = (theta, theta'), s in L
        return np.vstack([y[1], -alpha * (1 - s) * np.cos(y[0])])

    def ends(start: np.ndarray, end: np.ndarray) -> np.ndarray:
        return np.array([start[0], end[1]])

    s = np.linspace(0, 1, 201)
    solution = solve_bvp(slope, ends, s, np.zeros((2, s.size)), tol=1e-8, max_nodes=100000)
    if not solution.success:
        raise RuntimeError(f"elastica alpha={alpha}: {solution.message}")
    fine = np.linspace(0, 1, 20001)
    drop = np.sin(solution.sol(fine)[0])
    return float(length * np.sum(0.5 * (drop[1:] + drop[:-1])) * (fine[1] - fine[0]))


def first_bending_frequency(rod: RodSpec) -> float:
    """Hz, clamped-free Euler-Bernoulli beam."""
    mass_per_length = rod.density * rod.area
    return (
        FIRST_MODE**2
        / (2 * math.pi)
        * math.sqrt(rod.bending_stiffness / (mass_per_length * rod.length**4))
    )


# ----------------------------------------------------------------------------- simulation
def tip(backend) -> np.ndarray:
    """End point (m) of the free end: the last segment's centre plus half a segment."""
    axis = quat_rotate(backend.segment_quaternions()[-1], np.array([1.0, 0.0, 0.0]))
    return backend.segment_positions()[-1] + 0.5 * backend.rod.segment_length * axis


def settled_tip_drop(name: str, rod: RodSpec) -> float:
    """Clamp height minus tip height (m) of the cantilever at rest."""
    backend = make_backend(BackendSpec(name=name, held_ends="left", rod=rod))
    try:
        backend.reset(0)
        still, last = np.zeros((2, 6)), tip(backend)
        for _ in range(SETTLE_STEPS):
            backend.step(still)
            now = tip(backend)
            if np.linalg.norm(now - last) / backend.control_dt < REST_SPEED:
                break
            last = now
        return float(backend.rest_gripper_poses()[0, 2] - tip(backend)[2])
    finally:
        backend.close()


def vibration_frequency(name: str, rod: RodSpec) -> float:
    """Hz of the tip's free lateral vibration after a one-step kick of the clamp."""
    spec = BackendSpec(name=name, held_ends="left", rod=rod, physics_dt=UNDAMPED_DT.get(name))
    backend = make_backend(spec)
    try:
        backend.reset(0)
        kick = np.zeros((2, 6))
        kick[0, 1] = KICK
        backend.step(kick)
        lateral = []
        for _ in range(round(VIBRATION_SECONDS / backend.control_dt)):
            backend.step(np.zeros((2, 6)))
            lateral.append(tip(backend)[1])
        return zero_crossing_frequency(np.array(lateral), backend.control_dt)
    finally:
        backend.close()


def zero_crossing_frequency(signal: np.ndarray, dt: float) -> float:
    """Hz from the interpolated zero crossings of ``signal`` about its mean (nan if < 3)."""
    centred = signal - signal.mean()
    i = np.nonzero(np.sign(centred[:-1]) * np.sign(centred[1:]) < 0)[0]
    if i.size < 3:
        return float("nan")
    times = (i + centred[i] / (centred[i] - centred[i + 1])) * dt
    return float((i.size - 1) / (2 * (times[-1] - times[0])))


def main() -> None:
    paper = RodSpec(length=LENGTH, n_segments=SEGMENTS)
    undamped = paper.model_copy(
        update={"bending_damping": 0.0, "twist_damping": 0.0, "air_damping": 0.0}
    )
    weight = paper.density * paper.area * GRAVITY
    print(f"rod {LENGTH} m, N {SEGMENTS}, E {paper.young_bending:g} Pa, r {paper.radius} m")
    print(f"{'check':36s}" + "".join(f"{name:>10s}" for name in backends.names()))
    rows: list[tuple[str, dict[str, float]]] = []
    reference = self_weight_deflection(paper)
    alpha = weight * LENGTH**3 / paper.bending_stiffness
    rows.append(
        (
            f"self-weight w L^4/8EI (alpha {alpha:.2f})",
            {n: settled_tip_drop(n, paper) / reference for n in backends.names()},
        )
    )
    for alpha in ALPHAS:
        density = alpha * paper.bending_stiffness / (paper.area * GRAVITY * LENGTH**3)
        rod = paper.model_copy(update={"density": density})
        reference = elastica_deflection(alpha, LENGTH)
        rows.append(
            (
                f"elastica, self-weight alpha {alpha:g}",
                {n: settled_tip_drop(n, rod) / reference for n in backends.names()},
            )
        )
    reference = first_bending_frequency(paper)
    rows.append(
        (
            f"first bending freq. ({reference:.2f} Hz)",
            {n: vibration_frequency(n, undamped) / reference for n in backends.names()},
        )
    )
    for label, ratios in rows:
        print(f"{label:36s}" + "".join(f"{ratios[n]:10.3f}" for n in backends.names()))
        sys.stdout.flush()


if __name__ == "__main__":
    main()
