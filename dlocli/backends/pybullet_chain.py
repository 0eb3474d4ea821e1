"""PyBullet backend: the rod as a chain of rigid capsules joined by elastic spherical joints.

Model (SI units throughout)
- One multibody of ``N`` capsule links, each of length ``l = L / N`` and mass
  ``rho * A * l``. Link frames sit at segment starts (the joint pivots); the inertial frame
  sits at the segment centre with its x axis along the rod, so PyBullet's link "world
  position" *is* the segment centre of base.py's convention.
- Elasticity and rotary inertia: :mod:`dlocli.backends.pybullet_model` (``ChainModel``):
  joint springs ``EI / l`` and ``GJ / l`` exactly, an armature where explicit springs need it.
- Clamps (the rod spec's ``clamp_compliance``, default "half-segment"): each held end
  segment hangs on a point-to-point constraint at the gripper and a clamp spring-damper to
  the gripper's orientation, twice a rod joint's (the half segment between gripper and first
  joint), applied as an external torque: the statics converge to the continuum's as 1/N^2.
  With "rigid" clamps the held segment is fixed in the gripper and a cantilever of N
  segments deflects ``(1 - 1/N)^2`` of Euler-Bernoulli's ``w L^4 / (8 EI)`` (-9.8% at 20).
- Damping: the rod spec's bending and twist damping times (above) and its air damping,
  PyBullet's own velocity damping of every link (acceleration ``-d (1 + |v|) v``). A spec
  whose damping is None keeps the backend's own constants: ``pybullet_model.DAMPING_STEPS``
  physics steps of joint damping and ``AIR_DAMPING`` = 5/s (the rest shape settles with
  ``SETTLE_DAMPING``).
- Grippers: each held end is a constraint (point-to-point, or ``JOINT_FIXED`` for rigid
  clamps) between the end of its segment and a world frame moved every physics step
  (``changeConstraint``, global ERP 1: no lag).
  Both ends are held the same way, so the rod stays symmetric end to end (the mirror test);
  the multibody's floating base, segment 0, is an ordinary segment. (Driving the base
  kinematically instead, by resetting its twist, carried the whole chain along at every
  change of command, since the joint velocities are relative to the base: a mirrored motion
  differed by up to 44 mm.) ``held_ends == "left"`` omits the right one (a free cantilever
  end).
- Limits: PyBullet reports at most 128 joint coordinates, i.e. 30 spherical joints: the
  chain has at most 31 segments (``dlocli.backends.facts.PybulletFacts``, checked by the spec).
"""

from __future__ import annotations

import contextlib
import math
import time
from typing import NamedTuple

import numpy as np
import pybullet as p

from dlocli.backends.base import (
    END_LOAD,
    Backend,
    segment_inertia,
)
from dlocli.backends.facts import PybulletFacts
from dlocli.backends.pybullet_model import ChainModel
from dlocli.backends.pybullet_rays import RayScene
from dlocli.backends.pybullet_render import ChainCamera
from dlocli.backends.pybullet_rotations import (
    right_product,
    rotate,
    rotation_vector,
    spin,
    wxyz,
    xyzw,
)
from dlocli.backends.rays import RayHits
from dlocli.backends.rotations import quat_normalize, quat_rotate
from dlocli.specs import BackendSpec

AIR_DAMPING = 5.0  # 1/s, default PyBullet linear/angular velocity damping of every link
SETTLE_DAMPING = 20.0  # 1/s, air damping while the rest shape settles in reset()
SETTLE_TIME = 3.0  # s of simulated settling for the rest shape
HOLD_FORCE = 1e4  # N, maximum force of the right gripper's fixed constraint
HOLD_ERP = 1.0  # fraction of the right gripper's pose error removed per physics step
SOLVER_ITERATIONS = 10  # PGS sweeps; one 6-row constraint converges in a few
MAX_JOINT_SPEED = 100.0  # rad/s; random gripper motion stays under 3, faster means a blow-up


