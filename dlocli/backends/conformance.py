"""Physics conformance: the rod against textbook mechanics, through the public backend API.

Every check builds a rod from a :class:`~dlocli.specs.RodSpec`, simulates it on one backend
and returns simulated / reference. The references are computed here: Euler-Bernoulli's
cantilever under its own weight ``w L^4 / 8 EI`` and under a tip load ``P L^3 / 3 EI``; the
large-deflection cantilever under its own weight (the elastica ``EI theta'' = -w (L - s)
cos theta``, solved with scipy's ``solve_bvp``); Saint-Venant twist ``T s / GJ``; the first
bending and twist frequencies of a clamped-free rod; a damping ratio asked through the rod
spec. A check that needs an ability a backend does not declare (``Backend.capabilities``)
says so (:func:`missing`). tests/test_physics_conformance.py asserts the tolerances,
benchmarks/rod_physics.py prints the table.

Conventions: a segment's frame stands for the rod at the segment centre (so the last
segment's twist is compared with the continuum's at ``L - l/2``), the tip is the end point of
the last segment. Dynamic checks switch gravity off (a clean Euler-Bernoulli rod about its
straight shape) and run at :func:`~dlocli.backends.base.material_physics_dt`, the step at
which explicit springs move the segments' real inertia.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from dlocli.backends.base import (
    END_LOAD,
    KELVIN_VOIGT_REAL_INERTIA,
    Backend,
    material_physics_dt,
)
from dlocli.backends.rotations import quat_multiply, quat_rotate
from dlocli.registry import backends
from dlocli.specs import STANDARD_GRAVITY, BackendSpec, RodSpec

SHORT = 0.2  # m: the short rod; its self-weight deflection is small (alpha 0.31)
SEGMENTS = 20
ALPHAS = (0.5, 1.0, 2.0, 5.0, 10.0)  # elastica load parameters w L^3 / EI
TIP_LOAD = 0.015  # P L^2 / EI: small deflection
TWIST_LOAD = 0.05  # T L / GJ (rad)
ASKED_DAMPING_RATIO = 0.1
SETTLE_STEPS = 500  # control steps (10 s) at most to come to rest
REST_SPEED = 1e-5  # m/s of the tip
REST_STEPS = 10  # control steps in a row below REST_SPEED
FIRST_BENDING = 1.8751  # beta_1 L of a clamped-free beam
STATIC_AIR_DAMPING = 5.0  # 1/s
UNDAMPED = {"bending_damping": 0.0, "twist_damping": 0.0, "air_damping": 0.0}
MOTION_SECONDS = 2.0
MOTION_TWIST = np.array([[0.0] * 6, [0.0, 0.0, 0.05, 0.25, 0.0, 0.0]])  # 10 cm, 0.5 rad in 2 s
MOTION_AIR_DAMPING = 1.0  # 1/s: the same motion's only damping (explicit on both backends)
X_AXIS = np.array([1.0, 0.0, 0.0])


# ----------------------------------------------------------------------------- references
def weight_per_length(rod: RodSpec, gravity: float = STANDARD_GRAVITY) -> float:
    return rod.density * rod.area * gravity


def self_weight_deflection(rod: RodSpec) -> float:
    """Euler-Bernoulli tip deflection (m) of a cantilever under its own weight."""
    return weight_per_length(rod) * rod.length**4 / (8 * rod.bending_stiffness)


def elastica_deflection(alpha: float, length: float) -> float:
    """Tip drop (m) of a cantilever of load parameter ``w L^3 / EI``, solved as a BVP."""
    from scipy.integrate import solve_bvp

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
    stiffness = rod.bending_stiffness / (rod.density * rod.area * rod.length**4)
    return FIRST_BENDING**2 / (2 * math.pi) * math.sqrt(stiffness)


def first_twist_frequency(rod: RodSpec) -> float:
    """Hz, clamped-free rod in torsion: ``sqrt(G / rho) / 4 L``."""
    polar_inertia = rod.density * 2 * rod.second_moment  # rho J per length
    return math.sqrt(rod.torsional_stiffness / polar_inertia) / (4 * rod.length)


# ----------------------------------------------------------------------------- simulation
def cantilever(
    name: str,
    rod: RodSpec,
    gravity: float = STANDARD_GRAVITY,
    physics_dt: float | None = None,
    control_dt: float = 0.02,
) -> Backend:
    """The rod held by the left gripper only, at rest."""
    spec = BackendSpec(name=name, held_ends="left", rod=rod, gravity=gravity, physics_dt=physics_dt)
    backend = backends.get(name)(spec, control_dt=control_dt)
    backend.reset(0)
    return backend


def tip(backend: Backend) -> np.ndarray:
    """End point (m) of the free end: the last segment's centre plus half a segment."""
    axis = quat_rotate(backend.segment_quaternions()[-1], X_AXIS)
    return backend.segment_positions()[-1] + 0.5 * backend.rod.segment_length * axis


