"""MuJoCo 3.x backend: a ``composite`` cable with the ``mujoco.elasticity.cable`` plugin.

Model (built from the :class:`~dlocli.specs.RodSpec`, compiled once per backend):

- ``n_segments`` rigid cylinders (radius, density) chained by ball joints. The plugin gives
  each joint a bending stiffness ``E I / l`` (E = ``young_bending``) and a twisting stiffness
  ``G J / l`` with G = E / (2 (1 + ``poisson``)); its stress-free shape is straight
  (``flat``). Ball joints do not stretch, so the rod is inextensible: ``young_tension`` is
  not used (at 1e8 Pa the real one would stretch by ~1e-4 under its own weight).
- Joint damping ``RAYLEIGH_BETA * E I / l`` (stiffness-proportional, time constant 0.05 s):
  the slow shape modes of a 1 m rod stay underdamped, the fast segment modes are
  overdamped, the cantilever test settles in < 0.5 s. MuJoCo integrates joint damping
  implicitly, which is what keeps the (explicit) plugin stiffness stable at a 4 ms step even
  for short, stiff segments (the step is stable for dt < 2 beta in the linear analysis).
  The rod spec's ``bending_damping`` and ``twist_damping`` replace it per joint axis (the
  first degree of freedom of each ball joint is the twist about the rod axis) once the rest
  state has settled with the default; ``air_damping`` adds forces on every segment at
  every physics step, PyBullet's velocity damping law.
- No contacts (not even rod self-contact): the rod hangs in the air and may pass through
  itself when it is coiled by large gripper rotations.
- Clamps (the rod spec's ``clamp_compliance``, default "half-segment"): a joint at each
  held end stands for the half segment between the gripper and the first joint, stiffness
  2 E I / l and 2 G J / l, so the statics converge to the continuum's as 1/N^2 (a rigid end
  segment leaves out that compliance: a cantilever deflects (1 - 1/N)^2 of the beam's). The
  cable has an invisible, gravity-compensated stub body behind each gripper whose joint to
  the rod end is that clamp joint: the plugin's stiffness of the joint after a body is
  E I / (that body's length), so the left stub is half a segment long, and the right stub
  (whose joint follows a full segment) has twice the second moment.
- Each held rod end (its stub, or with "rigid" clamps the end segment) is rigidly part of a
  gravity-compensated "pad" body (the gripper's fingers): the first cable body is a jointless
  child of pad 0, pad 1 (``held_ends="both"`` only) a jointless child of the last one.
  Each pad is welded to a kinematic (mocap) body that follows the commanded gripper pose.
  A weld on the light end segment alone is far too soft at this stiffness; the pads'
  inertia makes the weld's rotational stiffness ``PAD_STIFFNESS_RATIO`` (25) times the
  joint bending stiffness, so the pad (with a rigid clamp, the held segment) stays within
  ~0.7 degrees and ~0.5 mm of a gripper moving at full speed.
  Stiffer pads hold the ends so rigidly that a rod pulled taut kinks at its end joint and
  diverges (100x: 7 in 10 stress episodes, 40x: 2 in 40, 25x and 15x: none in 100).
- The weld impedance *decreases* for violations beyond ~1 cm / 0.6 degrees (solimp dmin
  0.99 > dmax 0.8): a rod pulled taut by gripper motions that the separation guard cannot
  see (ends rotated apart) slips in the gripper instead of blowing up the simulation.
- The mocap targets lead the commanded poses by the weld's steady-state lag (about
  ``1.6 * timeconst * velocity``), so the pads track moving grippers without a lag.
"""

from __future__ import annotations

import contextlib
import ctypes.util
import math
import os
import sys
import time
import warnings
import weakref

import numpy as np

from dlocli.backends.base import END_LOAD, KELVIN_VOIGT_REAL_INERTIA, Backend
from dlocli.backends.facts import MujocoFacts
from dlocli.backends.render import finite_points, render_rod
from dlocli.backends.rotations import quat_multiply, quat_normalize
from dlocli.specs import BackendSpec, RodSpec


