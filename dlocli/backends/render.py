"""Matplotlib 3D renderer of a rod state: the fallback of every backend without OpenGL.

Draws on an off-screen Agg canvas (no pyplot, no display, no global figure state), with fixed
axis limits around the gripper workspace so frames of a video line up.
"""

from __future__ import annotations

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from matplotlib.ticker import MaxNLocator

from dlocli.backends.base import GripperLimits
from dlocli.backends.rotations import quat_rotate

ROD_COLOR = "#d9591a"
GOAL_COLOR = "#2ca02c"
GRIPPER_COLOR = "#3366e6"
_DPI = 100


def _view_box(rod_length: float) -> tuple[np.ndarray, np.ndarray]:
    """Fixed plot limits (m): the gripper workspace, extended below for a hanging rod."""
    limits = GripperLimits.default(rod_length)
    low = limits.low - np.array([0.1, 0.1, 0.8]) * rod_length
    high = limits.high + np.array([0.1, 0.1, 0.1]) * rod_length
    return low, high


def finite_points(values: np.ndarray | None) -> np.ndarray | None:
    """(M,3) float array, or None for anything that is not a finite list of 3D points."""
    if values is None:
        return None
    points = np.asarray(values, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3 or not np.all(np.isfinite(points)):
        return None
    return points


def _fit(image: np.ndarray, width: int, height: int) -> np.ndarray:
    """Crop or pad (white) an RGB image to exactly (height, width, 3)."""
    out = np.full((height, width, 3), 255, dtype=np.uint8)
    h, w = min(height, image.shape[0]), min(width, image.shape[1])
    out[:h, :w] = image[:h, :w]
    return out


def render_rod(
    positions: np.ndarray,
    gripper_poses: np.ndarray,
    goal: np.ndarray | None = None,
    width: int = 480,
    height: int = 360,
    rod_length: float = 1.0,
) -> np.ndarray:
    """RGB image (height, width, 3) uint8 of a rod.

    Args:
        positions: (N,3) segment centres in metres (world frame, z up).
        gripper_poses: (2,7) gripper poses (x, y, z, qw, qx, qy, qz); drawn as squares with a
            short line along each gripper's x axis.
        goal: optional (N,3) goal segment centres, drawn as a dashed green line.
        width, height: image size in pixels.
        rod_length: rod length in metres; scales the fixed view box (the workspace).
    """
    width, height = max(1, int(width)), max(1, int(height))
    fig = Figure(figsize=(width / _DPI, height / _DPI), dpi=_DPI)
    canvas = FigureCanvasAgg(fig)
    ax = fig.add_axes((0.0, 0.0, 1.0, 1.0), projection="3d")
    low, high = _view_box(rod_length)

    goal_points = finite_points(goal)
    if goal_points is not None:
        ax.plot(*goal_points.T, linestyle="--", linewidth=2, color=GOAL_COLOR, label="goal")
        ax.scatter(*goal_points.T, s=8, color=GOAL_COLOR, depthshade=False)
    rod = finite_points(positions)
    if rod is not None:
        ax.plot(*rod.T, linewidth=5, color=ROD_COLOR, solid_capstyle="round", label="rod")
        ax.scatter(*rod.T, s=6, color="black", depthshade=False)
    grippers = np.asarray(gripper_poses, dtype=np.float64).reshape(-1, 7)
    if np.all(np.isfinite(grippers)):
        axes = quat_rotate(grippers[:, 3:], np.array([0.08 * rod_length, 0.0, 0.0]))
        ax.scatter(*grippers[:, :3].T, s=60, marker="s", color=GRIPPER_COLOR, depthshade=False)
        for origin, tip in zip(grippers[:, :3], grippers[:, :3] + axes, strict=True):
            ax.plot(*np.stack([origin, tip]).T, linewidth=2, color=GRIPPER_COLOR)

    ax.set_xlim(low[0], high[0])
    ax.set_ylim(low[1], high[1])
    ax.set_zlim(low[2], high[2])
    ax.set_box_aspect(tuple(high - low), zoom=0.9)
    ax.view_init(elev=20.0, azim=-65.0)  # in front, slightly from the right: x right, z up
    ax.tick_params(labelsize=6, pad=0)
    for axis, label in zip((ax.xaxis, ax.yaxis, ax.zaxis), "xyz", strict=True):
        axis.set_major_locator(MaxNLocator(4))
        axis.set_label_text(f"{label} (m)", fontsize=7)
    if goal_points is not None:
        ax.legend(loc="upper left", fontsize=7, frameon=False)
    canvas.draw()
    image = np.asarray(canvas.buffer_rgba())[..., :3]
    return _fit(image, width, height)