def settle(backend: Backend) -> np.ndarray:
    """Step with the grippers still until the tip has been at rest for REST_STEPS steps in a
    row (a heavy rod starts slowly under a new load); its position (m)."""
    still, resting = np.zeros((2, 6)), 0
    last = np.append(tip(backend), twist_angle(backend) * backend.rod.length)
    for _ in range(SETTLE_STEPS):
        if not backend.step(still):
            raise RuntimeError(f"{backend.name}: the rod diverged while settling")
        # the tip's speed and its twist rate times the length (m/s)
        now = np.append(tip(backend), twist_angle(backend) * backend.rod.length)
        slow = np.abs(now - last).max() / backend.control_dt < REST_SPEED
        resting = resting + 1 if slow else 0
        if resting == REST_STEPS:
            break
        last = now
    return tip(backend)


def twist_angle(backend: Backend) -> float:
    """Rotation (rad) of the last segment about its axis relative to the left gripper."""
    grip = backend.gripper_poses()[0, 3:] * np.array([1.0, -1.0, -1.0, -1.0])
    w, x, _, _ = quat_multiply(grip, backend.segment_quaternions()[-1])
    return 2.0 * math.atan2(x, w)  # the twist part of the swing-twist decomposition


def zero_crossings(signal: np.ndarray, dt: float) -> np.ndarray:
    """Times (s) of the interpolated sign changes of ``signal``."""
    i = np.nonzero(np.sign(signal[:-1]) * np.sign(signal[1:]) < 0)[0]
    return (i + signal[i] / (signal[i] - signal[i + 1])) * dt


def frequency(signal: np.ndarray, dt: float) -> float:
    """Hz from the zero crossings of an oscillation about zero (nan if fewer than 3)."""
    times = zero_crossings(signal, dt)
    if times.size < 3:
        return float("nan")
    return float((times.size - 1) / (2 * (times[-1] - times[0])))


def damping_ratio(signal: np.ndarray, dt: float) -> float:
    """Damping ratio from the decay of the extremes between zero crossings (log decrement)."""
    times = zero_crossings(signal, dt)
    cuts = np.ceil(times / dt).astype(int)
    peaks = np.array([np.abs(signal[a:b]).max() for a, b in zip(cuts[:-1], cuts[1:], strict=True)])
    if peaks.size < 3:
        return float("nan")
    decrement = -np.polyfit(np.arange(peaks.size), np.log(peaks), 1)[0]  # per half period
    return float(decrement / math.sqrt(math.pi**2 + decrement**2))