def _choose_headless_gl() -> str | None:
    """Without a display, ask MuJoCo for EGL (or OSMesa) if its libraries are present.

    MuJoCo reads MUJOCO_GL once, when it is imported. Returns the choice made, if any.
    """
    if "MUJOCO_GL" in os.environ or os.environ.get("DISPLAY"):
        return None
    find = ctypes.util.find_library
    if find("EGL") and (find("OpenGL") or find("GL")):
        os.environ["MUJOCO_GL"] = "egl"
    elif find("OSMesa"):
        os.environ["MUJOCO_GL"] = "osmesa"
    return os.environ.get("MUJOCO_GL")


def _forget_gl_imports(had_pyopengl_platform: bool) -> None:
    """Undo a failed ``import mujoco`` with our GL choice, so it can be imported without GL."""
    for name in [n for n in sys.modules if n.split(".")[0] in ("mujoco", "OpenGL")]:
        del sys.modules[name]
    if not had_pyopengl_platform:
        os.environ.pop("PYOPENGL_PLATFORM", None)  # MuJoCo's GL modules set it
    os.environ["MUJOCO_GL"] = "disable"


_had_pyopengl_platform = "PYOPENGL_PLATFORM" in os.environ
_gl_choice = _choose_headless_gl()
try:
    import mujoco
except Exception:  # a broken GL stack must not take the physics down: render() falls back
    if _gl_choice is None:
        raise
    _forget_gl_imports(_had_pyopengl_platform)
    import mujoco

#: segment lengths of the clamp stub behind a gripper: the plugin gives the joint that
#: follows a body the stiffness E I / (that body's length), so a half-segment stub makes the
#: joint at the gripper 2 E I / l, the compliance of the rod's half segment at its end
STUB_LENGTH = 0.5
RAYLEIGH_BETA = 0.05  # s; joint damping = beta * bending stiffness EI/l
PAD_MASS_RATIO = 3.0  # pad mass as a multiple of the rod mass
PAD_STIFFNESS_RATIO = 25.0  # weld rotational stiffness / joint bending stiffness
WELD_SOLIMP = (0.99, 0.8, 0.01, 0.5, 2.0)  # stiff near zero violation, yields beyond ~1 cm
SETTLE_MAX_TIME = 20.0  # s of simulated time to reach the rest state
SETTLE_TOLERANCE = 1e-6  # m/s, rad/s: largest generalized velocity counted as "at rest"
_STATE_SPEC = mujoco.mjtState.mjSTATE_INTEGRATION  # everything mj_step reads, warmstart too


def _keep_warnings_counted_only(message: str) -> None:
    """MuJoCo's warnings (an unstable simulation, ...) are counted in ``MjData.warning``,
    which the backend checks; printed, they would come before the one-line error, and MuJoCo
    would append them to a MUJOCO_LOG.TXT in the working directory."""
    del message


mujoco.set_mju_user_warning(_keep_warnings_counted_only)
_GL_BROKEN = False  # set once per process when no GL context can be made: no retry noise


# --------------------------------------------------------------------------- model building
def rest_polyline(n_segments: int, length: float, chord: float) -> np.ndarray:
    """(N+1,3) vertices (m) of a rod of equal segments from the origin to (chord, 0, 0).

    The first and last segments lie along +x (so both grippers have identity orientation)
    and the rod sags in the xz-plane with the profile of the first clamped buckling mode:
    segment angles ``-A sin(2 pi i / (N-1))``, A found by bisection to match the chord. A
    chord of at least the length gives a straight rod.
    """
    seg = length / n_segments
    if chord >= length * (1.0 - 1e-9):
        angles = np.zeros(n_segments)
    else:
        profile = np.sin(2.0 * np.pi * np.arange(n_segments) / (n_segments - 1))
        low, high = 0.0, 0.5 * np.pi
        for _ in range(60):  # chord(A) decreases monotonically on [0, pi/2]
            mid = 0.5 * (low + high)
            low, high = (mid, high) if seg * np.cos(mid * profile).sum() > chord else (low, mid)
        angles = -0.5 * (low + high) * profile
    steps = seg * np.stack([np.cos(angles), np.zeros(n_segments), np.sin(angles)], axis=1)
    return np.concatenate([np.zeros((1, 3)), np.cumsum(steps, axis=0)])


