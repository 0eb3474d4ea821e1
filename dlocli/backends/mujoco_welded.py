"""What both MuJoCo rods share: held ends are gravity-compensated pads welded to mocap
grippers, stepped in substeps, settled to rest once, saved and restored as MuJoCo states.

The weld impedance *decreases* for violations beyond ~1 cm / 0.6 degrees (solimp dmin
0.99 > dmax 0.8): a rod pulled taut by gripper motions that the separation guard cannot see
(ends rotated apart) slips in the gripper instead of blowing up the simulation. The mocap
targets lead the commanded poses by the weld's steady-state lag (about
``1.6 * timeconst * velocity``), so the pads track moving grippers without a lag.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable

import numpy as np

from dlocli.backends.base import Backend
from dlocli.backends.mujoco_common import MujocoRendering, mujoco

PAD_MASS_RATIO = 3.0  # pad mass as a multiple of the rod mass
PAD_STIFFNESS_RATIO = 25.0  # weld rotational stiffness / joint bending stiffness
WELD_SOLIMP = (0.99, 0.8, 0.01, 0.5, 2.0)  # stiff near zero violation, yields beyond ~1 cm
SETTLE_MAX_TIME = 20.0  # s of simulated time to reach the rest state
SETTLE_TOLERANCE = 1e-6  # m/s, rad/s: largest generalized velocity counted as "at rest"
STATE_SPEC = mujoco.mjtState.mjSTATE_INTEGRATION  # everything mj_step reads, warmstart too


class WeldedMujocoRod(MujocoRendering, Backend):
    """Stepping, settling and state of a MuJoCo rod held by welded pads.

    ``model``/``data`` are the compiled MuJoCo model and its state; each control period runs
    ``n_substeps`` physics steps of ``control_dt / n_substeps`` seconds (the largest step
    that divides the period and does not exceed ``physics_dt``).

    A subclass compiles ``model`` (:meth:`_compile`), then calls :meth:`_start`; it may
    place the rest shape before settling, apply forces between ``mj_step1`` and
    ``mj_step2`` and refresh more than body poses after a step.
    """

    def _substep(self, control_dt: float) -> float:
        """Set ``n_substeps``, an integer number per control period none longer than
        ``physics_dt``; return the substep (s)."""
        self.n_substeps = max(1, math.ceil(control_dt / self.physics_dt - 1e-9))
        return control_dt / self.n_substeps

    def _compile(self, build: Callable[[], mujoco.MjModel]) -> None:
        try:
            self.model = build()
        except ValueError as exc:  # MuJoCo's compiler refuses, e.g., a too light segment
            reason = str(exc).strip().splitlines()[0][:160]
            raise self.unworkable_rod(f"MuJoCo cannot build this rod ({reason})") from exc
        self.data = mujoco.MjData(self.model)

    def _start(self, control_dt: float) -> None:
        """Lead the substep targets by the weld's lag and size the saved state."""
        dt = control_dt / self.n_substeps
        # substep fractions of the control period, shifted ahead by the steady-state weld lag
        # 2 dmax/d0 * timeconst * velocity (from MuJoCo's reference acceleration)
        lead = 2.0 * WELD_SOLIMP[1] / WELD_SOLIMP[0] * (2.0 * dt) / control_dt
        fractions = np.arange(1, self.n_substeps + 1) / self.n_substeps + lead
        self._led_fractions = fractions[:, None, None]
        self._state_size = mujoco.mj_stateSize(self.model, STATE_SPEC)
        self._renderer = None
        self._renderer_finalizer = None
        self._mocap_pos = self.data.mocap_pos
        self._mocap_quat = self.data.mocap_quat
        self._warnings = self.data.warning.number

    # ----------------------------------------------------------------- hooks
    def _place_rest_shape(self, grippers: np.ndarray) -> None:
        """Put the rod where it starts settling (default: the compiled shape)."""
        del grippers

    def _forced(self) -> bool:
        """Whether forces are applied between ``mj_step1`` and ``mj_step2``."""
        return False

    def _apply_forces(self) -> None:
        """Set applied forces from the state ``mj_step1`` left."""

    def _refresh(self) -> None:
        """Body poses of the current state (mj_step leaves those of the state before its
        last integration)."""
        mujoco.mj_kinematics(self.model, self.data)

    # ----------------------------------------------------------------- physics
    def _settle(self, grippers: np.ndarray) -> np.ndarray:
        """Simulate the grippers held still until the rod is at rest; return that state."""
        m, d = self.model, self.data
        mujoco.mj_resetData(m, d)
        d.mocap_pos[:] = grippers[:, :3]
        d.mocap_quat[:] = grippers[:, 3:]
        self._place_rest_shape(grippers)
        chunk = max(1, round(0.25 / m.opt.timestep))
        for _ in range(max(1, math.ceil(SETTLE_MAX_TIME / (chunk * m.opt.timestep)))):
            mujoco.mj_step(m, d, nstep=chunk)
            if np.max(np.abs(d.qvel)) < SETTLE_TOLERANCE or not np.all(np.isfinite(d.qvel)):
                break
        if not np.all(np.isfinite(d.qpos)) or d.warning.number.any():
            raise self.unworkable_rod("the rod's rest state diverged")
        d.time = 0.0
        return self._get_physics_state()

    def _reset_physics(self, seed: int | None) -> None:
        del seed  # no backend-internal noise: the rest state is deterministic
        self._set_physics_state(self._rest_state)

    def _advance(self, start: np.ndarray, end: np.ndarray) -> bool:
        m, d = self.model, self.data
        delta = end - start
        # the end rotation on the start's hemisphere, so that interpolation takes the short way
        for i, (q0, q1) in enumerate(zip(start[:, 3:].tolist(), end[:, 3:].tolist(), strict=True)):
            if sum(a * b for a, b in zip(q0, q1, strict=True)) < 0.0:
                delta[i, 3:] = -end[i, 3:] - start[i, 3:]
        # (n,2,7) substep targets, each led by the weld lag. Rotations are at most 0.02 rad per
        # control period, where nlerp and slerp agree to ~1e-7 rad; MuJoCo normalises mocap
        # quaternions itself.
        targets = start + self._led_fractions * delta
        forced = self._forced()
        for position, quat in zip(targets[:, :, :3], targets[:, :, 3:], strict=True):
            self._mocap_pos[:] = position
            self._mocap_quat[:] = quat
            if forced:
                mujoco.mj_step1(m, d)
                self._apply_forces()
                mujoco.mj_step2(m, d)
            else:
                mujoco.mj_step(m, d)
        self._refresh()
        return not self._warnings.any()

    def _time_raw_physics(self, control_steps: int) -> float:
        start = time.perf_counter()
        mujoco.mj_step(self.model, self.data, nstep=control_steps * self.n_substeps)
        return (time.perf_counter() - start) / control_steps

    def _get_physics_state(self) -> np.ndarray:
        state = np.empty(self._state_size)
        mujoco.mj_getState(self.model, self.data, state, STATE_SPEC)
        return state

    def _set_physics_state(self, state: np.ndarray) -> None:
        state = np.ascontiguousarray(state, dtype=np.float64)
        if state.shape != (self._state_size,):
            raise ValueError(
                f"the {self.name} backend's state must have {self._state_size} values, "
                f"got {state.shape}"
            )
        mujoco.mj_setState(self.model, self.data, state, STATE_SPEC)
        self.data.warning.number[:] = 0
        self._refresh()
