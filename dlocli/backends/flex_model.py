"""The MJCF of the flex rod: a 1D ``flex`` (discrete elastic rod) held by two welded pads.

Layout (built from the :class:`~dlocli.specs.RodSpec` and the rest gripper poses):

- The rod's N + 1 vertices ``v0 .. vN`` (segment i is the edge from ``v_i`` to ``v_i+1``),
  plus a short "ghost" vertex behind each held end, on the pad, along the gripper's x axis.
  The flex's vertex list is ``ghost0, v0, ..., vN, ghost1`` (no ghost1 for a cantilever).
- Held vertices are fixed in a pad (the gripper's fingers): ``v0`` and ghost0 in pad 0,
  ``vN`` and ghost1 in pad 1; with ``clamp_compliance="rigid"`` also ``v1`` (``v_N-1``).
  Every other vertex is a body with three slide joints carrying the mass of the rod around
  it (a segment's mass; the free end of a cantilever half of it).
- Bending and twisting are MuJoCo's discrete elastic rod (``<elasticity young poisson>``,
  E = ``young_bending``): the moment at a vertex is E I times the curvature over the vertex's
  Voronoi length (half the two edges around it). The ghost edge is ``GHOST_LENGTH`` of a
  segment, so the vertex at a gripper has a Voronoi length of about half a segment: the
  clamp joint of stiffness 2 E I / l and 2 G J / l that ``clamp_compliance="half-segment"``
  asks for (with the real rod stopping at the gripper).
- Twist: MuJoCo 4 gives an edge a twist angle when a body named ``<flex>_twist_<edge>``
  (the flex's last edge: ``<flex>_twist``) with one hinge exists; its inertia about the
  hinge is the segment's polar inertia ``m r^2 / 2``. Edges inside a pad have none: their
  material frame is the pad's.
- The model is compiled straight (MuJoCo takes the compiled shape as stress-free) and the
  backend moves it to the sagging rest shape before settling.
- Edge lengths are held by the flex equality constraint at the stiffest time constant MuJoCo
  accepts (two steps) and an impedance near 1 at any violation, so that the task's pulls
  stretch edges little: ``young_tension`` is not used, as on the other backends.
- Damping: ``<elasticity damping>`` is stiffness-proportional (Kelvin-Voigt) on bending and
  twist alike, a time in seconds, integrated implicitly with the elasticity by MuJoCo's
  ``discrete`` integrator; tendons add what it leaves out (dlocli.backends.flex_damping).
  MuJoCo refuses elasticity damping on a flex pinned to mocap bodies, hence the pads:
  gravity-compensated free bodies welded to the mocap grippers as in the composite cable
  (dlocli.backends.mujoco_welded).
- No contacts: the rod hangs in the air and may pass through itself.
"""

from __future__ import annotations

import numpy as np

from dlocli.backends.flex_damping import clamps, damping_tendons, pad_sites
from dlocli.backends.flex_layout import FLEX, GHOST_LENGTH, FlexLayout, twist_body, vertex_body
from dlocli.backends.mujoco_common import LIGHT_XML, SCENE_XML, fmt_numbers, rest_polyline
from dlocli.backends.mujoco_welded import PAD_MASS_RATIO, PAD_STIFFNESS_RATIO, WELD_SOLIMP
from dlocli.specs import RodSpec

#: the edge-length constraint: near-hard at any violation, so that the task's pulls stretch
#: edges little (benchmarks/results/backend_stability_mujoco_rods.txt)
EDGE_SOLIMP = (0.9999, 0.9999, 0.001, 0.5, 2.0)


def _pad_xml(index: int, pose: np.ndarray, mass: float, inertia: float, sites: str) -> str:
    return (
        f'<body name="pad{index}" pos="{fmt_numbers(pose[:3])}" quat="{fmt_numbers(pose[3:])}" '
        f'gravcomp="1"><freejoint name="pad{index}"/><inertial pos="0 0 0" mass="{mass:.12g}" '
        f'diaginertia="{fmt_numbers([inertia] * 3)}"/>{sites}</body>'
    )


def _gripper_xml(index: int, pose: np.ndarray, marker: str, visible: bool) -> str:
    return (
        f'<body name="grip{index}" mocap="true" pos="{fmt_numbers(pose[:3])}" '
        f'quat="{fmt_numbers(pose[3:])}"><geom type="box" size="{marker}" '
        f'rgba="0.2 0.4 0.9 {0.6 if visible else 0.0}" contype="0" conaffinity="0"/></body>'
    )


def _slides(body: str) -> str:
    """Three slide joints along world x, y, z (the body is a child of the world): the body's
    position is three scalar joints, which fixed tendons can combine."""
    return "".join(
        f'<joint name="{body}_{axis}" type="slide" axis="{direction}"/>'
        for axis, direction in zip("xyz", ("1 0 0", "0 1 0", "0 0 1"), strict=True)
    )


def _vertex_xml(vertex: int, position: np.ndarray, mass: float, site: str) -> str:
    slides = _slides(vertex_body(vertex))
    # slide joints only: the rotary inertia is never used, any positive value compiles
    return (
        f'<body name="{vertex_body(vertex)}" pos="{fmt_numbers(position)}"><inertial pos="0 0 0" '
        f'mass="{mass:.12g}" diaginertia="1e-9 1e-9 1e-9"/>{slides}{site}</body>'
    )


