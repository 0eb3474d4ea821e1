"""A simulated RGB-D camera: a point cloud of the cable per frame, in the world frame.

Each pixel's ray is cast into the backend's scene (:meth:`Backend.cast_rays`: the rod, the
grippers) and onto a table, an analytic plane under the workspace (the backends' scenes
have none). The sensor then adds its faults: depth noise that grows with distance, along
the ray; pixels with no depth (out of range, or dropped at random). The cable's points are
the pixels whose ray hit the cable (what colour thresholding gives), plus a stated share of
stray points: table or gripper pixels taken for cable.

Pinhole camera, OpenCV's convention: x right, y down, z along the optical axis; depth is
the z coordinate. A frame carries the camera's intrinsics and extrinsics (camera to world)
beside its points.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from dlocli.backends.base import Backend
from dlocli.backends.rays import CABLE, GRIPPER, TABLE, RayHits
from dlocli.errors import BadInput
from dlocli.spec_base import validated
from dlocli.tracking.spec import CameraSpec

NOISE_FROM = 0.4  # m: the depth from which the noise grows (the model's nearest depth)
MM = 1e-3


@dataclass
class CloudFrame:
    """One frame: ``points`` (N,3) in the world frame (m), ``extrinsics`` (4,4) camera to
    world, ``intrinsics`` (3,3) pixels, ``time`` (s), and, from a simulator, ``segment``
    (N,) the rod segment each point shows (-1: a stray point), for measurements only."""

    points: np.ndarray
    extrinsics: np.ndarray
    intrinsics: np.ndarray
    time: float = 0.0
    segment: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int32))

    @property
    def viewpoint(self) -> np.ndarray:
        """(3,) the camera's position."""
        return self.extrinsics[:3, 3]

    def without_segments(self, hidden: np.ndarray) -> CloudFrame:
        """This frame with the points of the ``hidden`` segments (a mask) left out: the view
        of something in front of them."""
        keep = ~(np.asarray(hidden, dtype=bool)[self.segment] & (self.segment >= 0))
        return CloudFrame(
            self.points[keep], self.extrinsics, self.intrinsics, self.time, self.segment[keep]
        )


def intrinsic_matrix(spec: CameraSpec) -> np.ndarray:
    """(3,3) pinhole intrinsics: focal lengths from the vertical field of view unless given."""
    focal = 0.5 * spec.height / math.tan(math.radians(0.5 * spec.fov_deg))
    fx = spec.fx if spec.fx is not None else focal
    fy = spec.fy if spec.fy is not None else focal
    cx = spec.cx if spec.cx is not None else 0.5 * spec.width
    cy = spec.cy if spec.cy is not None else 0.5 * spec.height
    return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])


def look_at_extrinsics(position: np.ndarray, target: np.ndarray) -> np.ndarray:
    """(4,4) camera-to-world transform of a camera at ``position`` looking at ``target``,
    its image upright (world z up; straight down or up: x along world x)."""
    forward = target - position
    forward = forward / np.linalg.norm(forward)
    right = np.cross(forward, [0.0, 0.0, 1.0])
    if np.linalg.norm(right) < 1e-9:
        right = np.array([1.0, 0.0, 0.0])
    right = right / np.linalg.norm(right)
    down = np.cross(forward, right)
    transform = np.eye(4)
    transform[:3, :3] = np.stack([right, down, forward], axis=1)
    transform[:3, 3] = position
    return transform


def pixel_rays(intrinsics: np.ndarray, width: int, height: int) -> np.ndarray:
    """(H*W,3) unit ray directions through the pixel centres, in the camera frame."""
    u, v = np.meshgrid(np.arange(width) + 0.5, np.arange(height) + 0.5)
    x = (u.ravel() - intrinsics[0, 2]) / intrinsics[0, 0]
    y = (v.ravel() - intrinsics[1, 2]) / intrinsics[1, 1]
    rays = np.stack([x, y, np.ones_like(x)], axis=1)
    return rays / np.linalg.norm(rays, axis=1, keepdims=True)


def depth_sigma(spec: CameraSpec, depth: np.ndarray) -> np.ndarray:
    """The standard deviation (m) of the depth noise at ``depth`` (m)."""
    beyond = np.maximum(depth - NOISE_FROM, 0.0)
    return (spec.noise_mm + spec.noise_growth_mm * beyond**2) * MM


