"""Random rod shapes for episode starts and goals, made physically so every goal is reachable.

Two ways (``TaskSpec.shapes``):

- ``random-pose`` (default, the paper's scale): each moving gripper gets a target pose drawn
  uniformly from the pose region — a position offset from its rest position inside the box
  ``pose_offset_low..pose_offset_high`` (fractions of the rod length, stated for the right
  gripper; the left gripper's box is its mirror image through the plane x = 0) and an
  orientation turned from rest by a world-frame rotation vector whose components lie in
  ``±pose_max_rotation`` radians. Bimanual targets are redrawn until the grippers' separation
  lies inside the task's limits. The grippers are driven there at no more than the task's
  maximum velocities, then held still while the rod settles.
- ``near-rest``: piecewise-constant random gripper twists for ``reset_motion_steps`` control
  steps from rest, then settling: starts and goals a few centimetres apart (fast tests).

``recorded`` draws each start and goal from a file of gripper poses (``recorded_poses``: a
recorded cell's, e.g. a calibrated twin's), driven there like a random pose's. An episode
can also be given its gripper poses (``env.reset(options={"start_grippers": ...,
"goal_grippers": ...})``, (2, 7) each: a recorded cell's poses): the grippers are driven
there from rest like a random pose's, and the rod settles. Given orientations are unit
quaternions w x y z: a norm within 1% of 1 (a recording's rounding) is normalised, any other
(zero, scaled, not finite) is refused naming the option or the file's row.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from dlocli.backends.base import Backend, GripperLimits
from dlocli.backends.rotations import quat_from_rotvec, quat_multiply, quat_normalize
from dlocli.errors import BadInput, BadOption
from dlocli.specs import TaskSpec

#: how many control steps a near-rest motion keeps one velocity before drawing the next
MOTION_HOLD_STEPS = 10
#: pose error below which a driven gripper counts as arrived (m, rad)
ARRIVED = 1e-6
#: draws of bimanual targets before giving up on the separation limits
TARGET_DRAWS = 100


def max_twist(task: TaskSpec) -> np.ndarray:
    """(6,) the largest gripper twist: linear (m/s) then angular (rad/s) per component."""
    return np.array([task.max_linear_velocity] * 3 + [task.max_angular_velocity] * 3)


def apply_task_limits(backend: Backend, task: TaskSpec) -> None:
    """Set ``backend``'s gripper limits to ``task``'s workspace and separation (fractions of
    the rod length). BadInput if the workspace excludes a moving gripper's rest position or
    the separation limits the grippers' rest separation: every start and goal is driven from
    rest; the backend would pull a gripper outside the box into it at the first step (a jump,
    not a motion) and refuses any translation that leaves the separation outside its limits,
    so the grippers would stay at rest."""
    length, limits = backend.rod.length, backend.limits
    limits.low = np.array(task.workspace_low) * length
    limits.high = np.array(task.workspace_high) * length
    limits.min_separation = task.min_separation * length
    limits.max_separation = task.max_separation * length
    rest = backend.rest_gripper_poses()
    held = rest[backend.moving, :3]
    if np.any(held < limits.low - 1e-9) or np.any(held > limits.high + 1e-9):
        raise BadInput(
            f"task.workspace_low {list(task.workspace_low)} to task.workspace_high "
            f"{list(task.workspace_high)} excludes the grippers' rest positions "
            f"{np.round(held, 3).tolist()} (m), where every start and goal begins: widen the "
            "workspace to hold them"
        )
    if not backend.moving.all():  # one gripper: no separation to keep
        return
    separation = float(np.linalg.norm(rest[1, :3] - rest[0, :3])) / length
    if task.min_separation - 1e-9 <= separation <= task.max_separation + 1e-9:
        return
    raise BadInput(
        f"task.min_separation {task.min_separation:g} to task.max_separation "
        f"{task.max_separation:g} excludes the grippers' rest separation {separation:.3g} "
        "(fractions of the rod length), where every start and goal begins, so the grippers "
        f"could not move from there; set min_separation <= {separation:.3g} <= max_separation"
    )


def make_shape(
    backend: Backend,
    task: TaskSpec,
    moving: np.ndarray,
    rng: np.random.Generator,
    steps: int,
    recorded: np.ndarray | None = None,
) -> bool:
    """Move ``backend`` (already reset to rest) to a random shape; False if it diverged.

    ``steps`` is the near-rest motion length (random-pose drives until the target is reached);
    ``recorded``: the (K, 2, 7) poses of recorded shapes.
    """
    if task.shapes == "recorded":
        assert recorded is not None
        return shape_at(backend, task, recorded[rng.integers(len(recorded))])
    if task.shapes == "random-pose":
        targets = draw_gripper_targets(backend, task, moving, rng)
        ok = drive_grippers(backend, task, targets, moving)
    else:
        ok = random_motion(backend, task, moving, rng, steps)
    return ok and settle(backend, task.reset_settle_steps)


# ----------------------------------------------------------------------------- random pose
def draw_gripper_targets(
    backend: Backend, task: TaskSpec, moving: np.ndarray, rng: np.random.Generator
) -> np.ndarray:
    """(2,7) target poses: the rest poses with the moving grippers' drawn from the region."""
    rest = backend.rest_gripper_poses()
    limits = backend.limits
    for _ in range(TARGET_DRAWS):
        targets = rest.copy()
        for gripper in np.flatnonzero(moving):
            targets[gripper] = _draw_pose(rest[gripper], task, backend.rod.length, gripper, rng)
        targets[:, :3] = np.clip(targets[:, :3], limits.low, limits.high)
        separation = np.linalg.norm(targets[1, :3] - targets[0, :3])
        if limits.min_separation <= separation <= limits.max_separation:
            return targets
    raise BadInput(
        "no gripper targets inside the workspace and separation limits in "
        f"{TARGET_DRAWS} draws; widen max_separation or narrow the pose region"
    )


