"""Small quaternion helpers (w, x, y, z), numpy, vectorised over leading axes."""

from __future__ import annotations

from typing import Any

import numpy as np


def quat_multiply(q1: np.ndarray, q2: np.ndarray) -> np.ndarray:
    w1, x1, y1, z1 = np.moveaxis(q1, -1, 0)
    w2, x2, y2, z2 = np.moveaxis(q2, -1, 0)
    return np.stack(
        [
            w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2,
            w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
            w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2,
            w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2,
        ],
        axis=-1,
    )


def quat_from_rotvec(rotvec: np.ndarray) -> np.ndarray:
    """Unit quaternion of a rotation vector (axis * angle, radians)."""
    angle = np.linalg.norm(rotvec, axis=-1, keepdims=True)
    half = 0.5 * angle
    # sin(x)/x -> 1/2 scale near zero without dividing by zero
    scale = np.where(angle > 1e-12, np.sin(half) / np.maximum(angle, 1e-12), 0.5)
    return np.concatenate([np.cos(half), rotvec * scale], axis=-1)


def quat_normalize(q: np.ndarray) -> np.ndarray:
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    # canonical sign (w >= 0) so equal rotations compare equal
    return np.where(q[..., :1] < 0, -q, q)


def quat_rotate(q: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Rotate vectors v (...,3) by unit quaternions q (...,4)."""
    w = q[..., :1]
    u = q[..., 1:]
    t = 2.0 * np.cross(u, v)
    return v + w * t + np.cross(u, t)


def quat_to_matrix(q: np.ndarray) -> np.ndarray:
    eye = np.eye(3)
    return np.stack([quat_rotate(q, eye[i]) for i in range(3)], axis=-1)


def state_change(state: Any, next_state: Any) -> Any:
    """``next_state - state`` of (..., 7) segment states (position, quaternion), with the next
    quaternion's sign aligned to the current one: q and -q are the same rotation, and aligning
    keeps the change small and continuous. numpy arrays or torch tensors."""
    dot = (state[..., 3:] * next_state[..., 3:]).sum(-1, keepdims=True)
    sign = (dot >= 0) * 2.0 - 1.0
    position = next_state[..., :3] - state[..., :3]
    quat = next_state[..., 3:] * sign - state[..., 3:]
    if isinstance(state, np.ndarray):
        return np.concatenate([position, quat], -1)
    import torch

    return torch.cat([position, quat], -1)


def cross3(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Row-wise cross products of (M,3) arrays (cheaper than np.cross on the small arrays of
    one rod)."""
    return a[:, [1, 2, 0]] * b[:, [2, 0, 1]] - a[:, [2, 0, 1]] * b[:, [1, 2, 0]]
