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
  diverges (benchmarks/backend_stability.py).
- The weld impedance *decreases* for violations beyond ~1 cm / 0.6 degrees (solimp dmin
  0.99 > dmax 0.8): a rod pulled taut by gripper motions that the separation guard cannot
  see (ends rotated apart) slips in the gripper instead of blowing up the simulation.
- The mocap targets lead the commanded poses by the weld's steady-state lag (about
  ``1.6 * timeconst * velocity``), so the pads track moving grippers without a lag.
"""

from __future__ import annotations

import numpy as np

from dlocli.backends.base import END_LOAD, KELVIN_VOIGT_REAL_INERTIA
from dlocli.backends.facts import MujocoFacts
from dlocli.backends.mujoco_common import (
    LIGHT_XML,
    MUJOCO_MAJOR,
    SCENE_XML,
    mujoco,
    rest_polyline,
)
from dlocli.backends.mujoco_common import (
    fmt_numbers as _fmt,
)
from dlocli.backends.mujoco_welded import (
    PAD_MASS_RATIO,
    PAD_STIFFNESS_RATIO,
    WELD_SOLIMP,
    WeldedMujocoRod,
)
from dlocli.backends.rays import CABLE, GRIPPER, NOTHING, RayHits
from dlocli.backends.rotations import quat_multiply, quat_normalize
from dlocli.specs import BackendSpec, RodSpec

#: segment lengths of the clamp stub behind a gripper: the plugin gives the joint that
#: follows a body the stiffness E I / (that body's length), so a half-segment stub makes the
#: joint at the gripper 2 E I / l, the compliance of the rod's half segment at its end
STUB_LENGTH = 0.5
RAYLEIGH_BETA = 0.05  # s; joint damping = beta * bending stiffness EI/l
#: the grippers' geom group (MuJoCo draws groups 0 to 2), and the groups rays see without them
GRIPPER_GROUP = 2
RAY_GROUPS_WITHOUT_GRIPPERS = np.array([1, 1, 0, 1, 1, 1], dtype=np.uint8)


# --------------------------------------------------------------------------- model building


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
  {SCENE_XML}
  <worldbody>
    {LIGHT_XML}
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


def composite_cable_removed() -> str:
    """The one line for a user who asks for the composite cable on MuJoCo 4 or later."""
    return (
        f"the mujoco backend is MuJoCo 3's composite cable, which MuJoCo {mujoco.__version__} "
        "no longer has; use --backend mujoco-flex (the flex rod), or pip install "
        "'mujoco==3.17.0' to bring the cable back"
    )


# --------------------------------------------------------------------------- small helpers
def _right_multiplier(c: np.ndarray) -> np.ndarray:
    """4x4 matrix B with ``q @ B == q * c`` (quaternion product), for vectorised frame fixes."""
    return quat_multiply(np.eye(4), c)


# --------------------------------------------------------------------------- backend
class MujocoCable(MujocoFacts, WeldedMujocoRod):
    """MuJoCo 3.x composite cable (elasticity plugin), grippers as welded mocap bodies.

    ``model``/``data`` are the compiled MuJoCo model and its state; each control period runs
    ``n_substeps`` physics steps of ``control_dt / n_substeps`` seconds (the largest step
    that divides the period and does not exceed ``physics_dt``).
    """

    name = "mujoco"
    # joint damping is implicit in MuJoCo: any Kelvin-Voigt time at the segments' real inertia
    capabilities = frozenset({END_LOAD, KELVIN_VOIGT_REAL_INERTIA})
    # The largest step that survives the stress tests (benchmarks/backend_stability.py):
    # random smooth gripper motion is stable at larger steps, but full-speed rotations that
    # pull the rod taut diverge above this one.
    default_physics_dt = 0.004

    @classmethod
    def unavailable(cls) -> str | None:
        return composite_cable_removed() if MUJOCO_MAJOR >= 4 else None

    def __init__(self, spec: BackendSpec | None = None, control_dt: float = 0.02) -> None:
        super().__init__(spec, control_dt)
        dt = self._substep(control_dt)
        rest = self.rest_gripper_poses()
        frame_fix = None

        def build() -> mujoco.MjModel:
            nonlocal frame_fix
            model, frame_fix = build_model(
                self.rod, rest, self.spec.held_ends == "both", dt, self.spec.gravity
            )
            return model

        self._compile(build)
        self._frame_fix = _right_multiplier(frame_fix)
        self._half_segment = 0.5 * self.rod.segment_length
        self._bind_views()
        self._start(control_dt)
        self._rest_state = self._settle(rest)
        self._set_joint_damping()
        self._air_damping = self.rod.air_damping or 0.0
        self.reset()

    # ----------------------------------------------------------------- physics hooks
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

    def _forced(self) -> bool:
        return bool(self._air_damping) or self._end_load is not None

    def _apply_forces(self) -> None:
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
        self._bind_ray_labels()
        self._rod_origins = d.xpos[rod]  # segment start points
        self._rod_axes = d.xmat[rod, 0::3]  # x axis (first xmat column) of each segment
        self._rod_quats = d.xquat[rod]

    def _bind_ray_labels(self) -> None:
        """What each geom is to a ray: its kind and rod segment (rays skip the invisible
        clamp stubs and a free end's gripper, whose alpha is 0)."""
        m, rod = self.model, self._rod_bodies
        body = m.geom_bodyid
        self._geom_kind = np.full(m.ngeom + 1, NOTHING, dtype=np.int8)  # [-1]: no hit
        self._geom_segment = np.full(m.ngeom + 1, -1, dtype=np.int32)
        on_rod = (body >= rod.start) & (body < rod.stop)
        self._geom_kind[:-1][on_rod] = CABLE
        self._geom_segment[:-1][on_rod] = body[on_rod] - rod.start
        grippers = np.isin(body, [m.body("grip0").id, m.body("grip1").id])
        self._geom_kind[:-1][grippers] = GRIPPER
        # a group of their own (still drawn) so that rays can pass through them
        m.geom_group[grippers] = GRIPPER_GROUP

    def cast_rays(
        self, origin: np.ndarray, directions: np.ndarray, grippers: bool = True
    ) -> RayHits:
        """MuJoCo's rays (``mj_multiRay``) on the cable's and grippers' geoms."""
        vec = np.ascontiguousarray(directions, dtype=np.float64).reshape(-1)
        count = len(vec) // 3
        geom = np.empty(count, dtype=np.int32)
        dist = np.empty(count)
        if count:
            pnt = np.ascontiguousarray(origin, dtype=np.float64)
            # mocap grippers are static bodies to MuJoCo: flg_static keeps them
            groups = None if grippers else RAY_GROUPS_WITHOUT_GRIPPERS
            mujoco.mj_multiRay(self.model, self.data, pnt, vec, groups, 1, -1, geom, dist, None,
                               count, 100.0 * self.rod.length)  # fmt: skip
        missed = geom < 0
        return RayHits(
            np.where(missed, np.inf, dist), self._geom_kind[geom], self._geom_segment[geom]
        )

    def _state_is_sane(self) -> bool:
        # NaN and huge values already fail _advance through MuJoCo's warnings; what is left
        # to catch is an exploded but finite rod (NaN also fails the comparison)
        reach = np.abs(self._rod_origins - self._gripper_poses[0, :3]).max()
        return bool(reach < 3.0 * self.rod.length)

    # ----------------------------------------------------------------- observations
    def segment_positions(self) -> np.ndarray:
        # body origins sit at segment starts; the body x axis points along the rod
        return self._rod_origins + self._half_segment * self._rod_axes

    def segment_quaternions(self) -> np.ndarray:
        quats = self._rod_quats @ self._frame_fix
        return quats * np.copysign(1.0, quats[:, :1])  # canonical sign, w >= 0
