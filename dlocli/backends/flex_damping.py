"""Damping of the flex rod that MuJoCo's flex damping leaves out, as tendons (MuJoCo
integrates tendon damping implicitly).

MuJoCo's flex damping (``<elasticity damping>``, set to the bending time) damps bending and
twist, but on a curved rod only the growth of each vertex's curvature, not its turning: the
sagging rod's sideways swing, which bends it sideways at its clamps, escapes it. Two kinds
of tendons add what is missing:

- At each clamp (the pad vertex next to the free rod), two spatial tendons from pad sites
  one segment beside the clamp, along the pad's y and z axes, to the first free vertex damp
  its sideways motion relative to the pad: Kelvin-Voigt damping of the clamp joint in every
  direction (``bending_damping`` times its stiffness E I / Voronoi length, moved to the
  free vertex one segment away; a tendon at 45 degrees passes half of its damping sideways).
  Within the curvature's plane this adds to MuJoCo's own clamp damping.
- Twist beyond the bending time: at every vertex between two twisting edges, a fixed tendon
  on the difference of their twist angles, damping ``(twist_damping - bending_damping) G J /
  (Voronoi length)``. The vertex at a gripper has none: the pad's edge has no twist angle,
  and damping the next edge's angle alone would drag on a gripper that spins.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from dlocli.backends.flex_layout import FlexLayout, twist_body
from dlocli.backends.mujoco_common import fmt_numbers
from dlocli.specs import RodSpec

#: tendon name prefixes: scaled by the bending and the extra twist time
CLAMP, TWIST = "clamp", "twist"


@dataclass(frozen=True)
class Clamp:
    """A held rod end: the pad, its vertex next to the free rod and that free vertex."""

    pad: int
    held: int
    free: int

    def site(self, axis: str) -> str:
        return f"{CLAMP}{self.pad}{axis}"

    @property
    def rod_site(self) -> str:
        return f"{CLAMP}{self.pad}rod"


def clamps(layout: FlexLayout) -> list[Clamp]:
    """The clamps of the layout, left first."""
    left, right = layout.held()
    found = [Clamp(0, left[-1], left[-1] + 1)]
    if right:
        found.append(Clamp(1, right[0], right[0] - 1))
    return found


def pad_sites(clamp: Clamp, held_local: np.ndarray, segment: float) -> str:
    """The clamp's two pad sites, one segment beside the held vertex (pad frame, m)."""
    return "".join(
        f'<site name="{clamp.site(axis)}" pos="{fmt_numbers(held_local + offset)}"/>'
        for axis, offset in (("y", [0.0, segment, 0.0]), ("z", [0.0, 0.0, segment]))
    )


def clamp_tendons(rod: RodSpec, layout: FlexLayout, time: float) -> list[str]:
    """Spatial tendons of the clamps' damping, ``time`` the bending time (s)."""
    voronoi = layout.voronoi_lengths() * rod.segment_length
    tendons = []
    for clamp in clamps(layout):
        stiffness = rod.bending_stiffness / voronoi[clamp.held - 1]  # N m / rad
        # sideways at the free vertex: stiffness / l^2; the 45 degree tendon passes half
        damping = 2.0 * time * stiffness / rod.segment_length**2
        for axis in "yz":
            tendons.append(
                f'<spatial name="{clamp.site(axis)}" damping="{damping:.12g}">'
                f'<site site="{clamp.site(axis)}"/><site site="{clamp.rod_site}"/></spatial>'
            )
    return tendons


def twist_vertices(layout: FlexLayout) -> list[int]:
    """Flex vertices between two twisting edges (edge k joins vertices k and k + 1)."""
    twisting = set(layout.twisting_edges())
    return [i for i in range(1, layout.n_vertices - 1) if {i - 1, i} <= twisting]


def twist_tendons(rod: RodSpec, layout: FlexLayout, time: float) -> list[str]:
    """Fixed tendons of the twist damping beyond MuJoCo's, ``time`` in seconds."""
    voronoi = layout.voronoi_lengths() * rod.segment_length
    tendons = []
    for i in twist_vertices(layout):
        damping = time * rod.torsional_stiffness / voronoi[i - 1]
        joints = (
            f'<joint joint="{twist_body(i, layout)}" coef="1"/>'
            f'<joint joint="{twist_body(i - 1, layout)}" coef="-1"/>'
        )
        tendons.append(f'<fixed name="{TWIST}{i}" damping="{damping:.12g}">{joints}</fixed>')
    return tendons


def damping_tendons(rod: RodSpec, layout: FlexLayout, bending: float, twist: float) -> str:
    """MJCF ``<tendon>`` of the damping MuJoCo's flex damping leaves out (times in s)."""
    tendons = clamp_tendons(rod, layout, bending) + twist_tendons(rod, layout, twist)
    return f"<tendon>{''.join(tendons)}</tendon>"
