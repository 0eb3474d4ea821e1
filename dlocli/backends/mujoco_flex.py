"""MuJoCo 4 backend: the rod as a 1D flex (a discrete elastic rod), grippers as welded pads.

The model is built by :mod:`dlocli.backends.flex_model` from the same
:class:`~dlocli.specs.RodSpec` as the composite cable ("mujoco"): SI material, half-segment
clamps, bending and twist damping as Kelvin-Voigt times, air damping and an end load as
applied forces. Observations follow dlocli.backends.base: segment i is the flex edge from
vertex i to vertex i+1, its centre the edge's midpoint, its frame the edge's material frame
(x along the edge). MuJoCo keeps each twisting edge's reference frame in ``mjData.plastic``
(the edge tangent and first director, set by each step); the material frame is that
director, carried to the current tangent by parallel transport and turned by the edge's
twist angle. Saved states include ``plastic`` (``mjSTATE_INTEGRATION`` holds it).

MuJoCo 3.17 compiles the same model without twist (a 1D flex there is twist-free), so this
backend refuses MuJoCo before 4.0.
"""

from __future__ import annotations

import warnings

import numpy as np

from dlocli.backends.base import END_LOAD, KELVIN_VOIGT_REAL_INERTIA
from dlocli.backends.facts import FlexFacts
from dlocli.backends.flex_damping import CLAMP
from dlocli.backends.flex_layout import FlexLayout, twist_body, vertex_body
from dlocli.backends.flex_model import flex_points, flex_xml
from dlocli.backends.mujoco_common import MUJOCO_MAJOR, mujoco
from dlocli.backends.mujoco_welded import WeldedMujocoRod
from dlocli.backends.rotations import cross3
from dlocli.specs import DEFAULT_DAMPING_TIME, BackendSpec