def free_vibration(
    name: str, rod: RodSpec, period: float, mode: str, periods: float = 1.75
) -> tuple[np.ndarray, float]:
    """Tip lateral offset (bending) or last-segment twist (twist) after a quarter-period kick
    of the clamp, in free space, sampled 40 times per ``period`` (s); (signal, sample dt)."""
    control_dt = min(0.02, period / 40)
    backend = cantilever(name, rod, 0.0, material_physics_dt(rod), control_dt)
    try:
        kick = np.zeros((2, 6))
        # about 1% of the length (bending) or 0.05 rad (twist) at the clamp
        kick[0, 1 if mode == "bending" else 3] = (
            0.04 * rod.length if mode == "bending" else 0.2
        ) / period
        for _ in range(max(1, round(0.25 * period / control_dt))):
            backend.step(kick)
        signal = []
        for _ in range(round(periods * period / control_dt)):
            if not backend.step(np.zeros((2, 6))):
                raise RuntimeError(f"{name}: the rod diverged while vibrating")
            if mode == "bending":
                signal.append(tip(backend)[1] - backend.gripper_poses()[0, 1])
            else:
                signal.append(twist_angle(backend))
        return np.array(signal), control_dt
    finally:
        backend.close()


# ----------------------------------------------------------------------------- checks
def short_rod(**fields: object) -> RodSpec:
    return RodSpec(length=SHORT, n_segments=SEGMENTS, **fields)


def static_rod(**fields: object) -> RodSpec:
    """The short rod with air damping added: no equilibrium depends on damping, and it
    settles a rod with added rotary inertia (PyBullet) as soon as any other."""
    return short_rod(air_damping=STATIC_AIR_DAMPING, **fields)


def paper_rod(**fields: object) -> RodSpec:
    return RodSpec(n_segments=SEGMENTS, **fields)


def self_weight(name: str, alpha: float | None = None) -> float:
    """Settled tip drop / reference: Euler-Bernoulli, or the elastica at ``alpha``."""
    rod = static_rod()
    if alpha is not None:  # the load parameter set through the density
        density = alpha * rod.bending_stiffness / (rod.area * STANDARD_GRAVITY * SHORT**3)
        rod = static_rod(density=density)
    backend = cantilever(name, rod)
    try:
        drop = backend.gripper_poses()[0, 2] - settle(backend)[2]
    finally:
        backend.close()
    reference = self_weight_deflection(rod) if alpha is None else elastica_deflection(alpha, SHORT)
    return drop / reference


def tip_load(name: str) -> float:
    """Tip deflection under a downward end force, in free space / ``P L^3 / 3 EI``."""
    rod = static_rod()
    force = TIP_LOAD * rod.bending_stiffness / SHORT**2
    backend = cantilever(name, rod, gravity=0.0)
    try:
        backend.set_end_load(np.array([0.0, 0.0, -force]), np.zeros(3))
        drop = backend.gripper_poses()[0, 2] - settle(backend)[2]
    finally:
        backend.close()
    return drop / (force * SHORT**3 / (3 * rod.bending_stiffness))


def twist(name: str) -> float:
    """Last segment's twist under an end torque about the rod axis / ``T (L - l/2) / GJ``."""
    rod = static_rod()
    torque = TWIST_LOAD * rod.torsional_stiffness / SHORT
    backend = cantilever(name, rod, gravity=0.0)
    try:
        backend.set_end_load(np.zeros(3), torque * X_AXIS)
        settle(backend)
        angle = twist_angle(backend)
    finally:
        backend.close()
    return angle / (torque * (SHORT - 0.5 * rod.segment_length) / rod.torsional_stiffness)


def vibration_frequency(name: str, rod: RodSpec, mode: str) -> float:
    """First bending or twist frequency with damping off / the reference."""
    reference = first_bending_frequency(rod) if mode == "bending" else first_twist_frequency(rod)
    signal, dt = free_vibration(name, rod, 1.0 / reference, mode)
    return frequency(signal, dt) / reference


def air_damping_ratio(name: str) -> float:
    """The first bending mode's damping ratio / the one asked through ``air_damping``:
    ``d = 2 zeta omega`` (the linear part of the air damping law)."""
    rod = short_rod(**UNDAMPED)
    omega = 2 * math.pi * first_bending_frequency(rod)
    rod = rod.model_copy(update={"air_damping": 2 * ASKED_DAMPING_RATIO * omega})
    signal, dt = free_vibration(name, rod, 2 * math.pi / omega, "bending", periods=3)
    return damping_ratio(signal, dt) / ASKED_DAMPING_RATIO