class DepthCamera:
    """A depth camera of ``spec`` in the scene of a rod ``rod_length`` metres long (the
    spec's positions are in rod lengths)."""

    def __init__(self, spec: CameraSpec | dict | None = None, rod_length: float = 1.0) -> None:
        self.spec = spec if isinstance(spec, CameraSpec) else validated(
            CameraSpec, spec or {}, "camera"
        )  # fmt: skip
        self.rod_length = float(rod_length)
        self.intrinsics = intrinsic_matrix(self.spec)
        position = np.array(self.spec.position) * rod_length
        self.extrinsics = look_at_extrinsics(position, np.array(self.spec.look_at) * rod_length)
        camera_rays = pixel_rays(self.intrinsics, self.spec.width, self.spec.height)
        #: (H*W,3) unit pixel rays in the world frame, and each one's cosine to the axis
        self.rays = camera_rays @ self.extrinsics[:3, :3].T
        self.cosines = camera_rays[:, 2]
        self.origin = position

    def cast(self, backend: Backend, grippers: bool | None = None) -> RayHits:
        """Every pixel's first hit: the backend's scene, then the table. Only the pixels
        whose rays can reach the rod or a gripper are cast into the scene."""
        see = self.spec.see_grippers if grippers is None else grippers
        hits = RayHits.empty(len(self.rays))
        near = self._pixels_near(backend)
        if len(near):
            scene = backend.cast_rays(self.origin, self.rays[near], grippers=see)
            hits.distance[near], hits.kind[near] = scene.distance, scene.kind
            hits.segment[near] = scene.segment
        if self.spec.table_height is not None:
            height = self.spec.table_height * self.rod_length
            down = self.rays[:, 2]
            with np.errstate(divide="ignore", invalid="ignore"):
                t = np.where(down < 0, (height - self.origin[2]) / down, np.inf)
            hits.take(np.where(t > 0, t, np.inf), TABLE)
        return hits

    def _pixels_near(self, backend: Backend) -> np.ndarray:
        """The pixels inside the image box of the rod and the grippers, widened by the
        largest of their sizes: no other ray can hit them."""
        grippers = backend.held_gripper_poses()[:, :3]
        points = np.concatenate([backend.segment_positions(), grippers])
        local = (points - self.origin) @ self.extrinsics[:3, :3]  # camera frame
        reach = max(backend.rod.segment_length, 2.0 * backend.rod.radius)
        reach = max(reach, float(np.linalg.norm(backend.gripper_half_extents())))
        if not np.all(local[:, 2] > reach):  # something at or behind the camera: cast all
            return np.arange(len(self.rays))
        k = self.intrinsics
        u = k[0, 0] * local[:, 0] / local[:, 2] + k[0, 2]
        v = k[1, 1] * local[:, 1] / local[:, 2] + k[1, 2]
        margin_u = k[0, 0] * reach / local[:, 2]
        margin_v = k[1, 1] * reach / local[:, 2]
        low_u, high_u = (u - margin_u).min(), (u + margin_u).max()
        low_v, high_v = (v - margin_v).min(), (v + margin_v).max()
        width = self.spec.width
        pu, pv = np.arange(len(self.rays)) % width + 0.5, np.arange(len(self.rays)) // width + 0.5
        inside = (pu >= low_u) & (pu <= high_u) & (pv >= low_v) & (pv <= high_v)
        return np.flatnonzero(inside)

    def check_view(self, backend: Backend) -> None:
        """BadInput unless the camera sees some of the cable (grippers and faults aside)."""
        hits = self.cast(backend, grippers=False)
        depth = hits.distance * self.cosines
        seen = (hits.kind == CABLE) & (depth >= self.spec.min_range)
        if not (seen & (depth <= self.spec.max_range)).any():
            position = ", ".join(f"{v:g}" for v in self.spec.position)
            target = ", ".join(f"{v:g}" for v in self.spec.look_at)
            raise BadInput(
                f"camera: from ({position}) looking at ({target}) rod lengths, with a "
                f"{self.spec.fov_deg:g} degree view and depths {self.spec.min_range:g} to "
                f"{self.spec.max_range:g} m, it does not see the cable; point it at the "
                "workspace (camera.position, camera.look_at) or widen camera.fov_deg"
            )

    def capture(self, backend: Backend, rng: np.random.Generator, time: float = 0.0) -> CloudFrame:
        """The cable's point cloud as the camera and the segmentation give it now."""
        spec = self.spec
        hits = self.cast(backend)
        depth = hits.distance * self.cosines
        valid = np.isfinite(depth) & (depth >= spec.min_range) & (depth <= spec.max_range)
        if spec.invalid_fraction:
            valid &= rng.random(len(depth)) >= spec.invalid_fraction
        picked = np.flatnonzero(valid & (hits.kind == CABLE))
        picked = np.concatenate([picked, self._stray(hits, valid, len(picked), rng)])
        noisy = depth[picked]
        if spec.noise_mm or spec.noise_growth_mm:
            noisy = noisy + depth_sigma(spec, noisy) * rng.standard_normal(len(picked))
        along = noisy / self.cosines[picked]
        points = self.origin + along[:, None] * self.rays[picked]
        return CloudFrame(
            points, self.extrinsics.copy(), self.intrinsics.copy(), float(time),
            hits.segment[picked].astype(np.int32),
        )  # fmt: skip

    def _stray(
        self, hits: RayHits, valid: np.ndarray, cable_points: int, rng: np.random.Generator
    ) -> np.ndarray:
        """Pixels of the table or the grippers the segmentation takes for cable."""
        wanted = int(round(self.spec.stray_fraction * cable_points))
        candidates = np.flatnonzero(valid & ((hits.kind == TABLE) | (hits.kind == GRIPPER)))
        if wanted == 0 or len(candidates) == 0:
            return np.zeros(0, dtype=np.int64)
        return rng.choice(candidates, size=min(wanted, len(candidates)), replace=False)