def _fmt(values: np.ndarray | tuple[float, ...] | list[float]) -> str:
    return " ".join(f"{float(v):.12g}" for v in np.ravel(values))


def _cable_xml(
    rod: RodSpec,
    grippers: np.ndarray,
    vertices: np.ndarray,
    dt: float,
    pad_mass: float,
    pad_inertia: float,
    held_right: bool,
    gravity: float,
) -> str:
    """MJCF of the cable, its left pad, both mocap grippers and the welds (pad 1 is added later)."""
    seg = rod.segment_length
    bend = rod.bending_stiffness / seg
    twist = rod.young_bending / (2.0 * (1.0 + rod.poisson))
    solref = f"{2.0 * dt:.12g} 1"  # the stiffest time constant MuJoCo accepts (refsafe)
    marker = _fmt(np.array([0.02, 0.03, 0.03]) * rod.length)
    right_weld = (
        (
            f'<weld name="hold1" body1="grip1" body2="pad1" relpose="0 0 0 1 0 0 0" '
            f'solref="{solref}" solimp="{_fmt(WELD_SOLIMP)}"/>'
        )
        if held_right
        else ""
    )
    return f"""
<mujoco model="dlocli_cable">
  <extension><plugin plugin="mujoco.elasticity.cable"/></extension>
  <option timestep="{dt:.12g}" integrator="implicitfast" gravity="0 0 {-gravity:.12g}">
    <flag contact="disable" autoreset="disable"/>
  </option>
  <visual><global offwidth="1920" offheight="1440"/></visual>
  <asset>
    <texture name="sky" type="skybox" builtin="gradient" rgb1="0.95 0.95 0.97"
             rgb2="0.75 0.8 0.88" width="64" height="64"/>
  </asset>
  <worldbody>
    <light pos="0 -1 3" dir="0 0.3 -1" directional="true"/>
    <body name="grip0" mocap="true" pos="{_fmt(grippers[0, :3])}" quat="{_fmt(grippers[0, 3:])}">
      <geom type="box" size="{marker}" rgba="0.2 0.4 0.9 0.6" contype="0" conaffinity="0"/>
    </body>
    <body name="grip1" mocap="true" pos="{_fmt(grippers[1, :3])}" quat="{_fmt(grippers[1, 3:])}">
      <geom type="box" size="{marker}" rgba="0.2 0.4 0.9 {0.6 if held_right else 0.0}"
            contype="0" conaffinity="0"/>
    </body>
    <body name="pad0" pos="{_fmt(grippers[0, :3])}" quat="{_fmt(grippers[0, 3:])}" gravcomp="1">
      <freejoint name="pad0"/>
      <inertial pos="0 0 0" mass="{pad_mass:.12g}" diaginertia="{_fmt([pad_inertia] * 3)}"/>
      <composite prefix="rod" type="cable" vertex="{_fmt(vertices)}" initial="none">
        <plugin plugin="mujoco.elasticity.cable">
          <config key="twist" value="{twist:.12g}"/>
          <config key="bend" value="{rod.young_bending:.12g}"/>
          <config key="flat" value="true"/>
        </plugin>
        <joint kind="main" damping="{RAYLEIGH_BETA * bend:.12g}"/>
        <geom type="cylinder" size="{rod.radius:.12g}" density="{rod.density:.12g}"
              rgba="0.85 0.35 0.1 1"/>
      </composite>
    </body>
  </worldbody>
  <equality>
    <weld name="hold0" body1="grip0" body2="pad0" relpose="0 0 0 1 0 0 0"
          solref="{solref}" solimp="{_fmt(WELD_SOLIMP)}"/>
    {right_weld}
  </equality>
</mujoco>"""


