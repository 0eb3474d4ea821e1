"""The backend contract: a rod held by two 6-DoF kinematic grippers, stepped at control rate.

Conventions (docs/concepts.md):
- World frame, metres, z up, gravity -9.81 z. No floor: the rod hangs in the air.
- Rod of ``n_segments`` rigid segments. Segment i's frame has its x axis along the rod
  (from the left end towards the right end) and its origin at the segment centre.
- ``segment_positions()`` (N,3) centres; ``segment_quaternions()`` (N,4) unit (w,x,y,z).
- Gripper 0 ("left") holds the start of segment 0, gripper 1 ("right") the end of segment N-1.
  A gripper pose is (x, y, z, qw, qx, qy, qz): the held rod end point and the held segment's
  orientation at rest (the rod leaves the left gripper along its +x, enters the right one
  along its +x).
- ``step(velocities)`` takes (2,6) gripper twists in physical units — linear velocity (m/s)
  then world-frame angular velocity (rad/s) about the gripper position — and advances one
  control period. Translations are clipped to the workspace and the separation limits here,
  once, for every backend, so the rod cannot be torn (a taut rod blows up MuJoCo's cable and
  makes PyBullet let go).
- ``reset()`` puts the rod at rest in its nominal configuration: grippers on the x axis,
  ``initial_separation`` apart, centred at (0, 0, ``rest_height``), the rod sagging between
  them. Like the workspace, the rest configuration scales with the rod length. Randomisation
  of the start is the task's job (it moves the grippers).
- A diverged simulation (NaN, explosion) sets ``diverged`` and makes further steps no-ops.
"""

from __future__ import annotations

import math
from abc import ABC, abstractmethod
from dataclasses import dataclass

import numpy as np

from dlocli.backends.facts import BackendFacts
from dlocli.backends.rays import GRIPPER_HALF_EXTENTS, RayHits, cast_on_shapes
from dlocli.errors import BadInput, UnworkablePhysics
from dlocli.specs import BackendSpec, RodSpec, segment_limit_error

#: omega_max * dt of the chain's fastest mode for explicit springs: stable and accurate
#: (semi-implicit Euler diverges from 2, PyBullet's chain from ~0.85)
COURANT = 0.5
#: the fastest mode of a compliant clamp's segment over the fastest rod mode, squared: the
#: clamp joint is twice a rod joint (measured: 1.0 diverges at 10 segments and 2e7 Pa)
CLAMP_STIFFENING = 1.5
#: backend capabilities (``Backend.capabilities``) that physics checks may need
END_LOAD = "end_load"  # set_end_load
#: implicit joint damping: Kelvin-Voigt damping of any strength on the segments' real inertia
KELVIN_VOIGT_REAL_INERTIA = "kelvin_voigt_real_inertia"
REST_HEIGHT = 0.8  # rod lengths: inside the length-scaled workspace (z from 0.3 to 1.4)
INITIAL_SEPARATION = 0.9  # fraction of the rod length: a slack rod (a taut one is torn apart)


@dataclass
class GripperLimits:
    """Where grippers may go: a workspace box and gripper separation bounds (metres)."""

    low: np.ndarray
    high: np.ndarray
    min_separation: float
    max_separation: float

    @classmethod
    def default(cls, rod_length: float) -> GripperLimits:
        return cls(
            low=np.array([-0.8, -0.6, 0.3]) * rod_length,
            high=np.array([0.8, 0.6, 1.4]) * rod_length,
            min_separation=0.2 * rod_length,
            max_separation=0.95 * rod_length,
        )


def _largest_feasible_fraction(d0: np.ndarray, dd: np.ndarray, lo: float, hi: float) -> float:
    """Largest a in [0,1] with lo <= |d0 + a dd| <= hi, by bisection (steps are millimetres)."""
    start, change = d0.tolist(), dd.tolist()

    def feasible(a: float) -> bool:
        dist = math.hypot(*(x + a * y for x, y in zip(start, change, strict=True)))
        return lo - 1e-12 <= dist <= hi + 1e-12

    if feasible(1.0):
        return 1.0
    good, bad = 0.0, 1.0
    for _ in range(30):
        mid = 0.5 * (good + bad)
        good, bad = (mid, bad) if feasible(mid) else (good, mid)
    return good


