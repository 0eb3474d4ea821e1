"""The rod's end-for-end twin of a trajectory: the same motion with the other end acting.

A single-gripper dataset only ever shows the right end moving; the rod is symmetric end to
end, so every such transition has a twin in which the left end moves, as valid as the
original up to how the simulator holds the two ends (below). Training on both
(``FitSpec.mirror``) lets a model learned with one gripper see the left end act.

The map is the half turn ``R`` of the world about the vertical z axis, followed by relabelling
the rod's ends (segment i becomes segment N-1-i, the left gripper becomes the right one):

=============================  ============================================================
quantity                       twin
=============================  ============================================================
position ``(x, y, z)``         ``(-x, -y, z)``: ``R p``, segment order reversed
quaternion ``(w, x, y, z)``    ``(w, -x, -y, z)``: ``q_R q q_R`` with ``q_R = (0, 0, 0, 1)``
gripper pose                   the same, rows swapped (left <-> right)
command (v, omega)             ``(-vx, -vy, vz, -wx, -wy, wz)``: ``R v``, ``R omega``; rows
                               swapped
goal                           as positions; reward and divergence unchanged
=============================  ============================================================

Quaternions: the world turns by ``q_R`` (on the left); each segment's frame also turns by a
half turn about its own z axis (on the right), because after relabelling its x axis must
point along the rod from the new left end (base.py): the old x axis points the other way.
The body half turn is about z, not y, so the grippers' rest orientation (identity) maps onto
itself; ``q_R q q_R = -(w, -x, -y, z)`` is the same rotation as ``(w, -x, -y, z)``, and the
sign keeps ``w >= 0``.

Why the twin is what the simulator does, for a rod held at both ends in the default task
(tests/test_mirror.py drives both backends both ways and measures the difference):

- The rest configuration maps onto itself: the grippers rest at ``(-d, 0, h)`` and
  ``(d, 0, h)`` with the identity orientation (``Backend.rest_gripper_poses``), and both
  backends lay the rod out in the xz plane with an end-for-end symmetric sag and let it settle.
  The default workspace box (symmetric in x and y about 0) and the separation limits map
  onto themselves, so the twin of a clipped command is clipped alike
  (``integrate_gripper_poses``); an asymmetric ``workspace_low/high`` breaks this.
- ``R`` is a proper rotation about the gravity axis: gravity and handedness (twist) are kept,
  and neither simulator has anything that turning the world about z changes (no floor, no
  contacts).
- The rod is homogeneous, its cross-section round, its stress-free shape straight and
  untwisted: each joint's bending and twisting energies depend on its relative rotation
  ``(tx, ty, tz)`` only through ``tx^2`` and ``ty^2 + tz^2``, which the relabelling keeps
  (a joint's relative rotation is inverted and turned about z: ``(tx, ty, -tz)``).
- Gripper commands are world-frame twists about the gripper position (base.py), so they turn
  with the world: ``exp(R omega dt) q'`` is the twin of ``exp(omega dt) q``.
- The ends are held alike physically but built differently, which is where the twin is not
  exact. MuJoCo welds equal pads at both ends, the left one the root of the kinematic tree,
  the right one a child of the last segment; PyBullet holds both ends by equal fixed
  constraints, the left one on the multibody's base. The same physics in other coordinates:
  the twin agrees up to discretisation (tests/test_mirror.py: within 1.6 mm while the rod
  moves ~55 mm, on both).
"""

from __future__ import annotations

from dataclasses import replace
from typing import TypeVar

import numpy as np

from dlocli.data import Dataset, Episode

#: sign of each position component under the half turn about z
POSITION_SIGN = np.array([-1.0, -1.0, 1.0])
#: sign of each quaternion component (w, x, y, z) under ``q -> q_R q q_R``
QUATERNION_SIGN = np.array([1.0, -1.0, -1.0, 1.0])
#: sign of each segment state component (position, quaternion)
STATE_SIGN = np.concatenate([POSITION_SIGN, QUATERNION_SIGN])
#: sign of each gripper pose component (position, quaternion)
POSE_SIGN = STATE_SIGN
#: sign of each gripper command component (linear, angular velocity: both turn with R)
COMMAND_SIGN = np.concatenate([POSITION_SIGN, POSITION_SIGN])

Trajectory = TypeVar("Trajectory", Dataset, Episode)


def _flip(array: np.ndarray, sign: np.ndarray) -> np.ndarray:
    """Rows (axis -2) reversed and components signed; the dtype is kept."""
    array = np.asarray(array)
    return (array[..., ::-1, :] * sign).astype(array.dtype, copy=False)


def mirror_positions(positions: np.ndarray) -> np.ndarray:
    """(..., N, 3) segment positions (or goals) of the twin."""
    return _flip(positions, POSITION_SIGN)


def mirror_quaternions(quaternions: np.ndarray) -> np.ndarray:
    """(..., N, 4) segment orientations (w, x, y, z) of the twin."""
    return _flip(quaternions, QUATERNION_SIGN)


def mirror_states(states: np.ndarray) -> np.ndarray:
    """(..., N, 7) segment states (position, quaternion) of the twin."""
    return _flip(states, STATE_SIGN)


def mirror_grippers(grippers: np.ndarray) -> np.ndarray:
    """(..., 2, 7) gripper poses of the twin (left and right swapped)."""
    return _flip(grippers, POSE_SIGN)


def mirror_actions(actions: np.ndarray) -> np.ndarray:
    """(..., 2, 6) per-gripper commands of the twin (left and right swapped)."""
    return _flip(actions, COMMAND_SIGN)


def mirror_task_action(action: np.ndarray) -> np.ndarray:
    """A 12-D bimanual action (left then right) of the twin; a single-gripper action ``a``
    has the bimanual twin ``mirror_task_action(concat(0, a))``: the left gripper acting."""
    action = np.asarray(action)
    return mirror_actions(action.reshape(*action.shape[:-1], 2, 6)).reshape(action.shape)


def mirror_transitions(transitions: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """The twins of ``Dataset.transitions()`` arrays: segment states (``state``,
    ``next_state``, ``previous_state``) and ``action`` mapped, other arrays (``reward``) kept."""
    out = dict(transitions)
    for key in ("previous_state", "state", "next_state"):
        if key in out:
            out[key] = mirror_states(out[key])
    if "action" in out:
        out["action"] = mirror_actions(out["action"])
    return out


def with_mirrored(transitions: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """``transitions`` followed by their twins (twice as many rows)."""
    twins = mirror_transitions(transitions)
    return {k: np.concatenate([v, twins[k]]) for k, v in transitions.items()}


def mirror(trajectory: Trajectory) -> Trajectory:
    """The twin of a :class:`~dlocli.data.Dataset` or :class:`~dlocli.data.Episode`: a new
    object; rewards, episode lengths and divergence flags are the same (and shared), attrs
    copied. ``mirror(mirror(x))`` equals ``x``."""
    mapped = {
        "positions": mirror_positions(trajectory.positions),
        "quaternions": mirror_quaternions(trajectory.quaternions),
        "grippers": mirror_grippers(trajectory.grippers),
        "actions": mirror_actions(trajectory.actions),
    }
    if isinstance(trajectory, Dataset):
        mapped["goals"] = mirror_positions(trajectory.goals)
        mapped["attrs"] = dict(trajectory.attrs)
    else:
        mapped["goal"] = mirror_positions(trajectory.goal)
    return replace(trajectory, **mapped)