class MujocoFlex(FlexFacts, WeldedMujocoRod):
    """MuJoCo 4 flex rod (discrete elastic rod with twist), grippers as welded mocap pads;
    ``layout`` says which flex vertex and edge is what."""

    name = "mujoco-flex"
    capabilities = frozenset({END_LOAD, KELVIN_VOIGT_REAL_INERTIA})
    default_physics_dt = 0.004

    @classmethod
    def unavailable(cls) -> str | None:
        if MUJOCO_MAJOR >= 4:
            return None
        return (
            f"the mujoco-flex backend needs MuJoCo 4 (its rod twists there; MuJoCo "
            f"{mujoco.__version__}'s 1D flex cannot); use --backend mujoco, or pip install "
            "'mujoco>=4.0.1,<4.1'"
        )

    def __init__(self, spec: BackendSpec | None = None, control_dt: float = 0.02) -> None:
        super().__init__(spec, control_dt)
        dt = self._substep(control_dt)
        self.layout = FlexLayout(
            self.n_segments, self.spec.held_ends == "both", self.rod.clamp_compliance == "rigid"
        )
        rest = self.rest_gripper_poses()
        # settled with the default damping (an undamped rod would take long), then set
        xml = flex_xml(
            self.rod,
            rest,
            self.layout,
            dt,
            self.spec.gravity,
            DEFAULT_DAMPING_TIME,
            DEFAULT_DAMPING_TIME,
        )
        self._compile(lambda: mujoco.MjModel.from_xml_string(xml))
        self._bind_indices()
        self._start(control_dt)
        self._air_damping = 0.0
        self._rest_state = self._settle(rest)
        self._set_damping(*self._damping_times())
        self._air_damping = self.rod.air_damping or 0.0
        self.reset()

    def _damping_times(self) -> tuple[float, float]:
        """(bending, twist) Kelvin-Voigt times in seconds; None in the spec: the default."""
        rod = self.rod
        bending = DEFAULT_DAMPING_TIME if rod.bending_damping is None else rod.bending_damping
        twist = bending if rod.twist_damping is None else rod.twist_damping
        return bending, twist

    def _set_damping(self, bending: float, twist: float) -> None:
        """The damping times (s); the model was compiled and settled with the default.
        MuJoCo's flex damping (the bending time) damps twist as well, so the twist tendons
        add the difference; a twist time below the bending time cannot be had (warned)."""
        if twist < bending:
            warnings.warn(
                f"{self.name}: twist_damping {twist:g} s is below bending_damping {bending:g} s;"
                f" MuJoCo's flex damping gives twist the bending time, {bending:g} s",
                RuntimeWarning,
                stacklevel=3,
            )
        m = self.model
        m.flex_damping[0] = bending
        for i in range(m.ntendon):
            time_ = bending if m.tendon(i).name.startswith(CLAMP) else max(0.0, twist - bending)
            m.tendon_damping[i] *= time_ / DEFAULT_DAMPING_TIME

    # ----------------------------------------------------------------- indices and views
    def _bind_indices(self) -> None:
        """Cache what the hot path reads: vertex, twist and plastic addresses into mjData."""
        self._quaternions: np.ndarray | None = None  # of the current state, once asked
        m, layout = self.model, self.layout
        self._vertices = m.flex_vertadr[0] + np.arange(layout.n_vertices)[layout.rod_vertices]
        edges = np.arange(layout.n_vertices - 1)[layout.rod_edges]
        twisting = set(layout.twisting_edges())
        # per rod segment: the qpos / dof address of its twist angle (-1: fixed in a pad)
        self._twist_qpos = np.array(
            [m.joint(twist_body(k, layout)).qposadr[0] if k in twisting else -1 for k in edges]
        )
        self._twist_dof = np.array(
            [m.joint(twist_body(k, layout)).dofadr[0] if k in twisting else -1 for k in edges]
        )
        self._twisting = self._twist_qpos >= 0
        frames = m.flex_plasticadr[0] + 6 * edges  # each edge: tangent (3), first director (3)
        self._plastic_tangent = frames[:, None] + np.arange(3)
        self._plastic_director = frames[:, None] + 3 + np.arange(3)
        free = layout.free_vertices()
        self._free_dofs = np.array(
            [m.body_dofadr[m.body(vertex_body(i)).id] + np.arange(3) for i in free]
        )
        self._free_masses = m.body_mass[[m.body(vertex_body(i)).id for i in free], None]
        self._twist_inertia = m.dof_armature[self._twist_dof[self._twisting]] + np.array(
            [m.body_inertia[m.body(twist_body(k, layout)).id, 0] for k in edges[self._twisting]]
        )
        self._end_dofs = (
            None
            if layout.held_right
            else m.body_dofadr[m.body(vertex_body(layout.n_vertices - 1)).id] + np.arange(3)
        )

    # ----------------------------------------------------------------- physics hooks
    def _place_rest_shape(self, grippers: np.ndarray) -> None:
        """Pads on the (2,7) grippers and the free vertices on the sagging rest shape; the
        model was compiled straight (its stress-free shape)."""
        m, d = self.model, self.data
        for pad in range(1 + self.layout.held_right):
            address = m.jnt_qposadr[m.joint(f"pad{pad}").id]
            d.qpos[address : address + 7] = grippers[pad]
        points = flex_points(self.rod, self.layout, grippers)
        for vertex in self.layout.free_vertices():
            body = m.body(vertex_body(vertex)).id
            address = m.jnt_qposadr[m.body_jntadr[body]]
            d.qpos[address : address + 3] = points[vertex] - m.body_pos[body]

    def _apply_forces(self) -> None:
        """Air damping and the end load as generalized forces, from mj_step1's velocities."""
        d = self.data
        d.qfrc_applied[:] = 0.0
        if self._air_damping:
            # PyBullet's law on every vertex, -d (1 + |v|) m v, and on every twist angle
            velocity = d.qvel[self._free_dofs]
            rate = self._air_damping * (1.0 + np.linalg.norm(velocity, axis=1, keepdims=True))
            d.qfrc_applied[self._free_dofs] = -rate * self._free_masses * velocity
            spin = d.qvel[self._twist_dof[self._twisting]]
            spin_rate = self._air_damping * (1.0 + np.abs(spin))
            d.qfrc_applied[self._twist_dof[self._twisting]] = (
                -spin_rate * self._twist_inertia * spin
            )
        if self._end_load is not None:
            self._apply_end_load(*(np.array(v) for v in self._end_load))

    def _apply_end_load(self, force: np.ndarray, torque: np.ndarray) -> None:
        """Force on the free end vertex; torque about the last edge's axis on its twist angle,
        the rest of the torque as a couple of forces on the edge's two vertices."""
        d = self.data
        ends = d.flexvert_xpos[self._vertices[-2:]]
        edge = ends[1] - ends[0]
        length = float(np.linalg.norm(edge))
        tangent = edge / length
        axial = float(torque @ tangent)
        couple = np.cross(torque - axial * tangent, tangent) / length
        d.qfrc_applied[self._end_dofs] += force + couple
        before = self._free_dofs[-2]  # the second-to-last rod vertex is free (a cantilever)
        d.qfrc_applied[before] -= couple
        d.qfrc_applied[self._twist_dof[-1]] += axial

    def _forced(self) -> bool:
        return bool(self._air_damping) or self._end_load is not None

    def _refresh(self) -> None:
        """Body poses and flex vertices of the current state (mj_step leaves those of the
        state before its last integration)."""
        mujoco.mj_kinematics(self.model, self.data)
        mujoco.mj_flex(self.model, self.data)
        self._quaternions = None

    def _state_is_sane(self) -> bool:
        points = self.data.flexvert_xpos[self._vertices]
        reach = np.abs(points - self._gripper_poses[0, :3]).max()
        return bool(reach < 3.0 * self.rod.length)

    # ----------------------------------------------------------------- observations
    def edge_stretch(self) -> np.ndarray:
        """(N,) each segment's length over its rest length, minus one (the flex's edges are
        held by a stiff constraint, not rigid)."""
        points = self.data.flexvert_xpos[self._vertices]
        lengths = np.linalg.norm(points[1:] - points[:-1], axis=1)
        return lengths / self.rod.segment_length - 1.0

    def segment_positions(self) -> np.ndarray:
        points = self.data.flexvert_xpos[self._vertices]
        return 0.5 * (points[1:] + points[:-1])

    def segment_quaternions(self) -> np.ndarray:
        # computed once per state: the env reads them for the observation and the velocity
        if self._quaternions is None:
            self._quaternions = self._material_frames()
        return self._quaternions.copy()

    def _material_frames(self) -> np.ndarray:
        points = self.data.flexvert_xpos[self._vertices]
        edges = points[1:] - points[:-1]
        tangent = edges / np.linalg.norm(edges, axis=1, keepdims=True)
        plastic = self.data.plastic
        stored = plastic[self._plastic_tangent]
        director = parallel_transport(plastic[self._plastic_director], stored, tangent)
        angle = np.where(self._twisting, self.data.qpos[self._twist_qpos], 0.0)[:, None]
        binormal = cross3(tangent, director)
        material = np.cos(angle) * director + np.sin(angle) * binormal
        return frames_to_quaternions(tangent, material)


