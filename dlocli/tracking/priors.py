"""Where the tracker expects the cable's nodes in the next frame: a :class:`NodePrior`.

The tracker asks its prior for every frame's prediction, which seeds the fit and holds the
nodes the camera does not see. A prior sees only node positions (the markers), oldest
first, and the held nodes' next positions when the robot knows them: the learned marker
model (:mod:`dlocli.tracking.model_prior`) or :class:`ContinuityPrior`, geometry alone.
"""

from __future__ import annotations

from typing import Protocol, runtime_checkable

import numpy as np

from dlocli.errors import BadInput


@runtime_checkable
class NodePrior(Protocol):
    """Predicts the M tracked nodes one frame ahead."""

    def predict(self, history: np.ndarray, held_next: np.ndarray | None) -> np.ndarray:
        """(M,3) next node positions from ``history`` (T,M,3), the last T tracked frames,
        oldest first (T >= 1), and ``held_next`` (H,3), the held nodes' next positions in
        node order (None: unknown)."""
        ...


def check_history(history: np.ndarray, nodes: int) -> np.ndarray:
    """``history`` as a float (T, nodes, 3) array with T >= 1, or BadInput."""
    history = np.asarray(history, dtype=np.float64)
    if history.ndim != 3 or history.shape[1:] != (nodes, 3) or len(history) == 0:
        raise BadInput(
            f"a node prior needs the last frames as (T, {nodes}, 3) positions, got {history.shape}"
        )
    return history


class ContinuityPrior:
    """The cable's geometric continuity: each node keeps a damped share of its last velocity,
    held nodes go where the robot puts them, and no two neighbours end up farther apart than
    the cable between them (``rest_spacing``, (M-1,) metres along the cable).

    ``held`` (M,) flags the held nodes; ``damping`` is the share of the velocity kept (0:
    the cable stands still, 1: constant velocity)."""

    def __init__(self, held: np.ndarray, rest_spacing: np.ndarray, damping: float = 0.5):
        self.held = np.asarray(held, dtype=bool)
        self.rest_spacing = np.asarray(rest_spacing, dtype=np.float64)
        if self.rest_spacing.shape != (len(self.held) - 1,):
            raise BadInput(f"rest_spacing must hold {len(self.held) - 1} neighbour distances")
        self.damping = float(damping)

    def predict(self, history: np.ndarray, held_next: np.ndarray | None) -> np.ndarray:
        history = check_history(history, len(self.held))
        last = history[-1]
        velocity = history[-1] - history[-2] if len(history) > 1 else np.zeros_like(last)
        nxt = last + self.damping * velocity
        pinned = np.zeros(len(last), dtype=bool)
        if held_next is not None:
            nxt[self.held] = np.asarray(held_next, dtype=np.float64).reshape(-1, 3)
            pinned = self.held
        return limit_spacing(nxt, self.rest_spacing, pinned)


def limit_spacing(
    nodes: np.ndarray, longest: np.ndarray, pinned: np.ndarray, sweeps: int = 20
) -> np.ndarray:
    """(M,3) nodes moved so that no neighbours lie farther apart than ``longest`` (M-1,):
    red-black sweeps (the even edges, then the odd ones) that share each excess between the
    edge's ends, all of it to a free end beside a ``pinned`` node."""
    nodes = nodes.copy()
    free = (~pinned).astype(np.float64)
    for _ in range(sweeps):
        edge = nodes[1:] - nodes[:-1]
        if not (np.einsum("ij,ij->i", edge, edge) > longest**2 * (1 + 1e-9)).any():
            break
        for parity in (0, 1):
            a = np.arange(parity, len(nodes) - 1, 2)
            edge = nodes[a + 1] - nodes[a]
            length = np.maximum(np.linalg.norm(edge, axis=1), 1e-12)
            share = free[a] + free[a + 1]
            excess = np.maximum(length - longest[a], 0.0)
            move = (np.where(share > 0, excess / length / np.maximum(share, 1), 0.0))[:, None]
            nodes[a] += free[a, None] * move * edge
            nodes[a + 1] -= free[a + 1, None] * move * edge
    return nodes
