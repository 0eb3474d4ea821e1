"""The tracker: ordered cable nodes from each frame's unordered, noisy, partial point cloud.

A Gaussian mixture whose centroids are a chain of nodes along the cable, fitted by EM to
each frame (in the family of CPD trackers: CDCPD, TrackDLO), with the chain's shape held:

- E step: each point's responsibilities over the nodes, a uniform share for stray points.
- M step: the nodes minimising the points' weighted squared distances, plus the chain's
  Laplacian (curvature) kept close to the predicted shape's, plus a pull towards the
  predicted positions that is weak for seen nodes and strong for hidden ones (one linear
  solve, the same matrix for x, y and z); the held nodes stay where the robot puts them.
  Then the nodes are moved back to the cable's rest spacing (it neither stretches nor
  shrinks).
- A node is seen when the points it explains reach a share of the cable's points per node.

The prediction comes from a :class:`~dlocli.tracking.priors.NodePrior` on the markers
(their motion, spread along the chain); the first frame is laid out from its cloud, ordered
from the grippers. A camera sees the cable's near surface: every point is moved away from
the camera by the mean depth of a cylinder's visible surface behind its front (pi/4 of the
radius), so the chain follows the cable's axis, where the markers are.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from dlocli.errors import BadInput
from dlocli.tracking.camera import CloudFrame
from dlocli.tracking.chain import (
    initial_chain,
    interpolation_matrix,
    keep_lengths,
    laplacian,
    near_points,
)
from dlocli.tracking.priors import ContinuityPrior, NodePrior
from dlocli.tracking.spec import TrackerSpec

HISTORY = 3  # frames of tracked markers the prior sees
FIRST_FRAME_ITERATIONS = 3  # times the per-frame EM iterations, for the first frame
MIN_SIGMA = 1e-3  # m: the mixture's narrowest width
GATE = 4.0  # points farther than this many node spacings from the predicted chain: stray
FAR = 1e6  # m^2: the squared distance that gives a node no points


@dataclass
class TrackedFrame:
    """The tracker's answer for one frame: ``markers`` (M,3) positions, ``visible`` (M,)
    whether the camera saw each one, ``visibility`` (M,) the share of its expected points
    (0 to 1), and ``chain`` (K,3) the fitted nodes."""

    markers: np.ndarray
    visible: np.ndarray
    visibility: np.ndarray
    chain: np.ndarray


class CableTracker:
    """Tracks M markers at arc lengths ``arc`` (M,) (metres from the cable's left end, those
    beyond its ends on the grippers) of a cable ``length`` metres long and ``radius`` metres
    thick; ``held`` (M,) flags the markers the robot places (its grippers hold them)."""

    def __init__(
        self,
        arc: np.ndarray,
        held: np.ndarray,
        length: float,
        radius: float,
        spec: TrackerSpec | None = None,
        prior: NodePrior | None = None,
    ) -> None:
        self.spec = spec or TrackerSpec()
        self.arc = np.asarray(arc, dtype=np.float64)
        self.held = np.asarray(held, dtype=bool)
        self.length, self.radius = float(length), float(radius)
        count = max(2, round(1.0 / self.spec.spacing) + 1)
        on_cable = self.arc[self.held & (self.arc >= 0) & (self.arc <= length)]
        #: (K,) the chain's arc lengths: evenly spaced, and at each held marker on the cable
        self.chain_arc = np.unique(np.concatenate([np.linspace(0, length, count), on_cable]))
        self.rest = np.diff(self.chain_arc)
        self.to_markers = interpolation_matrix(self.arc, self.chain_arc)
        self.to_chain = interpolation_matrix(self.chain_arc, self.arc)
        #: (K,) which held marker pins each chain node (-1: none)
        self.pin_of = np.full(len(self.chain_arc), -1)
        for m in np.flatnonzero(self.held):
            at = np.flatnonzero(np.isclose(self.chain_arc, self.arc[m], atol=1e-9))
            self.pin_of[at] = m
        self.laplacian = laplacian(len(self.chain_arc))
        self.shape_matrix = self.laplacian.T @ self.laplacian
        self.prior = prior or ContinuityPrior(self.held, np.diff(self.arc))
        self._history: list[np.ndarray] = []
        self._chain: np.ndarray | None = None
        self._seen = np.ones(len(self.chain_arc), dtype=bool)
        self._loose_ends: list[int] = []

    @classmethod
    def for_layout(cls, layout, radius: float, spec=None, prior=None) -> CableTracker:
        """A tracker of an observation's markers (:class:`dlocli.env.observation.MarkerLayout`)."""
        return cls(layout.arc, layout.held, layout.length, radius, spec, prior)

    # ------------------------------------------------------------------ the frames
    def start(self, frame: CloudFrame, held: np.ndarray | None = None) -> TrackedFrame:
        """Lay the chain out on the first frame, ordered from the grippers: ``held`` (H,3),
        the held markers' positions (None: from the cloud's two farthest points)."""
        points = self._points(frame)
        if len(points) < 2:
            raise BadInput(
                f"tracker: the first frame has {len(points)} cable points; the camera must "
                "see the cable to start tracking (point it at the workspace)"
            )
        held = self._held(held)
        ends = None
        if held is not None:
            markers = np.zeros((len(self.arc), 3))
            markers[self.held] = held
            ends = tuple(self.to_chain[[0, -1]] @ markers)  # the held ends, straight on
        chain = initial_chain(points, self.chain_arc, 0.5 * self._spacing, ends)
        self._history = []
        self._seen[:] = True
        fitted = self._fit(points, chain, self._pins(held),
                           self.spec.iterations * FIRST_FRAME_ITERATIONS)  # fmt: skip
        return self._report(fitted, held)

    def step(self, frame: CloudFrame, held: np.ndarray | None = None) -> TrackedFrame:
        """Track the next frame; ``held`` (H,3) where the robot put the held markers."""
        if self._chain is None:
            return self.start(frame, held)
        held = self._held(held)
        history = np.stack(self._history)
        predicted = self.prior.predict(history, held)
        # the markers' predicted motion, spread along the chain: the shape between them is
        # the last fit's
        chain = self._chain + self.to_chain @ (predicted - history[-1])
        fitted = self._fit(self._points(frame), chain, self._pins(held), self.spec.iterations)
        return self._report(fitted, held)

    # ------------------------------------------------------------------ the fit
    @property
    def _spacing(self) -> float:
        return float(self.rest.mean())

    def _points(self, frame: CloudFrame) -> np.ndarray:
        """The frame's points, each moved from the cable's front surface to its axis."""
        points = np.asarray(frame.points, dtype=np.float64).reshape(-1, 3)
        if not np.isfinite(points).all():
            raise BadInput("tracker: the cloud holds NaN or infinite points; drop them first")
        away = points - frame.viewpoint
        distance = np.maximum(np.linalg.norm(away, axis=1, keepdims=True), 1e-9)
        return points + (0.25 * math.pi * self.radius) * away / distance

    def _held(self, held: np.ndarray | None) -> np.ndarray | None:
        if held is None:
            return None
        held = np.asarray(held, dtype=np.float64)
        if held.shape != (int(self.held.sum()), 3) or not np.isfinite(held).all():
            raise BadInput(
                f"tracker: the held markers' positions must be {int(self.held.sum())} finite "
                f"(x, y, z) rows, got shape {held.shape}"
            )
        return held

    def _pins(self, held: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
        """(K,) the pinned chain nodes and (K,3) where they are (rows of unpinned nodes 0)."""
        pinned = (self.pin_of >= 0) & (held is not None)
        where = np.zeros((len(self.chain_arc), 3))
        if held is not None:
            markers = np.zeros((len(self.arc), 3))
            markers[self.held] = held
            where[pinned] = markers[self.pin_of[pinned]]
        return pinned, where

    def _fit(
        self, points: np.ndarray, predicted: np.ndarray, pins: tuple, iterations: int
    ) -> np.ndarray:
        """EM on the mixture of chain nodes, from the ``predicted`` chain (K,3)."""
        pinned, where = pins
        predicted = np.where(pinned[:, None], where, predicted)
        points = points[near_points(points, predicted, GATE * self._spacing)]
        nodes, sigma2 = predicted.copy(), self._spacing**2
        support, resp = np.zeros(len(nodes)), None
        # an end node the robot does not place takes no points: a mixture's end component
        # sits inside the cloud's end; the chain's shape carries it straight on instead
        loose_ends = [k for k in (0, len(nodes) - 1) if not pinned[k]]
        self._loose_ends = loose_ends
        for _ in range(iterations):
            d2 = _squared_distances(points, nodes)
            d2[:, loose_ends] = FAR
            if resp is not None:  # the width of the last responsibilities around the new nodes
                sigma2 = max(float((resp * d2).sum() / max(3.0 * resp.sum(), 1e-12)),
                             MIN_SIGMA**2)  # fmt: skip
            resp = self._responsibilities(d2, sigma2)
            support = resp.sum(0)
            nodes = self._solve(resp, points, support, predicted, pinned, where)
            nodes = keep_lengths(nodes, self.rest, pinned)
        nodes = keep_lengths(nodes, self.rest, pinned, self.spec.length_sweeps)
        self._seen = self._visibility(support) >= self.spec.visible_support
        self._chain = nodes
        self._support = support
        return nodes

    def _responsibilities(self, d2: np.ndarray, sigma2: float) -> np.ndarray:
        """(N,K) the posterior of each node for each point at squared distances ``d2``
        (N,K), a uniform outlier term aside."""
        if len(d2) == 0:
            return d2
        nearest = d2.min(1, keepdims=True)
        gauss = np.exp(-0.5 * (d2 - nearest) / sigma2)
        # the uniform term, scaled by the same factor as the rows (their nearest node's)
        w = self.spec.outlier_weight
        uniform = (2 * math.pi * sigma2) ** 1.5 * w / (1 - w) * d2.shape[1] / len(d2)
        with np.errstate(over="ignore"):
            uniform = uniform * np.exp(0.5 * nearest / sigma2)
        return gauss / (gauss.sum(1, keepdims=True) + np.minimum(uniform, 1e300))

    def _solve(self, resp, points, support, predicted, pinned, where) -> np.ndarray:
        """The M step: one linear solve for the nodes (K,3)."""
        per_node = max(float(support.sum()) / len(support), 1.0)
        pull = np.where(self._seen, self.spec.prior_weight, self.spec.hidden_weight) * per_node
        spec, lap = self.spec, self.laplacian
        seen = self._seen[1:-1]  # the Laplacian's rows, centred on nodes 1 to K-2
        smooth = np.where(seen, spec.smoothness, spec.hidden_smoothness) * per_node
        bend = np.where(seen, spec.bending, spec.hidden_bending) * per_node
        shape = (lap.T * smooth) @ lap
        bending = (lap.T * bend) @ lap
        matrix = np.diag(support + pull) + shape + bending
        rhs = resp.T @ points + pull[:, None] * predicted + shape @ predicted
        matrix[pinned] = 0.0
        matrix[pinned, pinned] = 1.0
        rhs[pinned] = where[pinned]
        return np.linalg.solve(matrix, rhs)

    def _visibility(self, support: np.ndarray) -> np.ndarray:
        """(K,) each node's points over the cable's points per node (0 to 1); a loose end
        node (it takes no points) is seen when its neighbour is."""
        support = support.copy()
        for end in self._loose_ends:
            support[end] = support[1 if end == 0 else -2]
        per_node = float(support.sum()) / len(support)
        if per_node <= 0:
            return np.zeros(len(support))
        return np.clip(support / per_node, 0.0, 1.0)

    def _report(self, chain: np.ndarray, held: np.ndarray | None) -> TrackedFrame:
        markers = self.to_markers @ chain
        if held is not None:
            markers[self.held] = held
        visibility = np.clip(self.to_markers @ self._visibility(self._support), 0.0, 1.0)
        self._history = [*self._history[-(HISTORY - 1) :], markers]
        return TrackedFrame(
            markers, visibility >= self.spec.visible_support, visibility, chain.copy()
        )


def _squared_distances(points: np.ndarray, nodes: np.ndarray) -> np.ndarray:
    """(N,K) squared distances between points (N,3) and nodes (K,3)."""
    d2 = (points**2).sum(1)[:, None] + (nodes**2).sum(1)[None, :] - 2.0 * points @ nodes.T
    return np.maximum(d2, 0.0)