def _draw_pose(
    rest: np.ndarray, task: TaskSpec, length: float, gripper: int, rng: np.random.Generator
) -> np.ndarray:
    offset = rng.uniform(task.pose_offset_low, task.pose_offset_high) * length
    rotvec = rng.uniform(-task.pose_max_rotation, task.pose_max_rotation, 3)
    if gripper == 0:  # mirror through x = 0: x flips; a rotation vector (axial) keeps x only
        offset[0] = -offset[0]
        rotvec[1:] = -rotvec[1:]
    quat = quat_normalize(quat_multiply(quat_from_rotvec(rotvec), rest[3:]))
    return np.concatenate([rest[:3] + offset, quat])


def gripper_twists_towards(
    poses: np.ndarray, targets: np.ndarray, task: TaskSpec, moving: np.ndarray
) -> np.ndarray:
    """(2,6) twists that bring ``poses`` to ``targets`` in one control step where the
    velocity limits allow, and at the limits (per component) otherwise."""
    dt = task.control_dt
    linear = (targets[:, :3] - poses[:, :3]) / dt
    angular = rotation_between(poses[:, 3:], targets[:, 3:]) / dt
    twists = np.clip(np.concatenate([linear, angular], axis=1), -max_twist(task), max_twist(task))
    twists[~moving] = 0.0
    return twists


def rotation_between(start: np.ndarray, end: np.ndarray) -> np.ndarray:
    """(...,3) world-frame rotation vectors r, |r| <= pi, with end = exp(r) * start."""
    conjugate = start * np.array([1.0, -1.0, -1.0, -1.0])
    relative = quat_normalize(quat_multiply(end, conjugate))  # w >= 0: the short way round
    sin_half = np.linalg.norm(relative[..., 1:], axis=-1, keepdims=True)
    angle = 2.0 * np.arctan2(sin_half, relative[..., :1])
    scale = np.where(sin_half > 1e-12, angle / np.maximum(sin_half, 1e-12), 2.0)
    return relative[..., 1:] * scale


def drive_grippers(
    backend: Backend, task: TaskSpec, targets: np.ndarray, moving: np.ndarray
) -> bool:
    """Step ``backend`` until the moving grippers reach ``targets`` (or a step budget ends)."""
    budget = 4 * task.episode_steps
    for _ in range(budget):
        twists = gripper_twists_towards(backend.gripper_poses(), targets, task, moving)
        if np.abs(twists).max() * task.control_dt < ARRIVED:
            return True
        if not backend.step(twists):
            return False
    return True


# ----------------------------------------------------------------------------- near rest
def random_motion(
    backend: Backend, task: TaskSpec, moving: np.ndarray, rng: np.random.Generator, steps: int
) -> bool:
    """Piecewise-constant random gripper twists for ``steps`` control steps."""
    velocities = np.zeros((2, 6))
    for t in range(steps):
        if t % MOTION_HOLD_STEPS == 0:
            velocities = rng.uniform(-1.0, 1.0, (2, 6)) * max_twist(task)
            velocities[~moving] = 0.0
        if not backend.step(velocities):
            return False
    return True


def settle(backend: Backend, steps: int) -> bool:
    """Hold the grippers still for ``steps`` control steps."""
    return all(backend.step(np.zeros((2, 6))) for _ in range(steps))


# ----------------------------------------------------------------------------- given poses
#: what ``env.reset(options=...)`` takes: (2, 7) gripper poses of the episode's start or goal
POSE_OPTIONS = ("start_grippers", "goal_grippers")
#: how far a given orientation's norm may lie from 1 and still be normalised (a recording's
#: rounding or float32); farther, it is no unit quaternion (zero, scaled, another layout)
QUATERNION_NORM_TOLERANCE = 0.01