def _twist_xml(name: str, polar_inertia: float) -> str:
    return (
        f'<body name="{name}"><inertial pos="0 0 0" mass="1e-9" '
        f'diaginertia="{fmt_numbers([polar_inertia] * 3)}"/>'
        f'<joint name="{name}" type="hinge" axis="1 0 0"/></body>'
    )


def straight_grippers(rod: RodSpec, grippers: np.ndarray) -> np.ndarray:
    """(2,7) gripper poses with the right one moved along +x to hold the rod straight: the
    model is compiled there, as MuJoCo takes the compiled shape as the stress-free one."""
    straight = grippers.copy()
    straight[1, :3] = grippers[0, :3] + [rod.length, 0.0, 0.0]
    return straight


def flex_points(rod: RodSpec, layout: FlexLayout, grippers: np.ndarray) -> np.ndarray:
    """World positions (m) of every flex vertex of the rod at rest between (2,7) gripper
    poses on the x axis (identity orientation): straight, or sagging in the xz-plane."""
    chord = float(np.linalg.norm(grippers[1, :3] - grippers[0, :3]))
    rod_points = rest_polyline(rod.n_segments, rod.length, chord) + grippers[0, :3]
    if not layout.ghosts:
        return rod_points
    ghost = [GHOST_LENGTH * rod.segment_length, 0.0, 0.0]
    points = np.concatenate([[rod_points[0] - ghost], rod_points])
    if layout.held_right:
        points = np.concatenate([points, [rod_points[-1] + ghost]])
    return points


def flex_xml(
    rod: RodSpec,
    grippers: np.ndarray,
    layout: FlexLayout,
    dt: float,
    gravity: float,
    bending_damping: float,
    twist_damping: float,
) -> str:
    """MJCF of the rod between the (2,7) gripper poses (on the x axis, identity orientation,
    the rest pose of dlocli.backends.base), compiled straight (:func:`straight_grippers`):
    the backend moves it to the rest pose before settling."""
    grippers = straight_grippers(rod, grippers)
    seg = rod.segment_length
    points = flex_points(rod, layout, grippers)
    segment_mass = rod.density * rod.area * seg
    tau = 2.0 * dt  # the stiffest constraint time constant MuJoCo accepts
    pad_mass = PAD_MASS_RATIO * rod.mass
    # rotational weld stiffness = inertia / (d tau)^2 (MuJoCo's solref in acceleration units)
    pad_inertia = PAD_STIFFNESS_RATIO * rod.bending_stiffness / seg * (WELD_SOLIMP[0] * tau) ** 2
    left, right = layout.held()
    owners, local = [], []
    for i, point in enumerate(points):
        pad = 0 if i in left else 1 if i in right else None
        if pad is None:
            owners.append(vertex_body(i))
            local.append(np.zeros(3))
        else:
            owners.append(f"pad{pad}")
            local.append(point - grippers[pad, :3])  # identity pad orientation at rest
    free = layout.free_vertices()
    last = layout.n_vertices - 1
    pad_site_xml, vertex_sites = ["", ""], {}
    for clamp in clamps(layout):
        pad_site_xml[clamp.pad] = pad_sites(clamp, local[clamp.held], seg)
        vertex_sites[clamp.free] = f'<site name="{clamp.rod_site}"/>'
    bodies = [
        _pad_xml(pad, grippers[pad], pad_mass, pad_inertia, pad_site_xml[pad])
        for pad in range(1 + layout.held_right)
    ]
    bodies += [
        _vertex_xml(
            i, points[i], segment_mass * (0.5 if i == last else 1.0), vertex_sites.get(i, "")
        )
        for i in free
    ]
    polar = 0.5 * segment_mass * rod.radius**2
    bodies += [_twist_xml(twist_body(k, layout), polar) for k in layout.twisting_edges()]
    marker = fmt_numbers(np.array([0.02, 0.03, 0.03]) * rod.length)
    solref = f"{tau:.12g} 1"
    solimp = fmt_numbers(WELD_SOLIMP)
    welds = [
        f'<weld name="hold{i}" body1="grip{i}" body2="pad{i}" relpose="0 0 0 1 0 0 0" '
        f'solref="{solref}" solimp="{solimp}"/>'
        for i in range(1 + layout.held_right)
    ]
    elements = " ".join(f"{k} {k + 1}" for k in range(layout.n_vertices - 1))
    return f"""
<mujoco model="dlocli_flex_rod">
  <option timestep="{dt:.12g}" integrator="discrete" gravity="0 0 {-gravity:.12g}">
    <flag contact="disable" autoreset="disable"/>
  </option>
  {SCENE_XML}
  <worldbody>
    {LIGHT_XML}
    {_gripper_xml(0, grippers[0], marker, True)}
    {_gripper_xml(1, grippers[1], marker, layout.held_right)}
    {"".join(bodies)}
  </worldbody>
  <deformable>
    <flex name="{FLEX}" dim="1" radius="{rod.radius:.12g}" body="{" ".join(owners)}"
          vertex="{fmt_numbers(np.array(local))}" element="{elements}" rgba="0.85 0.35 0.1 1">
      <elasticity young="{rod.young_bending:.12g}" poisson="{rod.poisson:.12g}"
                  damping="{bending_damping:.12g}"/>
    </flex>
  </deformable>
  <equality>
    <flex flex="{FLEX}" solref="{solref}" solimp="{fmt_numbers(EDGE_SOLIMP)}"/>
    {"".join(welds)}
  </equality>
  {damping_tendons(rod, layout, bending_damping, twist_damping)}
</mujoco>"""