def _spin_quaternion(quat: list[float], rotvec: list[float]) -> list[float]:
    """Unit quaternion (w,x,y,z) rotated by a world-frame rotation vector (rad), w >= 0.

    ``quat_normalize(quat_multiply(quat_from_rotvec(rotvec), quat))`` on plain floats: for
    two grippers every control step this is several times cheaper than numpy's per-call cost.
    """
    rx, ry, rz = rotvec
    angle = math.sqrt(rx * rx + ry * ry + rz * rz)
    scale = math.sin(0.5 * angle) / angle if angle > 1e-12 else 0.5
    sw, sx, sy, sz = math.cos(0.5 * angle), rx * scale, ry * scale, rz * scale
    w, x, y, z = quat
    product = (
        sw * w - sx * x - sy * y - sz * z,
        sw * x + sx * w + sy * z - sz * y,
        sw * y - sx * z + sy * w + sz * x,
        sw * z + sx * y - sy * x + sz * w,
    )
    norm = math.copysign(math.sqrt(sum(c * c for c in product)), product[0])
    return [c / norm for c in product]


def integrate_gripper_poses(
    poses: np.ndarray, velocities: np.ndarray, dt: float, limits: GripperLimits, moving: np.ndarray
) -> np.ndarray:
    """Advance (2,7) gripper poses by (2,6) twists over dt, respecting the limits.

    ``moving`` (2,) bool masks grippers that may move (a free rod end has no gripper).
    Plain floats per gripper: this runs every control step, numpy calls cost microseconds.
    """
    low, high = limits.low.tolist(), limits.high.tolist()
    new = []
    for pose, twist, may_move in zip(
        poses.tolist(), velocities.tolist(), moving.tolist(), strict=True
    ):
        step = [v * dt for v in twist] if may_move else [0.0] * 6
        position = pose[:3]
        if may_move:
            position = [
                min(max(p + s, lo), hi)
                for p, s, lo, hi in zip(position, step[:3], low, high, strict=True)
            ]
        new.append(position + _spin_quaternion(pose[3:], step[3:]))
    result = np.array(new)
    if moving.all():
        delta = result[:, :3] - poses[:, :3]
        frac = _largest_feasible_fraction(
            poses[1, :3] - poses[0, :3],
            delta[1] - delta[0],
            limits.min_separation,
            limits.max_separation,
        )
        if frac < 1.0:
            result[:, :3] = poses[:, :3] + delta * frac
    return result


def chain_modes_squared(rod: RodSpec, twist_inertia: float, bend_inertia: float) -> np.ndarray:
    """(twist, bending) omega^2 (rad^2/s^2) of the chain's fastest modes, neighbours
    alternating, for segments of these rotary inertias (kg m^2, about the centre):
    ``4 k_t / J_t`` and ``16 k_b / (m l^2 + 4 J_b)``, a compliant clamp's segment faster."""
    seg = rod.segment_length
    mass = rod.density * rod.area * seg
    clamp = CLAMP_STIFFENING if rod.clamp_compliance == "half-segment" else 1.0
    k_t, k_b = rod.torsional_stiffness / seg, rod.bending_stiffness / seg
    return clamp * np.array(
        [4.0 * k_t / twist_inertia, 16.0 * k_b / (mass * seg**2 + 4.0 * bend_inertia)]
    )


def segment_inertia(rod: RodSpec) -> tuple[float, float]:
    """(twist, bending) rotary inertia (kg m^2) of one cylindrical segment about its centre."""
    seg, r = rod.segment_length, rod.radius
    mass = rod.density * rod.area * seg
    return 0.5 * mass * r**2, mass * (3 * r**2 + seg**2) / 12.0


def material_physics_dt(rod: RodSpec) -> float:
    """The largest physics step (s) at which explicit springs move the rod's real segments,
    damping off: ``COURANT / omega`` of the chain's fastest mode."""
    return COURANT / math.sqrt(chain_modes_squared(rod, *segment_inertia(rod)).max())


