"""The tracked chain: nodes every few centimetres along the cable, the markers read off it,
its shape's Laplacian, its rest lengths, and its first placement on an unordered cloud.

Markers are far apart (a tenth of the cable); a chain of nodes a few centimetres apart
follows the cable's curve between them, and the markers are interpolated along it by arc
length (those beyond the cable's ends, on the grippers, straight on from its end).
"""

from __future__ import annotations

import numpy as np
from scipy.sparse.csgraph import dijkstra
from scipy.spatial import cKDTree


def interpolation_matrix(at: np.ndarray, knots: np.ndarray) -> np.ndarray:
    """(len(at), len(knots)) weights that interpolate values given at increasing ``knots``
    linearly at ``at`` (straight on beyond the first and last knots)."""
    right = np.clip(np.searchsorted(knots, at, side="right"), 1, len(knots) - 1)
    left = right - 1
    frac = (at - knots[left]) / (knots[right] - knots[left])
    weights = np.zeros((len(at), len(knots)))
    rows = np.arange(len(at))
    weights[rows, left] = 1.0 - frac
    weights[rows, right] += frac
    return weights


def laplacian(count: int) -> np.ndarray:
    """(count-2, count) second differences along the chain: its discrete curvature."""
    lap = np.zeros((max(count - 2, 0), count))
    for k in range(count - 2):
        lap[k, k : k + 3] = (1.0, -2.0, 1.0)
    return lap


def keep_lengths(
    nodes: np.ndarray, rest: np.ndarray, pinned: np.ndarray, sweeps: int = 4, tolerance=1e-4
) -> np.ndarray:
    """(K,3) nodes moved towards neighbour distances ``rest`` (K-1,): red-black sweeps (the
    even edges, then the odd ones, none sharing a node) that split each edge's error between
    its ends, all of it to the free end beside a ``pinned`` node; done early once every
    edge is within ``tolerance`` of its length (relative)."""
    nodes = nodes.copy()
    free = (~pinned).astype(np.float64)
    halves = []
    for parity in (0, 1):  # each half's edges, their ends' freedom and their shares
        a = np.arange(parity, len(nodes) - 1, 2)
        share = free[a] + free[a + 1]
        weight = np.where(share > 0, 1.0 / np.maximum(share, 1.0), 0.0)
        halves.append((a, a + 1, rest[a], weight, free[a, None], free[a + 1, None]))
    for _ in range(sweeps):
        worst = 0.0
        for a, b, length0, weight, free_a, free_b in halves:
            edge = nodes[b] - nodes[a]
            length = np.maximum(np.sqrt(np.einsum("ij,ij->i", edge, edge)), 1e-12)
            error = (length - length0) / length
            worst = max(worst, float(np.abs(error).max(initial=0.0)))
            move = (error * weight)[:, None] * edge
            nodes[a] += free_a * move
            nodes[b] -= free_b * move
        if worst < tolerance:
            break
    return nodes


def voxel_centroids(points: np.ndarray, size: float) -> np.ndarray:
    """The centroids of ``points`` (N,3) per cube of edge ``size``: an even thinning."""
    keys = np.floor(points / size).astype(np.int64)
    _, inverse, counts = np.unique(keys, axis=0, return_inverse=True, return_counts=True)
    sums = np.zeros((len(counts), 3))
    np.add.at(sums, inverse.ravel(), points)
    return sums / counts[:, None]


def ordered_path(points: np.ndarray, start: np.ndarray, end: np.ndarray) -> np.ndarray:
    """(P,3) the cheapest path from ``start`` to ``end`` through ``points`` where a step
    costs its squared length: many short steps along the cable beat one jump across a
    gap, and any gap can still be crossed."""
    nodes = np.concatenate([start[None], points, end[None]])
    diff = nodes[:, None, :] - nodes[None, :, :]
    cost = np.einsum("ijk,ijk->ij", diff, diff)
    _, previous = dijkstra(cost, indices=0, return_predecessors=True)
    path, node = [], len(nodes) - 1
    while node >= 0:
        path.append(node)
        node = previous[node]
    return nodes[path[::-1]]


def cable_ends(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two points far apart along the cloud (the farthest from the centre, then the farthest
    from that), the one with the smaller x first (the left gripper's side)."""
    first = points[np.argmax(np.linalg.norm(points - points.mean(0), axis=1))]
    second = points[np.argmax(np.linalg.norm(points - first, axis=1))]
    return (first, second) if first[0] <= second[0] else (second, first)


def without_loners(points: np.ndarray, reach: float) -> np.ndarray:
    """``points`` less those with no other point within ``reach`` (stray points; the
    cable's have neighbours along it), unless that leaves fewer than two."""
    if len(points) < 3:
        return points
    distance, _ = cKDTree(points).query(points, k=2)
    kept = points[distance[:, 1] <= reach]
    return kept if len(kept) >= 2 else points


def resample(path: np.ndarray, fractions: np.ndarray) -> np.ndarray:
    """Points at ``fractions`` (0 to 1) of the polyline ``path``'s length."""
    steps = np.linalg.norm(np.diff(path, axis=0), axis=1)
    along = np.concatenate([[0.0], np.cumsum(steps)])
    if along[-1] <= 0:
        return np.repeat(path[:1], len(fractions), axis=0)
    at = fractions * along[-1]
    return np.stack([np.interp(at, along, path[:, i]) for i in range(3)], axis=1)


def smooth(path: np.ndarray, window: int = 5) -> np.ndarray:
    """A moving average along the path, its ends kept."""
    if len(path) <= 2:
        return path
    kernel = np.ones(window) / window
    padded = np.concatenate([np.repeat(path[:1], window // 2, 0), path,
                             np.repeat(path[-1:], window // 2, 0)])  # fmt: skip
    out = np.stack([np.convolve(padded[:, i], kernel, mode="valid") for i in range(3)], axis=1)
    out[0], out[-1] = path[0], path[-1]
    return out


def initial_chain(
    points: np.ndarray,
    arcs: np.ndarray,
    thinning: float,
    ends: tuple[np.ndarray, np.ndarray] | None = None,
) -> np.ndarray:
    """(K,3) chain nodes at ``arcs`` (0 to L) laid along an unordered cloud (N,3): thinned
    to cubes of ``thinning`` metres, ordered from ``ends`` (the cable's end points where the
    grippers hold it; None: the cloud's two farthest points), smoothed and resampled by arc
    length."""
    thinned = voxel_centroids(points, thinning)
    start, end = ends if ends is not None else cable_ends(without_loners(thinned, 3 * thinning))
    path = smooth(ordered_path(thinned, np.asarray(start), np.asarray(end)))
    return resample(path, (arcs - arcs[0]) / (arcs[-1] - arcs[0]))


def near_points(points: np.ndarray, nodes: np.ndarray, reach: float) -> np.ndarray:
    """The mask of ``points`` within ``reach`` of some node (a k-d tree of the nodes)."""
    if len(points) == 0:
        return np.zeros(0, dtype=bool)
    distance, _ = cKDTree(nodes).query(points, distance_upper_bound=reach)
    return np.isfinite(distance)