def episode_poses(
    options: dict | None, limits: GripperLimits
) -> tuple[np.ndarray | None, np.ndarray | None]:
    """The start and goal gripper poses in reset ``options`` (None where not given);
    BadOption for an unknown key or poses that are not (2, 7), finite, in the workspace, with
    unit quaternions (norms within ``QUATERNION_NORM_TOLERANCE`` of 1 are normalised)."""
    options = options or {}
    unknown = sorted(set(options) - set(POSE_OPTIONS))
    if unknown:
        raise BadOption(
            f"reset option {unknown[0]!r} is not known; the options are {', '.join(POSE_OPTIONS)}"
        )
    return tuple(_checked_poses(options.get(k), k, limits) for k in POSE_OPTIONS)  # type: ignore[return-value]


def _checked_poses(poses: object, name: str, limits: GripperLimits) -> np.ndarray | None:
    if poses is None:
        return None
    expected = f"reset option {name} must be finite (2, 7) gripper poses (x y z, w qx qy qz)"
    try:
        poses = np.asarray(poses, dtype=np.float64)
    except (TypeError, ValueError):  # text, objects, complex numbers
        raise BadOption(expected) from None
    if poses.shape != (2, 7) or not np.all(np.isfinite(poses)):
        raise BadOption(expected)
    if np.any(poses[:, :3] < limits.low) or np.any(poses[:, :3] > limits.high):
        raise BadOption(f"reset option {name}: a gripper lies outside the task's workspace")
    separation = float(np.linalg.norm(poses[1, :3] - poses[0, :3]))
    if not limits.min_separation <= separation <= limits.max_separation:
        raise BadOption(
            f"reset option {name}: the grippers are {separation:.3f} m apart, outside the "
            f"task's {limits.min_separation:.3f}-{limits.max_separation:.3f} m"
        )
    _check_unit_quaternions(poses[:, 3:], name)
    poses[:, 3:] /= np.linalg.norm(poses[:, 3:], axis=1, keepdims=True)
    return poses


def _check_unit_quaternions(quaternions: np.ndarray, name: str) -> None:
    """BadOption unless each of the (2, 4) finite ``quaternions`` has a norm within
    ``QUATERNION_NORM_TOLERANCE`` of 1: a zero one has no direction, and normalising a huge
    one overflows; either ended deep in the backend as non-finite gripper velocities."""
    with np.errstate(over="ignore"):  # a norm past float's range is inf, refused below
        norms = np.linalg.norm(quaternions, axis=1)
    for side, quaternion, norm in zip(("left", "right"), quaternions, norms, strict=True):
        if not abs(norm - 1.0) <= QUATERNION_NORM_TOLERANCE:
            raise BadOption(
                f"reset option {name}: the {side} gripper's orientation "
                f"{np.array2string(quaternion, precision=3)} has norm {norm:.3g}; expected a "
                f"unit quaternion w x y z (a norm within 1 +- {QUATERNION_NORM_TOLERANCE:g} "
                "is normalised)"
            )


def shape_at(backend: Backend, task: TaskSpec, poses: np.ndarray) -> bool:
    """Drive both grippers of ``backend`` (at rest) to ``poses`` (2, 7) and let the rod
    settle; False if it diverged."""
    both = np.array([True, True])
    return drive_grippers(backend, task, poses, both) and settle(backend, task.reset_settle_steps)


def load_recorded_poses(path: Path, limits: GripperLimits) -> np.ndarray:
    """The (K, 2, 7) gripper poses of a ``recorded_poses`` file, each pair checked like a
    reset option's; BadInput naming the file, the row and the expected format."""
    expected = "expected a .npy file of (K, 2, 7) gripper poses (x y z, w qx qy qz)"
    try:
        poses = np.load(path, allow_pickle=False)
    except (OSError, ValueError, EOFError) as exc:
        raise BadInput(f"recorded_poses {path} could not be read; {expected}") from exc
    if not isinstance(poses, np.ndarray) or poses.ndim != 3 or poses.shape[1:] != (2, 7):
        raise BadInput(f"recorded_poses {path} holds no (K, 2, 7) array; {expected}")
    if len(poses) == 0 or poses.dtype.kind not in "fiu":
        raise BadInput(f"recorded_poses {path} holds no poses; {expected}")
    try:
        return np.stack([_checked_poses(p, f"row {i}", limits) for i, p in enumerate(poses)])
    except BadOption as exc:
        raise BadInput(f"recorded_poses {path}: {exc}".replace("reset option ", "")) from None