class Backend(BackendFacts, ABC):
    """A simulated rod held by grippers. Subclasses implement the physics hooks (``_*``)
    and set their facts (:class:`~dlocli.backends.facts.BackendFacts`)."""

    #: registry name, set by subclasses
    name: str = ""
    #: optional abilities a physics check may need ("end_load": :meth:`set_end_load`)
    capabilities: frozenset[str] = frozenset()
    #: whether the last state saw the cable (a simulator always does; a cell's tracker may not)
    tracked: bool = True

    @classmethod
    def unavailable(cls) -> str | None:
        """Why this backend cannot run with the installed simulator (one line naming the
        fix), or None if it can."""
        return None

    def __init__(self, spec: BackendSpec | None = None, control_dt: float = 0.02) -> None:
        reason = self.unavailable()
        if reason:
            raise BadInput(reason)
        self.spec = spec or BackendSpec(name=self.name)
        # a spec changed by model_copy(update=...) skips the spec's own validation
        error = segment_limit_error(self.name, self.max_segments, self.spec.rod.n_segments)
        if error:
            raise BadInput(error)
        self.rod = self.spec.rod
        self.n_segments = self.rod.n_segments
        self.control_dt = control_dt
        self.limits = GripperLimits.default(self.rod.length)
        self.moving = np.array([True, self.spec.held_ends == "both"])
        self.diverged = False
        self._gripper_poses = self.rest_gripper_poses()
        self._end_load: tuple[list[float], list[float]] | None = None

    # ----------------------------------------------------------------- public API
    def set_end_load(self, force: np.ndarray, torque: np.ndarray) -> None:
        """Load the free rod end from the next step on: a constant world-frame force (N) at
        its end point and torque (N m) on its last segment (both zero: no load).

        For physics checks on a cantilever (``held_ends="left"``), where backends have the
        "end_load" capability.
        """
        if END_LOAD not in self.capabilities:
            raise NotImplementedError(f"the {self.name} backend cannot load the rod's end")
        if self.spec.held_ends != "left":
            raise ValueError("an end load needs a free rod end: held_ends='left'")
        force = np.asarray(force, dtype=np.float64).reshape(3)
        torque = np.asarray(torque, dtype=np.float64).reshape(3)
        loaded = bool(np.any(force) or np.any(torque))
        self._end_load = (force.tolist(), torque.tolist()) if loaded else None

    def rest_gripper_poses(self) -> np.ndarray:
        """(2,7) nominal gripper poses: on the x axis, slack separation, rod along +x."""
        half = 0.5 * INITIAL_SEPARATION * self.rod.length
        if self.spec.held_ends == "left":
            half = 0.5 * self.rod.length  # cantilever: straight out from the left gripper
        poses = np.zeros((2, 7))
        poses[:, 3] = 1.0
        poses[0, :3] = (-half, 0.0, self.rest_height)
        poses[1, :3] = (half, 0.0, self.rest_height)
        return poses

    @property
    def rest_height(self) -> float:
        """Height (m) of the grippers at rest."""
        return REST_HEIGHT * self.rod.length

    def reset(self, seed: int | None = None) -> None:
        """Rest configuration (deterministic); ``seed`` seeds any backend-internal noise."""
        self.diverged = False
        self._gripper_poses = self.rest_gripper_poses()
        self._reset_physics(seed)

    def step(self, velocities: np.ndarray) -> bool:
        """Advance one control period with (2,6) gripper twists; return False if diverged."""
        if self.diverged:
            return False
        velocities = np.asarray(velocities, dtype=np.float64).reshape(2, 6)
        if not np.all(np.isfinite(velocities)):
            raise ValueError("gripper velocities must be finite")
        self._move(velocities)
        return not self.diverged

    def _move(self, velocities: np.ndarray) -> None:
        """One control period of the grippers at (2,6) ``velocities`` inside the limits."""
        start = self._gripper_poses
        end = integrate_gripper_poses(start, velocities, self.control_dt, self.limits, self.moving)
        self._gripper_poses = end
        ok = self._advance(start, end)
        if not ok or not self._state_is_sane():
            self.diverged = True

    def gripper_poses(self) -> np.ndarray:
        """(2,7) gripper poses (position, quaternion w x y z)."""
        return self._gripper_poses.copy()

    def get_state(self) -> np.ndarray:
        """Full simulator state as a flat float64 vector (gripper poses included)."""
        return np.concatenate(
            [self._gripper_poses.ravel(), [float(self.diverged)], self._get_physics_state()]
        )

    def set_state(self, state: np.ndarray) -> None:
        """Restore a state from :meth:`get_state` exactly (same future under same actions)."""
        state = np.asarray(state, dtype=np.float64)
        self._gripper_poses = state[:14].reshape(2, 7).copy()
        self.diverged = bool(state[14])
        self._set_physics_state(state[15:])

    def _state_is_sane(self) -> bool:
        # NaN/inf propagate through the sums and fail the comparisons: no separate isfinite
        offset = self.segment_positions() - self._gripper_poses[0, :3]
        reach2 = np.einsum("ij,ij->i", offset, offset).max()
        if not reach2 < (3.0 * self.rod.length) ** 2:
            return False
        return bool(np.isfinite(self.segment_quaternions().sum()))

    # ----------------------------------------------------------------- subclass hooks
    @abstractmethod
    def _reset_physics(self, seed: int | None) -> None:
        """Rebuild the rest configuration for ``self._gripper_poses``."""

    @abstractmethod
    def _advance(self, start: np.ndarray, end: np.ndarray) -> bool:
        """Move grippers from ``start`` to ``end`` (2,7) over one control period; False if NaN."""

    @abstractmethod
    def _get_physics_state(self) -> np.ndarray: ...

    @abstractmethod
    def _set_physics_state(self, state: np.ndarray) -> None: ...

    @abstractmethod
    def segment_positions(self) -> np.ndarray:
        """(N,3) segment centre positions in metres."""

    @abstractmethod
    def segment_quaternions(self) -> np.ndarray:
        """(N,4) segment orientations, unit quaternions (w,x,y,z)."""

    @abstractmethod
    def render(
        self, width: int = 480, height: int = 360, goal: np.ndarray | None = None
    ) -> np.ndarray:
        """RGB image (height, width, 3) uint8 of the rod (and the goal shape, if given)."""

    def cast_rays(
        self, origin: np.ndarray, directions: np.ndarray, grippers: bool = True
    ) -> RayHits:
        """What rays from ``origin`` (3,) along unit ``directions`` (R,3) hit first: the rod
        (which segment), a held end's gripper (unless ``grippers`` is False: then rays pass
        through them), or nothing (a depth camera's view).

        The default casts them analytically on the reported segments (capsules) and gripper
        boxes; a simulator with its own ray casting overrides it."""
        return cast_on_shapes(
            np.asarray(origin, dtype=np.float64),
            np.asarray(directions, dtype=np.float64),
            self.segment_positions(),
            self.segment_quaternions(),
            self.rod.segment_length,
            self.rod.radius,
            self.held_gripper_poses() if grippers else np.zeros((0, 7)),
            self.gripper_half_extents(),
        )

    def held_gripper_poses(self) -> np.ndarray:
        """(G,7) the poses of the grippers that hold a rod end (a free end has none)."""
        return self.gripper_poses()[: 2 if self.spec.held_ends == "both" else 1]

    def gripper_half_extents(self) -> np.ndarray:
        """(3,) a gripper box's half extents (m) along its x, y, z axes."""
        return np.array(GRIPPER_HALF_EXTENTS) * self.rod.length

    def raw_physics_seconds(self, control_steps: int) -> float:
        """Seconds per control step of bare physics stepping (no wrapper), for benchmarks.

        Runs from a copy of the current state and restores it afterwards.
        """
        state = self.get_state()
        seconds = self._time_raw_physics(control_steps)
        self.set_state(state)
        return seconds

    def _time_raw_physics(self, control_steps: int) -> float:
        """Step the simulator's physics for ``control_steps`` control periods, grippers still,
        with nothing but the simulator's own stepping call in the loop; return seconds per
        control period."""
        raise NotImplementedError

    def close(self) -> None:  # noqa: B027 - optional hook
        """Release simulator resources."""

    @property
    def physics_dt(self) -> float:
        return self.spec.physics_dt or self.default_physics_dt

    def unworkable_rod(self, problem: str) -> UnworkablePhysics:
        """The error of a rod the simulator cannot hold (``problem``), naming its parameters."""
        rod = self.spec.rod
        return UnworkablePhysics(
            f"{self.spec.name}: {problem} (length {rod.length:g} m, radius "
            f"{rod.radius:g} m, density {rod.density:g} kg/m^3, Young's moduli "
            f"{rod.young_tension:g}/{rod.young_bending:g} Pa, physics_dt {self.physics_dt:g} s); "
            "bring the material closer to the defaults or pass a smaller backend.physics_dt"
        )

    #: subclasses: the physics step that keeps the rod stable at the maximum gripper speeds
    default_physics_dt: float = 0.002
