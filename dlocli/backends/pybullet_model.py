"""The PyBullet chain's discretised rod (:mod:`dlocli.backends.pybullet_chain`): per-segment
mass, stiffness, damping and rotary inertia, in SI units.

- Elasticity: every spherical joint carries a linear spring-damper on its rotation vector
  ``theta`` (log map of the joint quaternion, child frame, x = rod axis):
  ``tau = -diag(k_t, k_b, k_b) theta - beta diag(k_t, k_b, k_b) omega`` with
  ``k_b = EI / l`` and ``k_t = GJ / l`` exactly, so static shapes (the cantilever) are the
  discrete Euler-Bernoulli rod's.
- Why explicit torques plus armature: PyBullet 3.2.7 offers no calibrated implicit joint
  spring (``STABLE_PD_CONTROL`` gives static joint deflections orders of magnitude off
  ``tau / kp``, changing with kd; the spherical ``POSITION_CONTROL`` motor is a velocity
  constraint, not a spring). Explicit torques at 2 ms are unstable for the physical rotary
  inertia (the twist "zig-zag" mode of a 5 cm segment is ~2400 rad/s), and so is explicit
  Kelvin-Voigt damping whose rate at those modes exceeds ~1 / dt. So the segments' rotary
  inertia is raised (an armature, as in MuJoCo) just enough that the fastest discrete modes
  satisfy ``omega_max * dt <= COURANT`` (unstable from ~0.85), their damping rates likewise.
  Masses and stiffnesses stay physical and statics are exact; the dynamics are the real
  rod's only where no armature is needed: with little damping at
  ``base.material_physics_dt`` (``added_inertia`` says how much was added;
  benchmarks/results/rod_physics.txt gives it for the default rods). The backend therefore
  does not declare ``KELVIN_VOIGT_REAL_INERTIA``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from dlocli.backends.base import CLAMP_STIFFENING, COURANT, segment_inertia
from dlocli.specs import RodSpec

DAMPING_STEPS = 2.0  # joint damping time beta, in physics steps (damps the fastest modes)


@dataclass(frozen=True)
class ChainModel:
    """Per-segment parameters of the discretised rod (SI units)."""

    seg_length: float  # m
    seg_mass: float  # kg
    stiffness: np.ndarray  # (3,) N m/rad about (rod axis, bend y, bend z): (k_t, k_b, k_b)
    damping: np.ndarray  # (3,) N m s/rad, stiffness-proportional (a damping time each)
    inertia: np.ndarray  # (3,) kg m^2 about the segment centre, armature included

    @classmethod
    def from_rod(cls, rod: RodSpec, dt: float) -> ChainModel:
        """Physical mass and stiffness; rotary inertia raised to keep explicit springs stable."""
        seg = rod.segment_length
        m = rod.density * rod.area * seg
        k_b = rod.bending_stiffness / seg
        k_t = rod.torsional_stiffness / seg
        h = dt / COURANT
        default = DAMPING_STEPS * dt
        bend_time = default if rod.bending_damping is None else rod.bending_damping
        twist_time = default if rod.twist_damping is None else rod.twist_damping
        c_t, c_b = twist_time * k_t, bend_time * k_b
        # zig-zag modes (neighbours alternate): twist omega^2 = 4 k_t / J_t,
        # bending omega^2 = 16 k_b / (m l^2 + 4 J_b); J >= bound <=> omega * dt <= COURANT
        # (chain_modes_squared); a compliant clamp's segment is faster
        clamp = CLAMP_STIFFENING if rod.clamp_compliance == "half-segment" else 1.0
        real_twist, real_bend = segment_inertia(rod)
        j_twist = max(real_twist, 4.0 * clamp * k_t * h**2)
        j_bend = max(real_bend, (16.0 * clamp * k_b * h**2 - m * seg**2) / 4.0)
        # their explicit damping rates 4 c_t / J_t and 16 c_b / (m l^2 + 4 J_b) stay below
        # 2 COURANT / dt the same way; the default damping (two steps) never needs more
        j_twist_damped = max(j_twist, 2.0 * clamp * c_t * h)
        j_bend_damped = max(j_bend, (8.0 * clamp * c_b * h - m * seg**2) / 4.0)
        if (j_twist_damped, j_bend_damped) != (j_twist, j_bend):
            # one axis much heavier than the others: the explicit gyroscopic torque blows up
            j_twist = j_bend = max(j_twist_damped, j_bend_damped)
        stiffness = np.array([k_t, k_b, k_b])
        return cls(
            seg_length=seg,
            seg_mass=m,
            stiffness=stiffness,
            damping=np.array([c_t, c_b, c_b]),
            inertia=np.array([j_twist, j_bend, j_bend]),
        )