def parallel_transport(vectors: np.ndarray, before: np.ndarray, after: np.ndarray) -> np.ndarray:
    """(M,3) unit vectors normal to the unit tangents ``before`` turned by the smallest
    rotations that take ``before`` to ``after``, and re-made normal to ``after``."""
    axis = cross3(before, after)
    cos = np.einsum("ij,ij->i", before, after)[:, None]
    dot = np.einsum("ij,ij->i", axis, vectors)[:, None]
    turned = cos * vectors + cross3(axis, vectors) + dot * axis / (1.0 + cos)
    turned -= np.einsum("ij,ij->i", turned, after)[:, None] * after
    return turned / np.linalg.norm(turned, axis=1, keepdims=True)


def frames_to_quaternions(x_axes: np.ndarray, y_axes: np.ndarray) -> np.ndarray:
    """(M,4) unit quaternions (w x y z, w >= 0) of the frames with these orthonormal (M,3)
    x and y axes (MuJoCo's conversion: on a rod's few frames, cheaper than numpy's)."""
    matrices = np.stack([x_axes, y_axes, cross3(x_axes, y_axes)], axis=-1).reshape(-1, 9)
    quats = np.empty((len(matrices), 4))
    for quat, matrix in zip(quats, matrices, strict=True):
        mujoco.mju_mat2Quat(quat, matrix)
    return quats * np.copysign(1.0, quats[:, :1])
