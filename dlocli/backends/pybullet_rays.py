"""PyBullet's rays (``rayTestBatch``) on the chain of :mod:`dlocli.backends.pybullet_chain`.

The chain has no collision shapes (they would slow every step and PyBullet's rays hit only
collision shapes), so the rays are cast in a scene of their own: a second DIRECT client
holding a static capsule per segment and a box per gripper, moved to the rod's and the
grippers' poses before each batch. The physics never sees it.
"""

from __future__ import annotations

import contextlib
import math

import numpy as np
import pybullet as p

from dlocli.backends.pybullet_rotations import xyzw
from dlocli.backends.rays import CABLE, GRIPPER, RayHits

#: rays per rayTestBatch call (PyBullet returns at most 16383 of a longer batch)
BATCH = 8192
PARKED = (0.0, 0.0, -1e4)  # where an unused gripper box waits, out of every view


class RayScene:
    """Collision-only copies of ``segments`` capsules (``length``, ``radius``) and two
    gripper boxes (``half_extents``) in a private PyBullet client."""

    def __init__(self, segments: int, length: float, radius: float, half_extents: np.ndarray):
        self.client = p.connect(p.DIRECT)
        if self.client < 0:
            raise RuntimeError("could not start a PyBullet DIRECT client for rays")
        c = self.client
        along_x = p.getQuaternionFromEuler([0, math.pi / 2, 0])  # capsules are along z
        capsule = p.createCollisionShape(
            p.GEOM_CAPSULE, radius=radius, height=length, collisionFrameOrientation=along_x,
            physicsClientId=c,
        )  # fmt: skip
        box = p.createCollisionShape(
            p.GEOM_BOX, halfExtents=[float(h) for h in half_extents], physicsClientId=c
        )
        self.segments = [
            p.createMultiBody(0, capsule, basePosition=PARKED, physicsClientId=c)
            for _ in range(segments)
        ]
        self.grippers = [
            p.createMultiBody(0, box, basePosition=PARKED, physicsClientId=c) for _ in range(2)
        ]
        #: each body's kind and segment (bodies are numbered from 0 in a fresh client)
        count = segments + 2
        self.kind = np.zeros(count + 1, dtype=np.int8)  # [-1]: no hit
        self.segment = np.full(count + 1, -1, dtype=np.int32)
        for i, body in enumerate(self.segments):
            self.kind[body], self.segment[body] = CABLE, i
        for body in self.grippers:
            self.kind[body] = GRIPPER

    def place(self, centres: np.ndarray, orientations: np.ndarray, grippers: np.ndarray) -> None:
        """Segments at their centres (N,3) and orientations (N,4, x y z w); the held
        grippers' boxes at their poses (G,7, w x y z), the others parked."""
        c = self.client
        for body, centre, quat in zip(self.segments, centres.tolist(), orientations.tolist(),
                                      strict=True):  # fmt: skip
            p.resetBasePositionAndOrientation(body, centre, quat, physicsClientId=c)
        for g, body in enumerate(self.grippers):
            if g < len(grippers):
                pose = grippers[g]
                position, quat = pose[:3].tolist(), xyzw(pose[3:]).tolist()
            else:
                position, quat = list(PARKED), [0.0, 0.0, 0.0, 1.0]
            p.resetBasePositionAndOrientation(body, position, quat, physicsClientId=c)

    def cast(self, origin: np.ndarray, directions: np.ndarray, reach: float) -> RayHits:
        """Rays from ``origin`` (3,) along unit ``directions`` (R,3), up to ``reach`` metres."""
        hits = RayHits.empty(len(directions))
        start = np.asarray(origin, dtype=np.float64).tolist()
        for first in range(0, len(directions), BATCH):
            chunk = directions[first : first + BATCH]
            ends = (np.asarray(origin) + reach * chunk).tolist()
            results = p.rayTestBatch([start] * len(ends), ends, physicsClientId=self.client)
            body = np.array([r[0] for r in results], dtype=np.int64)
            fraction = np.array([r[2] for r in results])
            rows = slice(first, first + len(chunk))
            missed = body < 0
            hits.distance[rows] = np.where(missed, np.inf, fraction * reach)
            hits.kind[rows] = self.kind[body]
            hits.segment[rows] = self.segment[body]
        return hits

    def close(self) -> None:
        with contextlib.suppress(Exception):  # interpreter shutdown: pybullet may be gone
            if p.isConnected(physicsClientId=self.client):
                p.disconnect(physicsClientId=self.client)