def viscous_damping_ratio(name: str) -> float:
    """The first bending mode's damping ratio / the one asked through ``bending_damping``:
    ``beta = 2 zeta / omega`` (Kelvin-Voigt)."""
    rod = short_rod(**UNDAMPED)
    omega = 2 * math.pi * first_bending_frequency(rod)
    rod = rod.model_copy(update={"bending_damping": 2 * ASKED_DAMPING_RATIO / omega})
    signal, dt = free_vibration(name, rod, 2 * math.pi / omega, "bending", periods=3)
    return damping_ratio(signal, dt) / ASKED_DAMPING_RATIO


@dataclass(frozen=True)
class Check:
    """One physics check: ``run(backend name)`` returns simulated / reference."""

    name: str
    run: Callable[[str], float]
    tolerance: float  # |ratio - 1| allowed
    needs: frozenset[str] = field(default_factory=frozenset)  # backend capabilities
    slow: bool = False  # seconds of simulation at a fine step


CHECKS: tuple[Check, ...] = (
    Check("self-weight, w L^4/8EI", self_weight, 0.03),
    *(
        Check(f"elastica, self-weight alpha {a:g}", lambda n, a=a: self_weight(n, a), 0.03)
        for a in ALPHAS
    ),
    Check("tip load, P L^3/3EI", tip_load, 0.03, frozenset({END_LOAD})),
    Check("twist angle, T L/GJ", twist, 0.03, frozenset({END_LOAD})),
    Check(
        "first bending freq., 1 m rod",
        lambda n: vibration_frequency(n, paper_rod(**UNDAMPED), "bending"),
        0.10,
        slow=True,
    ),
    Check(
        "first bending freq., 0.2 m rod",
        lambda n: vibration_frequency(n, short_rod(**UNDAMPED), "bending"),
        0.10,
        slow=True,
    ),
    Check(
        "first twist freq., 1 m rod",
        lambda n: vibration_frequency(n, paper_rod(**UNDAMPED), "twist"),
        0.10,
    ),
    Check(
        "first twist freq., 0.2 m rod",
        lambda n: vibration_frequency(n, short_rod(**UNDAMPED), "twist"),
        0.10,
    ),
    Check("damping ratio 0.1, air_damping", air_damping_ratio, 0.20, slow=True),
    Check(
        "damping ratio 0.1, bending_damping",
        viscous_damping_ratio,
        0.20,
        frozenset({KELVIN_VOIGT_REAL_INERTIA}),
        slow=True,
    ),
)


def missing(check: Check, name: str) -> str | None:
    """Why backend ``name`` cannot take ``check``, or None if it can."""
    lacking = check.needs - backends.get(name).capabilities
    if not lacking:
        return None
    return f"the {name} backend does not declare {', '.join(sorted(lacking))}"


# ----------------------------------------------------------------------------- same motion
def motion_rod() -> RodSpec:
    """The paper rod whose only damping is a light air damping both backends apply alike."""
    return paper_rod(**{**UNDAMPED, "air_damping": MOTION_AIR_DAMPING})


def same_motion(name: str, rod: RodSpec | None = None) -> np.ndarray:
    """(steps, N, 3) segment centres of the rod (held at both ends) while the right gripper
    rises 10 cm and turns 0.5 rad about the rod axis in 2 s, at the material step."""
    rod = rod or motion_rod()
    spec = BackendSpec(name=name, rod=rod, physics_dt=material_physics_dt(rod))
    backend = backends.get(name)(spec)
    try:
        backend.reset(0)
        frames = []
        for _ in range(round(MOTION_SECONDS / backend.control_dt)):
            if not backend.step(MOTION_TWIST):
                raise RuntimeError(f"{name}: the rod diverged during the motion")
            frames.append(backend.segment_positions())
        return np.array(frames)
    finally:
        backend.close()