def _conj(q: np.ndarray) -> np.ndarray:
    return q * np.array([1.0, -1.0, -1.0, -1.0])


def _chain_quat(spec: mujoco.MjSpec, names: list[str]) -> np.ndarray:
    """Orientation of the last named body relative to the parent of the first (w x y z)."""
    quat = np.array([1.0, 0.0, 0.0, 0.0])
    for name in names:
        quat = quat_multiply(quat, np.asarray(spec.body(name).quat, dtype=np.float64))
    return quat_normalize(quat)


def build_model(
    rod: RodSpec, grippers: np.ndarray, held_right: bool, dt: float, gravity: float = 9.81
) -> tuple[mujoco.MjModel, np.ndarray]:
    """Compile the cable model for rest gripper poses (2,7).

    Returns the model and the constant quaternion ``c`` that maps a MuJoCo cable body frame
    to the dlocli segment frame (``q_segment = q_body * c``): the composite rotates its body
    frames about the rod axis for curved ``vertex`` shapes.
    """
    chord = float(np.linalg.norm(grippers[1, :3] - grippers[0, :3]))
    vertices = rest_polyline(rod.n_segments, rod.length, chord)
    seg = rod.segment_length
    stubs = clamp_stubs(rod, held_right)
    if stubs[0]:  # behind the left gripper, along the (level) first segment
        vertices = np.concatenate([[[-STUB_LENGTH * seg, 0.0, 0.0]], vertices])
    if stubs[1]:
        vertices = np.concatenate([vertices, [vertices[-1] + [STUB_LENGTH * seg, 0.0, 0.0]]])
    tau = 2.0 * dt
    pad_mass = PAD_MASS_RATIO * rod.mass
    # rotational weld stiffness = inertia / (d tau)^2 (MuJoCo's solref in acceleration units)
    pad_inertia = PAD_STIFFNESS_RATIO * rod.bending_stiffness / seg * (WELD_SOLIMP[0] * tau) ** 2
    xml = _cable_xml(rod, grippers, vertices, dt, pad_mass, pad_inertia, held_right, gravity)
    spec = mujoco.MjSpec.from_string(xml)
    bodies = len(vertices) - 1
    names = ["rodB_first"] + [f"rodB_{i}" for i in range(1, bodies - 1)] + ["rodB_last"]
    frame_fix = _conj(np.asarray(spec.body("rodB_first").quat, dtype=np.float64))
    for name, present in zip(("rodB_first", "rodB_last"), stubs, strict=True):
        if present:
            _make_stub(spec.body(name), rod.radius)
    if stubs[1]:
        # the plugin's joint stiffness is E I / (previous body's length): a full segment
        # here, so the right stub doubles its second moment instead (radius 2^(1/4) r)
        spec.body("rodB_last").first_geom().size[0] = rod.radius * 2.0**0.25
    if held_right:
        # pad 1 sits at the end point of the last segment (the right stub's start), in the
        # dlocli segment frame
        spec.body("rodB_last").add_body(
            name="pad1",
            pos=[0.0 if stubs[1] else seg, 0.0, 0.0],
            quat=frame_fix.tolist(),
            mass=pad_mass,
            inertia=[pad_inertia] * 3,
            gravcomp=1.0,
            explicitinertial=True,
        )
        # the right gripper must coincide with pad 1 at qpos0 for an unstressed weld
        last = quat_multiply(_chain_quat(spec, names), frame_fix)
        if abs(abs(float(last[0])) - 1.0) > 1e-6:
            raise RuntimeError("rest shape: the last segment does not lie along +x")
    return spec.compile(), frame_fix


