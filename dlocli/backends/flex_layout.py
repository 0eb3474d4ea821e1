"""Which vertices, edges, bodies and joints of the flex rod are what (dlocli.backends.flex_model
builds it, dlocli.backends.mujoco_flex reads it)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: the ghost edge behind a gripper, in segment lengths: short, so that the vertex at the
#: gripper has a Voronoi length of (1 + GHOST_LENGTH) / 2 segments (stiffness ~2 E I / l)
GHOST_LENGTH = 0.02
FLEX = "rod"


@dataclass(frozen=True)
class FlexLayout:
    """Which flex vertices and edges are what (indices into the flex's own lists).

    Half-segment clamps put a ghost vertex behind each held end; rigid clamps have none (the
    end segment itself lies in the pad, so the first bending vertex is v1, Voronoi length a
    whole segment: the rigid clamp's E I / l)."""

    n_segments: int
    held_right: bool
    rigid: bool

    @property
    def ghosts(self) -> int:
        """Ghost vertices before v0 (and after vN, when the right end is held)."""
        return 0 if self.rigid else 1

    @property
    def rod_vertices(self) -> slice:
        """v0 .. vN among the flex vertices."""
        return slice(self.ghosts, self.ghosts + self.n_segments + 1)

    @property
    def rod_edges(self) -> slice:
        """The N rod segments among the flex edges (edge k joins vertices k and k + 1)."""
        return slice(self.ghosts, self.ghosts + self.n_segments)

    @property
    def n_vertices(self) -> int:
        return self.n_segments + 1 + self.ghosts * (1 + self.held_right)

    def held(self) -> tuple[list[int], list[int]]:
        """Flex vertex indices fixed in pad 0 and in pad 1."""
        left = list(range(0, self.ghosts + 1 + self.rigid))
        if not self.held_right:
            return left, []
        return left, list(range(self.n_vertices - self.ghosts - 1 - self.rigid, self.n_vertices))

    def free_vertices(self) -> list[int]:
        left, right = self.held()
        return [i for i in range(self.n_vertices) if i not in left + right]

    def twisting_edges(self) -> list[int]:
        """Flex edges with a free vertex: a twist angle each (the others turn with a pad)."""
        free = set(self.free_vertices())
        return [k for k in range(self.n_vertices - 1) if k in free or k + 1 in free]

    def voronoi_lengths(self) -> np.ndarray:
        """Per interior flex vertex (1 .. n-2), half the two edges around it, in segments."""
        edges = np.ones(self.n_vertices - 1)
        if self.ghosts:
            edges[0] = GHOST_LENGTH
            if self.held_right:
                edges[-1] = GHOST_LENGTH
        return 0.5 * (edges[1:] + edges[:-1])


def twist_body(edge: int, layout: FlexLayout) -> str:
    """MuJoCo's name of an edge's twist body and joint: the flex's last edge has no number."""
    last = edge == layout.n_vertices - 2
    return f"{FLEX}_twist" if last else f"{FLEX}_twist_{edge}"


def vertex_body(vertex: int) -> str:
    return f"vertex{vertex}"
