"""Images of the PyBullet chain (:mod:`dlocli.backends.pybullet_chain`) from PyBullet's tiny
renderer: a fixed camera in front of the workspace, the grippers and goal drawn as
visual-only bodies that exist only while an image is taken."""

from __future__ import annotations

import contextlib

import numpy as np
import pybullet as p

from dlocli.backends.pybullet_rotations import xyzw
from dlocli.specs import RodSpec


class ChainCamera:
    """The camera of one PyBullet client holding a rod of ``rod``'s size whose grippers rest
    at ``rest_height`` (m)."""

    def __init__(self, client: int, rod: RodSpec, rest_height: float) -> None:
        self.client = client
        self.rod = rod
        self.rest_height = rest_height
        self._visuals: dict[str, int] = {}  # visual shapes, created once per kind

    def image(
        self, grips: np.ndarray, goal: np.ndarray | None, width: int, height: int
    ) -> np.ndarray:
        """(height, width, 3) uint8 RGB of the scene with boxes at the held grippers' poses
        ``grips`` (k, 7: position, w x y z quaternion) and spheres at the goal points."""
        markers: list[int] = []
        try:
            markers = self._add_markers(grips, goal)
            return self._camera_image(width, height)
        finally:
            # markers live only while rendering: static bodies still cost physics time
            for body in markers:
                with contextlib.suppress(Exception):
                    p.removeBody(body, physicsClientId=self.client)

    def _visual(self, kind: str, **shape: object) -> int:
        """A visual shape (``createVisualShape`` arguments), created once per kind."""
        if kind not in self._visuals:
            self._visuals[kind] = p.createVisualShape(physicsClientId=self.client, **shape)
        return self._visuals[kind]

    def _add_markers(self, grips: np.ndarray, goal: np.ndarray | None) -> list[int]:
        """Visual-only bodies (no mass, no collision) at the grippers and goal points."""
        r = self.rod.radius
        box = self._visual(
            "gripper", shapeType=p.GEOM_BOX, halfExtents=[2 * r] * 3, rgbaColor=[0.4, 0.4, 0.45, 1]
        )
        ball = self._visual(
            "goal", shapeType=p.GEOM_SPHERE, radius=1.2 * r, rgbaColor=[0.1, 0.7, 0.2, 1]
        )
        places = [(box, pose[:3], xyzw(pose[3:])) for pose in grips]  # a free end: no gripper
        try:
            points = np.asarray(goal, dtype=np.float64).reshape(-1, 3)
        except (TypeError, ValueError):  # None or not (N,3)-like: draw no goal
            points = np.zeros((0, 3))
        places += [(ball, pt, [0, 0, 0, 1]) for pt in points if np.isfinite(pt).all()]
        return [
            p.createMultiBody(
                baseMass=0,
                baseVisualShapeIndex=vis,
                basePosition=list(pos),
                baseOrientation=list(orn),
                physicsClientId=self.client,
            )
            for vis, pos, orn in places
        ]

    def _camera_image(self, width: int, height: int) -> np.ndarray:
        """A fixed camera in front of the workspace (-y side), slightly above, looking at it."""
        L = self.rod.length
        target = [0.0, 0.0, self.rest_height - 0.2 * L]
        view = p.computeViewMatrix([0.0, -1.6 * L, self.rest_height + 0.3 * L], target, [0, 0, 1])
        proj = p.computeProjectionMatrixFOV(50.0, width / height, 0.05 * L, 10.0 * L)
        _, _, rgba, _, _ = p.getCameraImage(
            width,
            height,
            view,
            proj,
            renderer=p.ER_TINY_RENDERER,
            flags=p.ER_NO_SEGMENTATION_MASK,
            physicsClientId=self.client,
        )
        return np.asarray(rgba, dtype=np.uint8).reshape(height, width, 4)[..., :3].copy()