def clamp_stubs(rod: RodSpec, held_right: bool) -> tuple[bool, bool]:
    """Whether the cable has a stub body behind (left, right) gripper: the clamp joints."""
    compliant = rod.clamp_compliance == "half-segment"
    return compliant, compliant and held_right


def _make_stub(body: mujoco.MjsBody, radius: float) -> None:
    """A clamp stub: invisible, weightless (part of its pad), the rod's radius by default."""
    body.gravcomp = 1.0
    geom = body.first_geom()
    geom.rgba[3] = 0.0
    geom.size[0] = radius


# --------------------------------------------------------------------------- small helpers
def _right_multiplier(c: np.ndarray) -> np.ndarray:
    """4x4 matrix B with ``q @ B == q * c`` (quaternion product), for vectorised frame fixes."""
    return quat_multiply(np.eye(4), c)


# --------------------------------------------------------------------------- backend
class MujocoCable(MujocoFacts, Backend):
    """MuJoCo 3.x composite cable (elasticity plugin), grippers as welded mocap bodies.

    ``model``/``data`` are the compiled MuJoCo model and its state; each control period runs
    ``n_substeps`` physics steps of ``control_dt / n_substeps`` seconds (the largest step
    that divides the period and does not exceed ``physics_dt``).
    """

    name = "mujoco"
    # joint damping is implicit in MuJoCo: any Kelvin-Voigt time at the segments' real inertia
    capabilities = frozenset({END_LOAD, KELVIN_VOIGT_REAL_INERTIA})
    # The largest step that survives the stress tests (benchmarks/backend_stability.py):
    # random smooth gripper motion is stable even at 10 ms, but full-speed rotations that pull
    # the rod taut diverge in 0/100 episodes at 4 ms, 2/40 at 5 ms, 7/10 at 10 ms.
    default_physics_dt = 0.004

    def __init__(self, spec: BackendSpec | None = None, control_dt: float = 0.02) -> None:
        super().__init__(spec, control_dt)
        # an integer number of substeps per control period, none longer than physics_dt
        self.n_substeps = max(1, math.ceil(control_dt / self.physics_dt - 1e-9))
        dt = control_dt / self.n_substeps
        rest = self.rest_gripper_poses()
        try:
            self.model, frame_fix = build_model(
                self.rod, rest, self.spec.held_ends == "both", dt, self.spec.gravity
            )
        except ValueError as exc:  # MuJoCo's compiler refuses, e.g., a too light segment
            reason = str(exc).strip().splitlines()[0][:160]
            raise self.unworkable_rod(f"MuJoCo cannot build this rod ({reason})") from exc
        self.data = mujoco.MjData(self.model)
        self._frame_fix = _right_multiplier(frame_fix)
        self._half_segment = 0.5 * self.rod.segment_length
        self._bind_views()
        # substep fractions of the control period, shifted ahead by the steady-state weld lag
        # 2 dmax/d0 * timeconst * velocity (from MuJoCo's reference acceleration)
        lead = 2.0 * WELD_SOLIMP[1] / WELD_SOLIMP[0] * (2.0 * dt) / control_dt
        fractions = np.arange(1, self.n_substeps + 1) / self.n_substeps + lead
        self._led_fractions = fractions[:, None, None]
        self._state_size = mujoco.mj_stateSize(self.model, _STATE_SPEC)
        self._renderer: mujoco.Renderer | None = None
        self._renderer_finalizer: weakref.finalize | None = None
        self._rest_state = self._settle(rest)
        self._set_joint_damping()
        self._air_damping = self.rod.air_damping or 0.0
        self.reset()

    # ----------------------------------------------------------------- physics hooks
    def _settle(self, grippers: np.ndarray) -> np.ndarray:
        """Simulate the grippers held still until the rod is at rest; return that state."""
        m, d = self.model, self.data
        mujoco.mj_resetData(m, d)
        d.mocap_pos[:] = grippers[:, :3]
        d.mocap_quat[:] = grippers[:, 3:]
        chunk = max(1, round(0.25 / m.opt.timestep))
        for _ in range(max(1, math.ceil(SETTLE_MAX_TIME / (chunk * m.opt.timestep)))):
            mujoco.mj_step(m, d, nstep=chunk)
            if np.max(np.abs(d.qvel)) < SETTLE_TOLERANCE or not np.all(np.isfinite(d.qvel)):
                break
        if not np.all(np.isfinite(d.qpos)) or d.warning.number.any():
            raise self.unworkable_rod("the rod's rest state diverged")
        d.time = 0.0
        return self._get_physics_state()

    def _set_joint_damping(self) -> None:
        """The rod spec's bending and twist damping, where it sets them (the compiled model
        holds the default, ``RAYLEIGH_BETA`` times the bending stiffness, on every axis)."""
        rod, seg = self.rod, self.rod.segment_length
        dofs = self.model.dof_damping[self._rod_dofs].reshape(-1, 3)  # (twist, bend, bend)
        scale = self._joint_stiffness
        if rod.bending_damping is not None:
            dofs[:, 1:] = rod.bending_damping * rod.bending_stiffness / seg
            if rod.twist_damping is None:  # the default twist coefficient is the bending one
                dofs[:, 0] = dofs[:, 1]
        if rod.twist_damping is not None:
            dofs[:, 0] = rod.twist_damping * rod.torsional_stiffness / seg
        # a clamp joint is stiffer, so its damping is too (the same material)
        self.model.dof_damping[self._rod_dofs] = (dofs * scale[:, None]).ravel()

    def _apply_segment_forces(self) -> None:
        """Air damping and the end load as applied forces, from the state mj_step1 left."""
        if self._air_damping:
            self._apply_air_damping()
        else:
            self.data.xfrc_applied[self._rod_bodies] = 0.0
        if self._end_load is not None:
            force, torque = (np.array(v) for v in self._end_load)
            last = self._rod_bodies.stop - 1
            end = self._rod_origins[-1] + 2.0 * self._half_segment * self._rod_axes[-1]
            arm = end - self.data.xipos[last]  # xfrc_applied acts at the centre of mass
            self.data.xfrc_applied[last, :3] += force
            self.data.xfrc_applied[last, 3:] += torque + np.cross(arm, force)

    def _apply_air_damping(self) -> None:
        """Set each segment's applied force and torque to PyBullet's velocity damping,
        ``-d (1 + |v|) m v`` and ``-d (1 + |w|) I w``, from the velocities mj_step1 left."""
        d, rod = self.data, self._rod_bodies
        spin = d.cvel[rod, :3]  # world-frame angular velocity
        # cvel's linear part is the velocity at the root's subtree centre of mass
        arm = d.xipos[rod] - d.subtree_com[self.model.body_rootid[rod]]
        velocity = d.cvel[rod, 3:] + np.cross(spin, arm)
        rate = self._air_damping * (1.0 + np.linalg.norm(velocity, axis=1, keepdims=True))
        d.xfrc_applied[rod, :3] = -rate * self._rod_masses * velocity
        frames = d.ximat[rod].reshape(-1, 3, 3)  # principal axes of inertia, world frame
        local = np.einsum("nji,nj->ni", frames, spin) * self.model.body_inertia[rod]
        spin_rate = self._air_damping * (1.0 + np.linalg.norm(spin, axis=1, keepdims=True))
        d.xfrc_applied[rod, 3:] = -spin_rate * np.einsum("nij,nj->ni", frames, local)

    def _reset_physics(self, seed: int | None) -> None:
        del seed  # no backend-internal noise: the rest state is deterministic
        self._set_physics_state(self._rest_state)

    def _bind_views(self) -> None:
        """Cache numpy views into mjData: the hot path then pays no attribute lookups.

        They stay valid (MuJoCo never reallocates mjData) and always show the current state.
        """
        d = self.data
        first = self.model.body("rodB_first").id
        stubs = clamp_stubs(self.rod, self.spec.held_ends == "both")
        rod = slice(first + stubs[0], first + stubs[0] + self.n_segments)
        self._rod_bodies = rod
        self._rod_masses = self.model.body_mass[rod, None]
        # the ball joints of the cable, 3 dofs each: those of segments 1 .. N-1, and those of
        # segment 0 and the right stub where the clamps are compliant (the first cable body
        # is fixed in pad 0)
        last = self.model.body("rodB_last").id
        cable = np.arange(first + 1, last + 1)
        joints = self.model.jnt_dofadr[np.isin(self.model.jnt_bodyid, cable)]
        self._rod_dofs = (joints[:, None] + np.arange(3)).ravel()
        # each joint's stiffness in units of the segment's (E I / l, G J / l): 2 at a clamp
        self._joint_stiffness = np.ones(len(joints))
        self._joint_stiffness[0] += stubs[0]
        self._joint_stiffness[-1] += stubs[1]
        self._rod_origins = d.xpos[rod]  # segment start points
        self._rod_axes = d.xmat[rod, 0::3]  # x axis (first xmat column) of each segment
        self._rod_quats = d.xquat[rod]
        self._mocap_pos = d.mocap_pos
        self._mocap_quat = d.mocap_quat
        self._warnings = d.warning.number

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
        for position, quat in zip(targets[:, :, :3], targets[:, :, 3:], strict=True):
            self._mocap_pos[:] = position
            self._mocap_quat[:] = quat
            if self._air_damping or self._end_load is not None:
                mujoco.mj_step1(m, d)
                self._apply_segment_forces()
                mujoco.mj_step2(m, d)
            else:
                mujoco.mj_step(m, d)
        # mj_step leaves body poses of the state before its last integration: refresh them
        mujoco.mj_kinematics(m, d)
        return not self._warnings.any()

    def _state_is_sane(self) -> bool:
        # NaN and huge values already fail _advance through MuJoCo's warnings; what is left
        # to catch is an exploded but finite rod (NaN also fails the comparison)
        reach = np.abs(self._rod_origins - self._gripper_poses[0, :3]).max()
        return bool(reach < 3.0 * self.rod.length)

    def _time_raw_physics(self, control_steps: int) -> float:
        start = time.perf_counter()
        mujoco.mj_step(self.model, self.data, nstep=control_steps * self.n_substeps)
        return (time.perf_counter() - start) / control_steps

    def _get_physics_state(self) -> np.ndarray:
        state = np.empty(self._state_size)
        mujoco.mj_getState(self.model, self.data, state, _STATE_SPEC)
        return state

    def _set_physics_state(self, state: np.ndarray) -> None:
        state = np.ascontiguousarray(state, dtype=np.float64)
        if state.shape != (self._state_size,):
            raise ValueError(
                f"MuJoCo cable state must have {self._state_size} values, got {state.shape}"
            )
        mujoco.mj_setState(self.model, self.data, state, _STATE_SPEC)
        self.data.warning.number[:] = 0
        mujoco.mj_kinematics(self.model, self.data)

    # ----------------------------------------------------------------- observations
    def segment_positions(self) -> np.ndarray:
        # body origins sit at segment starts; the body x axis points along the rod
        return self._rod_origins + self._half_segment * self._rod_axes

    def segment_quaternions(self) -> np.ndarray:
        quats = self._rod_quats @ self._frame_fix
        return quats * np.copysign(1.0, quats[:, :1])  # canonical sign, w >= 0

    # ----------------------------------------------------------------- rendering
    def render(
        self, width: int = 480, height: int = 360, goal: np.ndarray | None = None
    ) -> np.ndarray:
        """Offscreen MuJoCo image if a GL context can be made, else the matplotlib fallback.

        A goal that is not a finite (M,3) array is not drawn.
        """
        goal_points = finite_points(goal)
        try:
            image = self._render_gl(width, height, goal_points)
        except Exception as exc:  # any GL failure means "no GL here": fall back, never crash
            _mark_gl_broken(exc)
            image = None
        if image is not None:
            return image
        try:
            return render_rod(
                self.segment_positions(),
                self.gripper_poses(),
                goal_points,
                width,
                height,
                rod_length=self.rod.length,
            )
        except Exception as exc:  # a blank frame beats a crashed episode or video
            warnings.warn(
                f"rod rendering failed ({exc!r}); returning a blank image",
                RuntimeWarning,
                stacklevel=2,
            )
            return np.full((max(1, int(height)), max(1, int(width)), 3), 255, dtype=np.uint8)

    def _render_gl(self, width: int, height: int, goal: np.ndarray | None) -> np.ndarray | None:
        if _GL_BROKEN or not hasattr(mujoco, "Renderer"):
            return None
        offscreen = self.model.vis.global_
        if width > offscreen.offwidth or height > offscreen.offheight:
            return None
        renderer = self._renderer
        if renderer is None or (renderer.width, renderer.height) != (width, height):
            self._close_renderer()
            renderer = self._renderer = mujoco.Renderer(self.model, height, width)
            # close it before interpreter exit: MuJoCo's EGL atexit hook (registered earlier,
            # so run later) would otherwise leave GLContext.__del__ failing noisily
            self._renderer_finalizer = weakref.finalize(self, _close_quietly, renderer)
        renderer.update_scene(self.data, camera=self._camera())
        if goal is not None:
            self._add_goal(renderer.scene, goal)
        return renderer.render().copy()

    def _camera(self) -> mujoco.MjvCamera:
        """A fixed free camera in front of the workspace (looking along +y, x to the right)."""
        camera = mujoco.MjvCamera()
        camera.type = mujoco.mjtCamera.mjCAMERA_FREE
        camera.lookat[:] = (0.0, 0.0, 0.7 * self.rod.length)
        camera.distance = 1.8 * self.rod.length  # the 45 degree view spans the workspace
        camera.azimuth = 90.0
        camera.elevation = -10.0
        return camera

    def _add_goal(self, scene: mujoco.MjvScene, goal: np.ndarray) -> None:
        """Goal segment centres (M,3) as small green spheres (scene user geoms)."""
        size = np.array([1.5 * self.rod.radius, 0.0, 0.0])
        rgba = np.array([0.1, 0.8, 0.2, 0.7], dtype=np.float32)
        eye = np.eye(3).ravel()
        for point in goal[: max(0, scene.maxgeom - scene.ngeom)]:
            mujoco.mjv_initGeom(
                scene.geoms[scene.ngeom], mujoco.mjtGeom.mjGEOM_SPHERE, size, point, eye, rgba
            )
            scene.ngeom += 1

    def _close_renderer(self) -> None:
        if self._renderer_finalizer is not None:
            self._renderer_finalizer.detach()
            self._renderer_finalizer = None
        if self._renderer is not None:
            renderer, self._renderer = self._renderer, None
            _close_quietly(renderer)

    def close(self) -> None:
        self._close_renderer()


def _close_quietly(renderer: mujoco.Renderer) -> None:
    # a half-made or already torn-down GL context has nothing left to release
    with contextlib.suppress(Exception):
        renderer.close()


def _mark_gl_broken(exc: Exception) -> None:
    global _GL_BROKEN
    if not _GL_BROKEN:
        warnings.warn(
            f"MuJoCo offscreen rendering unavailable ({type(exc).__name__}); "
            "using the matplotlib renderer",
            RuntimeWarning,
            stacklevel=3,
        )
    _GL_BROKEN = True