class _Targets(NamedTuple):
    """Gripper drive for one control period (PyBullet lists, x y z w quaternions)."""

    hold_pos: list[list[list[float]]]  # (2, n, 3) gripper positions at each physics step's end
    hold_orn: list[list[list[float]]]  # (2, n, 4) their orientations (x y z w)
    spin: list[list[float]]  # (2, 3) their world angular velocities (rad/s)


class PybulletChain(PybulletFacts, Backend):
    """PyBullet chain of capsules, joint stiffness from EI/l and GJ/l (see module docstring)."""

    name = "pybullet"
    # its explicit joint damping needs added rotary inertia: no KELVIN_VOIGT_REAL_INERTIA
    capabilities = frozenset({END_LOAD})
    #: every dt is stable (the armature scales with dt^2); this one keeps the dynamics close to
    #: a converged run's at a useful simulation speed (benchmarks/rod_physics.py)
    default_physics_dt = 0.002

    def __init__(self, spec: BackendSpec | None = None, control_dt: float = 0.02) -> None:
        super().__init__(spec, control_dt)
        self._n_sub = max(1, round(control_dt / self.physics_dt))
        self._dt = control_dt / self._n_sub  # divides the control period exactly
        self.model = ChainModel.from_rod(self.rod, self._dt)
        self._air_damping = AIR_DAMPING if self.rod.air_damping is None else self.rod.air_damping
        self._client = p.connect(p.DIRECT)  # private server: several envs per process
        if self._client < 0:
            raise RuntimeError("could not start a PyBullet DIRECT physics server")
        self._body = -1
        self._holds: list[int] = []  # gripper constraint ids: left, then right if held
        self._joints = list(range(self.n_segments - 1))
        k, d = self.model.stiffness, self.model.damping  # (twist, bend, bend)
        self._gains = (float(k[0]), float(k[1]), float(d[0]), float(d[1]))
        self._frames: tuple[np.ndarray, np.ndarray] | None = None  # cached link frames
        self._camera = ChainCamera(self._client, self.rod, self.rest_height)
        self._ray_scene: RayScene | None = None  # made at the first cast_rays
        self._build()
        self._rest_state = self._settle_rest()

    # ----------------------------------------------------------------- construction
    def _build(self) -> None:
        c = self._client
        p.resetSimulation(physicsClientId=c)
        p.setGravity(0, 0, -self.spec.gravity, physicsClientId=c)
        p.setTimeStep(self._dt, physicsClientId=c)
        # the multibody fixed constraint uses the global ERP; the default 0.2 lags a moving
        # gripper by (1 - erp) / erp physics steps of travel (0.8 mm at 0.1 m/s)
        p.setPhysicsEngineParameter(
            erp=HOLD_ERP, numSolverIterations=SOLVER_ITERATIONS, physicsClientId=c
        )
        seg, r, n = self.model.seg_length, self.rod.radius, self.n_segments - 1
        along_x = p.getQuaternionFromEuler([0, math.pi / 2, 0])  # capsules are along z
        # no collision shapes (no floor, no self-collision): much faster steps; the
        # inertias are set explicitly in _set_dynamics
        vis = p.createVisualShape(
            p.GEOM_CAPSULE,
            radius=r,
            length=seg,
            visualFramePosition=[seg / 2, 0, 0],
            visualFrameOrientation=along_x,
            rgbaColor=[0.85, 0.35, 0.1, 1],
            physicsClientId=c,
        )
        self._body = p.createMultiBody(
            baseMass=self.model.seg_mass,
            baseCollisionShapeIndex=-1,
            baseVisualShapeIndex=vis,
            basePosition=[0, 0, self.rest_height],
            baseInertialFramePosition=[seg / 2, 0, 0],
            linkMasses=[self.model.seg_mass] * n,
            linkCollisionShapeIndices=[-1] * n,
            linkVisualShapeIndices=[vis] * n,
            linkPositions=[[seg, 0, 0]] * n,
            linkOrientations=[[0, 0, 0, 1]] * n,
            linkInertialFramePositions=[[seg / 2, 0, 0]] * n,
            linkInertialFrameOrientations=[[0, 0, 0, 1]] * n,
            linkParentIndices=list(range(n)),
            linkJointTypes=[p.JOINT_SPHERICAL] * n,
            linkJointAxis=[[0, 0, 1]] * n,
            physicsClientId=c,
        )
        self._set_dynamics(self._air_damping)
        # switch off the default joint motors: the joints are driven by our spring torques
        p.setJointMotorControlMultiDofArray(
            self._body,
            self._joints,
            p.POSITION_CONTROL,
            targetPositions=[[0, 0, 0, 1]] * n,
            forces=[[0, 0, 0]] * n,
            physicsClientId=c,
        )
        # (link, its end in its centre-of-mass frame): the start of segment 0 (the base),
        # the end of segment N-1
        ends = [(-1, -seg / 2), (n - 1, seg / 2)]
        held = ends[: 2 if self.spec.held_ends == "both" else 1]
        compliant = self.rod.clamp_compliance == "half-segment"
        # a compliant clamp holds the end point only; its joint springs are _clamp_torques'
        kind = p.JOINT_POINT2POINT if compliant else p.JOINT_FIXED
        self._clamp_links = [link for link, _ in held] if compliant else []
        for link, end in held:
            hold = p.createConstraint(
                self._body, link, -1, -1, kind, [0, 0, 0], [end, 0, 0],
                [0, 0, self.rest_height], physicsClientId=c,
            )  # fmt: skip
            p.changeConstraint(hold, maxForce=HOLD_FORCE, physicsClientId=c)
            self._holds.append(hold)

    def _set_dynamics(self, air_damping: float) -> None:
        """Sets the (armature) inertias and the multibody-wide velocity damping (1/s)."""
        c, b = self._client, self._body
        for link in [-1, *self._joints]:
            # separate calls: PyBullet drops the inertia when damping is in the same call
            p.changeDynamics(
                b, link, localInertiaDiagonal=self.model.inertia.tolist(), physicsClientId=c
            )
            p.changeDynamics(
                b, link, linearDamping=air_damping, angularDamping=air_damping, physicsClientId=c
            )

    def _arc_joint_state(self) -> np.ndarray:
        """Joint quaternions (x,y,z,w) of a slack vertical-plane arc with level end segments.

        Segment k points along (cos b_k, 0, -sin b_k), b_k = A sin(2 pi (k + 1/2) / N) with
        the end segments level (they are clamped), A found by bisection so the chord matches
        the gripper separation.
        """
        n, seg = self.n_segments, self.model.seg_length
        chord = np.linalg.norm(self._gripper_poses[1, :3] - self._gripper_poses[0, :3])
        shape = np.sin(2 * np.pi * (np.arange(n) + 0.5) / n)
        shape[[0, -1]] = 0.0

        def span(amplitude: float) -> float:
            return float(seg * np.cos(amplitude * shape).sum())

        lo, hi = 0.0, 1.5
        for _ in range(60):
            mid = 0.5 * (lo + hi)
            lo, hi = (mid, hi) if span(mid) > chord else (lo, mid)
        bend = np.diff(lo * shape)  # rotation of joint k about y, radians
        quats = np.zeros((n - 1, 4))
        quats[:, 1], quats[:, 3] = np.sin(bend / 2), np.cos(bend / 2)
        return quats

    def _settle_rest(self) -> np.ndarray:
        """Lay the rod out (arc or straight), let it settle with heavy damping, snapshot."""
        c, b, n = self._client, self._body, self.n_segments - 1
        straight = np.tile([0.0, 0, 0, 1], (n, 1))
        quats = self._arc_joint_state() if len(self._holds) == 2 else straight
        p.resetJointStatesMultiDof(
            b,
            self._joints,
            targetValues=quats.tolist(),
            targetVelocities=[[0, 0, 0]] * n,
            physicsClientId=c,
        )
        rest = self._gripper_poses
        # segment 0 starts at the left gripper (resetBase places the centre of mass)
        centre = rest[0, :3] + quat_rotate(rest[0, 3:], np.array([self.model.seg_length / 2, 0, 0]))
        p.resetBasePositionAndOrientation(
            b, centre.tolist(), xyzw(rest[0, 3:]).tolist(), physicsClientId=c
        )
        self._set_dynamics(SETTLE_DAMPING)
        # a straight cantilever in free space is at rest already
        settling = len(self._holds) == 2 or self.spec.gravity > 0
        for _ in range(round(SETTLE_TIME / self.control_dt) if settling else 0):
            if not self._advance(rest, rest):
                raise self.unworkable_rod("the rod's rest state diverged")
        self._set_dynamics(self._air_damping)
        state = self._get_physics_state()
        state[7:13] = 0.0  # at rest: exactly zero base and joint velocities
        state[13 + 4 * n : 13 + 7 * n] = 0.0
        self._set_physics_state(state)
        return state

    # ----------------------------------------------------------------- stepping
    def _reset_physics(self, seed: int | None) -> None:
        self._set_physics_state(self._rest_state)

    def _substep_targets(self, start: np.ndarray, end: np.ndarray) -> _Targets:
        """Gripper poses at the end of every physics step of one control period.

        Positions move linearly and orientations spin at the constant world angular velocity
        that :func:`integrate_gripper_poses` applied (``end = exp(w T) start``).
        """
        frac = np.arange(1, self._n_sub + 1)[:, None] / self._n_sub  # ends of the physics steps
        positions, orientations, spins_per_second = [], [], []
        for g in range(len(self._holds)):
            rotvec = spin(start[g, 3:], end[g, 3:])
            spins_per_second.append((rotvec / self.control_dt).tolist())
            angle = float(np.linalg.norm(rotvec))
            axis = rotvec / angle if angle > 1e-15 else np.zeros(3)
            half = 0.5 * angle * frac
            spins = np.hstack([np.cos(half), np.sin(half) * axis])  # (n,4) w x y z
            orientations.append(xyzw(spins @ right_product(start[g, 3:]).T).tolist())
            positions.append((start[g, :3] + frac * (end[g, :3] - start[g, :3])).tolist())
        return _Targets(hold_pos=positions, hold_orn=orientations, spin=spins_per_second)

    def _spring_torques(self, states: list) -> list[tuple[float, float, float]] | None:
        """Joint torques (N m, child frame) from PyBullet's multi-DoF joint states.

        ``tau = -K theta - C omega`` with ``theta`` the rotation vector of the joint
        quaternion. Plain Python: for ~20 joints it is twice as fast as numpy. None when a
        joint spins faster than ``MAX_JOINT_SPEED`` (or is NaN): the rod blew up.
        """
        kt, kb, ct, cb = self._gains
        torques = []
        for quat, (ox, oy, oz) in ((s[0], s[1]) for s in states):
            if not abs(ox) + abs(oy) + abs(oz) < MAX_JOINT_SPEED:
                return None
            tx, ty, tz = rotation_vector(*quat)
            torques.append((-kt * tx - ct * ox, -kb * ty - cb * oy, -kb * tz - cb * oz))
        return torques

    def _apply_end_load(self, force: list[float], torque: list[float]) -> None:
        """The end load on the last segment for the coming physics step (PyBullet clears
        external forces after every step)."""
        c, b, last = self._client, self._body, self.n_segments - 2
        start, quat = p.getLinkState(b, last, computeForwardKinematics=1, physicsClientId=c)[4:6]
        along = rotate(quat, (self.model.seg_length, 0.0, 0.0))
        end = [s + a for s, a in zip(start, along, strict=True)]
        p.applyExternalForce(b, last, force, end, p.WORLD_FRAME, physicsClientId=c)
        p.applyExternalTorque(b, last, torque, p.WORLD_FRAME, physicsClientId=c)

    @property
    def added_inertia(self) -> float:
        """The segments' rotary inertia over their real one, largest axis (1: none added)."""
        return float((self.model.inertia / np.array(segment_inertia(self.rod))[[0, 1, 1]]).max())

    def _clamp_torques(self, targets: _Targets, i: int) -> list[tuple[float, float, float]]:
        """World torques (N m) of the clamp joints on the held segments at physics step i.

        The spring-damper of a rod joint, twice as stiff (the half segment at the rod's end),
        between each gripper's orientation at the step's end and its segment's.
        """
        c, b = self._client, self._body
        kt, kb, ct, cb = (2.0 * gain for gain in self._gains)
        torques = []
        for g, link in enumerate(self._clamp_links):
            if link < 0:
                quat = p.getBasePositionAndOrientation(b, physicsClientId=c)[1]
                spin = p.getBaseVelocity(b, physicsClientId=c)[1]
            else:
                state = p.getLinkState(
                    b, link, computeLinkVelocity=1, computeForwardKinematics=1, physicsClientId=c
                )
                quat, spin = state[5], state[7]
            grip = targets.hold_orn[g][i]
            gx, gy, gz, gw = grip
            sx, sy, sz, sw = quat  # conj(grip) * segment, both x y z w
            rel = (
                gw * sx - gx * sw - gy * sz + gz * sy,
                gw * sy + gx * sz - gy * sw - gz * sx,
                gw * sz - gx * sy + gy * sx - gz * sw,
                gw * sw + gx * sx + gy * sy + gz * sz,
            )
            tx, ty, tz = rotation_vector(*rel)
            ox, oy, oz = rotate(
                grip, [a - e for a, e in zip(spin, targets.spin[g], strict=True)], inverse=True
            )
            local = (-kt * tx - ct * ox, -kb * ty - cb * oy, -kb * tz - cb * oz)
            torques.append(rotate(grip, local))
        return torques

    def _advance(self, start: np.ndarray, end: np.ndarray) -> bool:
        c, b, joints = self._client, self._body, self._joints
        targets = self._substep_targets(start, end)
        self._frames = None
        for i in range(self._n_sub):
            tau = self._spring_torques(p.getJointStatesMultiDof(b, joints, physicsClientId=c))
            if tau is None:
                return False
            p.setJointMotorControlMultiDofArray(
                b, joints, p.TORQUE_CONTROL, forces=tau, physicsClientId=c
            )
            for g, hold in enumerate(self._holds):
                p.changeConstraint(
                    hold,
                    targets.hold_pos[g][i],
                    jointChildFrameOrientation=targets.hold_orn[g][i],
                    maxForce=HOLD_FORCE,
                    physicsClientId=c,
                )
            if self._clamp_links:
                for link, torque in zip(
                    self._clamp_links, self._clamp_torques(targets, i), strict=True
                ):
                    p.applyExternalTorque(b, link, torque, p.WORLD_FRAME, physicsClientId=c)
            if self._end_load is not None:
                self._apply_end_load(*self._end_load)
            p.stepSimulation(physicsClientId=c)
        return True

    def _time_raw_physics(self, control_steps: int) -> float:
        # bare stepSimulation; the joint springs are ours (Python), so they count as overhead
        c = self._client
        start = time.perf_counter()
        for _ in range(control_steps * self._n_sub):
            p.stepSimulation(physicsClientId=c)
        return (time.perf_counter() - start) / control_steps

    # ----------------------------------------------------------------- state
    def _get_physics_state(self) -> np.ndarray:
        """[base pos 3, base quat xyzw 4, base lin vel 3, ang vel 3, joint quats 4n,
        joint vels 3n, gripper constraint targets (pos 3, quat xyzw 4) left then right (zeros
        for a free right end)]."""
        c, b = self._client, self._body
        pos, orn = p.getBasePositionAndOrientation(b, physicsClientId=c)
        lin, ang = p.getBaseVelocity(b, physicsClientId=c)
        states = p.getJointStatesMultiDof(b, self._joints, physicsClientId=c)
        targets = np.zeros((2, 7))
        for g, hold in enumerate(self._holds):
            info = p.getConstraintInfo(hold, physicsClientId=c)
            targets[g] = np.concatenate([info[7], info[9]])
        return np.concatenate(
            [
                pos,
                orn,
                lin,
                ang,
                np.ravel([s[0] for s in states]),
                np.ravel([s[1] for s in states]),
                targets.ravel(),
            ]
        ).astype(np.float64)

    def _set_physics_state(self, state: np.ndarray) -> None:
        c, b, n = self._client, self._body, self.n_segments - 1
        self._frames = None
        state = np.asarray(state, dtype=np.float64)
        quats = state[13 : 13 + 4 * n].reshape(n, 4)
        vels = state[13 + 4 * n : 13 + 7 * n].reshape(n, 3)
        p.resetBasePositionAndOrientation(
            b, state[:3].tolist(), state[3:7].tolist(), physicsClientId=c
        )
        p.resetBaseVelocity(b, state[7:10].tolist(), state[10:13].tolist(), physicsClientId=c)
        p.resetJointStatesMultiDof(
            b,
            self._joints,
            targetValues=quats.tolist(),
            targetVelocities=vels.tolist(),
            physicsClientId=c,
        )
        for g, hold in enumerate(self._holds):
            target = state[13 + 7 * n + 7 * g : 20 + 7 * n + 7 * g]
            p.changeConstraint(
                hold,
                target[:3].tolist(),
                jointChildFrameOrientation=target[3:].tolist(),
                maxForce=HOLD_FORCE,
                physicsClientId=c,
            )

    # ----------------------------------------------------------------- observations
    def _link_frames(self) -> tuple[np.ndarray, np.ndarray]:
        """Segment centres (N,3) and orientations (N,4, x y z w), cached until the next change."""
        if self._frames is None:
            self._frames = self._read_link_frames()
        return self._frames

    def _read_link_frames(self) -> tuple[np.ndarray, np.ndarray]:
        c, b = self._client, self._body
        base_pos, base_orn = p.getBasePositionAndOrientation(b, physicsClientId=c)
        links = p.getLinkStates(b, self._joints, computeForwardKinematics=1, physicsClientId=c)
        pos = np.array([base_pos, *(s[0] for s in links)], dtype=np.float64)
        orn = np.array([base_orn, *(s[1] for s in links)], dtype=np.float64)
        return pos, orn

    def segment_positions(self) -> np.ndarray:
        return self._link_frames()[0].copy()

    def segment_quaternions(self) -> np.ndarray:
        return quat_normalize(wxyz(self._link_frames()[1]))  # unit, w >= 0

    def cast_rays(
        self, origin: np.ndarray, directions: np.ndarray, grippers: bool = True
    ) -> RayHits:
        """PyBullet's rays (``rayTestBatch``) on a copy of the rod and grippers
        (:mod:`dlocli.backends.pybullet_rays`)."""
        if self._ray_scene is None:
            self._ray_scene = RayScene(
                self.n_segments, self.model.seg_length, self.rod.radius,
                self.gripper_half_extents(),
            )  # fmt: skip
        held = self.held_gripper_poses() if grippers else np.zeros((0, 7))
        self._ray_scene.place(*self._link_frames(), held)
        directions = np.asarray(directions, dtype=np.float64).reshape(-1, 3)
        return self._ray_scene.cast(origin, directions, 100.0 * self.rod.length)

    # ----------------------------------------------------------------- rendering
    def render(
        self, width: int = 480, height: int = 360, goal: np.ndarray | None = None
    ) -> np.ndarray:
        """Tiny-renderer image of the rod, grippers (grey boxes) and goal (green spheres)."""
        width, height = max(1, int(width)), max(1, int(height))
        grips = self._gripper_poses if self.spec.held_ends == "both" else self._gripper_poses[:1]
        try:
            return self._camera.image(grips, goal, width, height)
        except Exception:  # noqa: BLE001 - rendering must never crash a run
            return self._fallback_image(width, height, goal)

    def _fallback_image(self, width: int, height: int, goal: np.ndarray | None) -> np.ndarray:
        try:
            from dlocli.backends.render import render_rod

            return render_rod(self.segment_positions(), self.gripper_poses(), goal, width, height)
        except Exception:  # noqa: BLE001 - last resort: a blank frame, never a crash
            return np.full((height, width, 3), 255, dtype=np.uint8)

    def close(self) -> None:
        if self._ray_scene is not None:
            self._ray_scene.close()
            self._ray_scene = None
        if self._client >= 0 and p.isConnected(physicsClientId=self._client):
            p.disconnect(physicsClientId=self._client)
        self._client = -1

    def __del__(self) -> None:
        with contextlib.suppress(Exception):  # interpreter shutdown: pybullet may be gone
            self.close()
