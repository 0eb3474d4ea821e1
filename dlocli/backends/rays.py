"""What a depth camera's rays hit in a backend's scene: the rod, a gripper or nothing.

Every backend answers :meth:`~dlocli.backends.base.Backend.cast_rays` with a
:class:`RayHits`. MuJoCo's cable and PyBullet's chain cast them with their simulator
(``mj_multiRay``, ``rayTestBatch``); any other backend (the flex rod, a plugin, a cell) gets
the analytic caster here, on what every backend reports: the segments as capsules of the
rod's radius between their end points, and each held end's gripper as a box.

A gripper is a box of half extents ``GRIPPER_HALF_EXTENTS`` rod lengths centred on the
gripper's point in the gripper's frame, the size MuJoCo's scenes give it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: what a ray hit
NOTHING, CABLE, GRIPPER, TABLE = 0, 1, 2, 3
KIND_NAMES = ("nothing", "cable", "gripper", "table")
#: a gripper's box (half extents along its x, y, z), in rod lengths
GRIPPER_HALF_EXTENTS = (0.02, 0.03, 0.03)


@dataclass
class RayHits:
    """The first hit of each of R rays: ``distance`` (R,) metres along the unit direction
    (inf: nothing), ``kind`` (R,) one of NOTHING, CABLE, GRIPPER, TABLE, and ``segment``
    (R,) the rod segment hit (-1 unless the kind is CABLE)."""

    distance: np.ndarray
    kind: np.ndarray
    segment: np.ndarray

    @classmethod
    def empty(cls, count: int) -> RayHits:
        return cls(
            np.full(count, np.inf), np.zeros(count, dtype=np.int8), np.full(count, -1, np.int32)
        )

    def take(self, distance: np.ndarray, kind: int, segment: np.ndarray | None = None) -> None:
        """Keep the hits at ``distance`` (R,) where they are nearer than the ones held."""
        nearer = distance < self.distance
        self.distance[nearer] = distance[nearer]
        self.kind[nearer] = kind
        self.segment[nearer] = -1 if segment is None else segment[nearer]


def rotation_matrices(quaternions: np.ndarray) -> np.ndarray:
    """(K,3,3) rotation matrices of unit quaternions (K,4) (w, x, y, z)."""
    w, x, y, z = np.moveaxis(np.asarray(quaternions, dtype=np.float64), -1, 0)
    return np.stack(
        [
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
            np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
            np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
        ],
        -2,
    )


def capsule_distances(
    origin: np.ndarray, directions: np.ndarray, starts: np.ndarray, ends: np.ndarray, radius: float
) -> np.ndarray:
    """(R,S) distance along each unit ray from ``origin`` (3,) to each capsule of ``radius``
    around the segments ``starts`` -> ``ends`` (S,3); inf where it misses."""
    axis = ends - starts  # (S,3)
    to_origin = origin - starts  # (S,3)
    axis2 = np.einsum("sj,sj->s", axis, axis)
    along_ray = directions @ axis.T  # (R,S) d . ba
    axis_origin = np.einsum("sj,sj->s", axis, to_origin)  # ba . oa
    ray_origin = directions @ to_origin.T  # d . oa
    origin2 = np.einsum("sj,sj->s", to_origin, to_origin)
    a = axis2 - along_ray**2
    b = axis2 * ray_origin - axis_origin * along_ray
    c = axis2 * origin2 - axis_origin**2 - radius**2 * axis2
    h = b * b - a * c
    with np.errstate(invalid="ignore", divide="ignore"):
        t = (-b - np.sqrt(h)) / a
        y = axis_origin + t * along_ray
    side = (h >= 0) & (y > 0) & (y < axis2) & (t > 0)
    distance = np.where(side, t, np.inf)
    # the caps: spheres at both ends (a ray that misses the side may still hit one)
    for centre in (starts, ends):
        offset = origin - centre  # (S,3)
        half_b = directions @ offset.T
        cc = np.einsum("sj,sj->s", offset, offset) - radius**2
        hh = half_b * half_b - cc
        with np.errstate(invalid="ignore"):
            tt = -half_b - np.sqrt(hh)
        distance = np.minimum(distance, np.where((hh >= 0) & (tt > 0), tt, np.inf))
    return distance


def box_distances(
    origin: np.ndarray, directions: np.ndarray, poses: np.ndarray, half: np.ndarray
) -> np.ndarray:
    """(R,G) distance along each unit ray to each box of half extents ``half`` (3,) at the
    poses (G,7) (centre, w x y z quaternion); inf where it misses (slab method)."""
    frames = rotation_matrices(poses[:, 3:])  # (G,3,3) box axes as columns
    local_origin = np.einsum("gji,gj->gi", frames, origin - poses[:, :3])  # (G,3)
    local_dir = np.einsum("gji,rj->rgi", frames, directions)  # (R,G,3)
    with np.errstate(divide="ignore", invalid="ignore"):
        inverse = 1.0 / local_dir
        near = (-half - local_origin) * inverse
        far = (half - local_origin) * inverse
    enter = np.nanmax(np.minimum(near, far), axis=-1)
    leave = np.nanmin(np.maximum(near, far), axis=-1)
    hit = (enter <= leave) & (leave > 0)
    return np.where(hit, np.maximum(enter, 0.0), np.inf)


def cast_on_shapes(
    origin: np.ndarray,
    directions: np.ndarray,
    centres: np.ndarray,
    quaternions: np.ndarray,
    segment_length: float,
    radius: float,
    grippers: np.ndarray,
    gripper_half: np.ndarray,
) -> RayHits:
    """Rays from ``origin`` (3,) along unit ``directions`` (R,3) against the rod (segment
    centres (N,3) and orientations (N,4), x along the rod) and the grippers (G,7)."""
    hits = RayHits.empty(len(directions))
    if len(directions) == 0:
        return hits
    axes = rotation_matrices(quaternions)[:, :, 0]
    half = 0.5 * segment_length * axes
    rod = capsule_distances(origin, directions, centres - half, centres + half, radius)
    nearest = np.argmin(rod, axis=1)
    hits.take(rod[np.arange(len(rod)), nearest], CABLE, nearest.astype(np.int32))
    if len(grippers):
        hits.take(box_distances(origin, directions, grippers, gripper_half).min(1), GRIPPER)
    return hits
