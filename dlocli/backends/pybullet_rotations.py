"""Rotations in PyBullet's terms: its (x, y, z, w) quaternions against dlocli's (w, x, y, z),
and the rotation helpers of the chain's inner loop on plain floats (per joint and physics
step, where NumPy's per-call overhead would dominate)."""

from __future__ import annotations

import math

import numpy as np


def xyzw(q: np.ndarray) -> np.ndarray:
    """(w,x,y,z) -> PyBullet's (x,y,z,w)."""
    return q[..., [1, 2, 3, 0]]


def wxyz(q: np.ndarray) -> np.ndarray:
    """PyBullet's (x,y,z,w) -> (w,x,y,z)."""
    return q[..., [3, 0, 1, 2]]


def right_product(q: np.ndarray) -> np.ndarray:
    """4x4 matrix M with ``a * q = M @ a`` for quaternions (w,x,y,z)."""
    w, x, y, z = q
    return np.array([[w, -x, -y, -z], [x, w, z, -y], [y, -z, w, x], [z, y, -x, w]])


def spin(q0: np.ndarray, q1: np.ndarray) -> np.ndarray:
    """Rotation vector r (radians, world frame) of the shortest spin with q1 = exp(r) q0."""
    rel = right_product(q0 * np.array([1.0, -1, -1, -1])) @ q1  # q1 * conj(q0)
    if rel[0] < 0:
        rel = -rel
    sin_half = float(np.linalg.norm(rel[1:]))
    if sin_half < 1e-15:
        return np.zeros(3)
    return rel[1:] * (2.0 * math.atan2(sin_half, rel[0]) / sin_half)


def rotate(q: tuple[float, ...], v: tuple[float, ...], inverse: bool = False) -> tuple:
    """Vector v rotated by the unit quaternion q (x y z w), or by its inverse; plain floats."""
    x, y, z, w = q
    if inverse:
        x, y, z = -x, -y, -z
    tx, ty, tz = 2 * (y * v[2] - z * v[1]), 2 * (z * v[0] - x * v[2]), 2 * (x * v[1] - y * v[0])
    return (
        v[0] + w * tx + y * tz - z * ty,
        v[1] + w * ty + z * tx - x * tz,
        v[2] + w * tz + x * ty - y * tx,
    )


def rotation_vector(x: float, y: float, z: float, w: float) -> tuple[float, float, float]:
    """Rotation vector (rad) of the quaternion (x y z w), the shorter rotation; plain floats."""
    sin_half = math.sqrt(x * x + y * y + z * z)
    # theta = 2 asin(|v|) v / |v| for the shorter rotation (sign of w); -> 2 v at 0
    f = math.asin(min(sin_half, 1.0)) / sin_half if sin_half > 1e-12 else 1.0
    f = math.copysign(2.0 * f, w)
    return f * x, f * y, f * z
