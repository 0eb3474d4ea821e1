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
    """Row-wise cross products of (M,3) arrays (np.cross costs several times more on the
    small arrays of one rod)."""
    return a[:, [1, 2, 0]] * b[:, [2, 0, 1]] - a[:, [2, 0, 1]] * b[:, [1, 2, 0]]


def quat_from_frames(x_axes: np.ndarray, y_axes: np.ndarray) -> np.ndarray:
    """(M,4) unit quaternions (w >= 0) of the frames with these orthonormal (M,3) x and y axes
    (world frame), by Shepperd's method: each row's largest of |w|, |x|, |y|, |z| is found
    from the matrix diagonal and the others divided by it, so no frame loses precision."""
    z_axes = cross3(x_axes, y_axes)
    xx, yy, zz = x_axes[:, 0], y_axes[:, 1], z_axes[:, 2]
    # 4 q_k^2 for k = w, x, y, z, from the diagonal
    squares = np.stack([1 + xx + yy + zz, 1 + xx - yy - zz, 1 - xx + yy - zz, 1 - xx - yy + zz])
    pick = np.argmax(squares, axis=0)
    big = 0.5 * np.sqrt(np.maximum(squares[pick, np.arange(len(pick))], 1e-300))  # |q_pick|
    # off-diagonal sums and differences: 4 q_i q_j for every pair
    zy, yz = y_axes[:, 2], z_axes[:, 1]  # m[2,1] and m[1,2]
    xz, zx = z_axes[:, 0], x_axes[:, 2]  # m[0,2] and m[2,0]
    yx, xy = x_axes[:, 1], y_axes[:, 0]  # m[1,0] and m[0,1]
    wx, wy, wz = zy - yz, xz - zx, yx - xy
    xy_, xz_, yz_ = yx + xy, xz + zx, zy + yz
    products = np.stack(
        [
            np.stack([squares[0], wx, wy, wz]),
            np.stack([wx, squares[1], xy_, xz_]),
            np.stack([wy, xy_, squares[2], yz_]),
            np.stack([wz, xz_, yz_, squares[3]]),
        ]
    )  # (4 picks, 4 components, M): 4 q_pick q_component
    rows = products[pick, :, np.arange(len(pick))]  # (M, 4)
    quats = rows / (2.0 * big[:, None])
    quats /= np.linalg.norm(quats, axis=1, keepdims=True)
    return np.where(quats[:, :1] < 0, -quats, quats)
