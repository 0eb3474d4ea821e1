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


def quat_from_frames(x_axes: np.ndarray, y_axes: np.ndarray) -> np.ndarray:
    """(M,4) unit quaternions (w >= 0) of the frames with these orthonormal (M,3) x and y axes
    (world frame), by Shepperd's method: the largest of w, x, y, z is found from the matrix
    trace, the others from it, so no frame loses precision."""
    z_axes = np.cross(x_axes, y_axes)
    m = np.stack([x_axes, y_axes, z_axes], axis=-1)  # columns are the frame's axes
    trace = np.stack([m[:, 0, 0] + m[:, 1, 1] + m[:, 2, 2], m[:, 0, 0], m[:, 1, 1], m[:, 2, 2]])
    pick = np.argmax(trace, axis=0)
    quats = np.empty((len(m), 4))
    for choice in range(4):
        rows = pick == choice
        if rows.any():
            quats[rows] = _shepperd(m[rows], choice)
    quats /= np.linalg.norm(quats, axis=1, keepdims=True)
    return np.where(quats[:, :1] < 0, -quats, quats)


def _shepperd(m: np.ndarray, choice: int) -> np.ndarray:
    """Quaternions of rotation matrices ``m`` (K,3,3) from their largest component ``choice``
    (0: w, 1: x, 2: y, 3: z)."""
    diag = m[:, 0, 0], m[:, 1, 1], m[:, 2, 2]
    if choice == 0:
        s = 2.0 * np.sqrt(1.0 + diag[0] + diag[1] + diag[2])
        parts = (0.25 * s, (m[:, 2, 1] - m[:, 1, 2]) / s, (m[:, 0, 2] - m[:, 2, 0]) / s,
                 (m[:, 1, 0] - m[:, 0, 1]) / s)  # fmt: skip
    elif choice == 1:
        s = 2.0 * np.sqrt(1.0 + diag[0] - diag[1] - diag[2])
        parts = ((m[:, 2, 1] - m[:, 1, 2]) / s, 0.25 * s, (m[:, 0, 1] + m[:, 1, 0]) / s,
                 (m[:, 0, 2] + m[:, 2, 0]) / s)  # fmt: skip
    elif choice == 2:
        s = 2.0 * np.sqrt(1.0 - diag[0] + diag[1] - diag[2])
        parts = ((m[:, 0, 2] - m[:, 2, 0]) / s, (m[:, 0, 1] + m[:, 1, 0]) / s, 0.25 * s,
                 (m[:, 1, 2] + m[:, 2, 1]) / s)  # fmt: skip
    else:
        s = 2.0 * np.sqrt(1.0 - diag[0] - diag[1] + diag[2])
        parts = ((m[:, 1, 0] - m[:, 0, 1]) / s, (m[:, 0, 2] + m[:, 2, 0]) / s,
                 (m[:, 1, 2] + m[:, 2, 1]) / s, 0.25 * s)  # fmt: skip
    return np.stack(parts, axis=-1)
