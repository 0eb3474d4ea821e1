"""A recorded cable's calibrated twin as a shape-control task, with episodes from its recordings.

The twin is the calibrated rod (the cable between its grip markers) in a bimanual task in
the recorded cell's geometry: the recordings, shifted into the backend's workspace by one
offset per cable, give the grippers' poses (each at its grip marker, along its held pair,
the roll transported as in the replay), and the workspace is the box they span plus a
margin. The controller observes the recorded cable's markers: the rod's markers at their
mean arc lengths between the grips, and the outer held marker of each pair on its gripper.
So a marker model trained on the recordings plans on the twin unchanged.

An episode's goal is the shape the twin settles into with its grippers at one recorded
frame's poses (the recorded cable was moving there, so the settled shape is not the
recorded one: :func:`goal_gap_mm` says how far it is), its start another frame's, settled.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from dlocli.backends.base import REST_HEIGHT
from dlocli.calibration.fit import Cable
from dlocli.calibration.replay import (
    WORKSPACE_MARGIN,
    centring_offset,
    grip_markers,
    gripper_targets,
)
from dlocli.errors import BadInput
from dlocli.io import atomic_path, write_text_atomic
from dlocli.specs import BackendSpec, EnvSpec, ObservationSpec, TaskSpec


@dataclass(frozen=True)
class TwinSettings:
    """The twin task's own choices (the rod and geometry come from the cable)."""

    episode_steps: int = 300
    max_linear_velocity: float = 0.2  # m/s
    max_angular_velocity: float = 1.0  # rad/s
    noise_mm: float = 2.0
    seed: int = 0


@dataclass(frozen=True)
class Twin:
    """The twin's env spec, and how the recordings map into its workspace."""

    spec: EnvSpec
    offset: np.ndarray  # (3,) added to a recording to put it in the twin's workspace
    grip: tuple[int, int]  # the grip markers
    recordings: list[tuple[str, np.ndarray]]  # the eval recordings, (T, V, 3) each
    held: np.ndarray  # (V,) the held markers

    def poses(self, recording: np.ndarray) -> np.ndarray:
        """(T, 2, 7) the grippers' poses along a recording, in the twin's workspace."""
        return gripper_targets(recording + self.offset, "transported", self.grip)

    def options(self, recording: np.ndarray, start: int, goal: int) -> dict[str, np.ndarray]:
        """``env.reset`` options of the episode from frame ``start`` to frame ``goal``."""
        poses = self.poses(recording)
        return {"start_grippers": poses[start], "goal_grippers": poses[goal]}


def make_twin(
    cable: Cable, calibrated: BackendSpec, rate_hz: float, settings: TwinSettings
) -> Twin:
    """The twin of ``cable`` (:func:`~dlocli.calibration.fit.load_cable`) with the fitted rod
    ``calibrated`` (its calibrated.yaml's backend)."""
    grip = grip_markers(cable.held, calibrated.rod.clamp_compliance)
    length = calibrated.rod.length
    recordings, everything = cable.eval, cable.train + cable.eval
    grips = np.concatenate([r[:, list(grip)] for _, r in everything]).reshape(-1, 3)
    offset = centring_offset(grips, REST_HEIGHT * length)
    shifted = grips + offset
    low = (shifted.min(0) - WORKSPACE_MARGIN) / length
    high = (shifted.max(0) + WORKSPACE_MARGIN) / length
    separation = max(
        float(np.linalg.norm(r[:, grip[1]] - r[:, grip[0]], axis=-1).max()) for _, r in everything
    )
    task = TaskSpec(
        name="bimanual",
        episode_steps=settings.episode_steps,
        control_dt=1.0 / rate_hz,
        max_linear_velocity=settings.max_linear_velocity,
        max_angular_velocity=settings.max_angular_velocity,
        max_separation=min(0.999, max(0.95, separation / length + 0.01)),
        min_separation=0.0,
        workspace_low=tuple(low.tolist()),
        workspace_high=tuple(high.tolist()),
        observation=marker_observation(cable.arc, grip, length, settings.noise_mm),
    )
    spec = EnvSpec(backend=calibrated, task=task, seed=settings.seed)
    return Twin(spec, offset, grip, recordings, cable.held)


def recorded_poses(twin: Twin, recordings: list[np.ndarray], every: int = 10) -> np.ndarray:
    """(K, 2, 7) the grippers' poses at every ``every``-th frame of ``recordings`` (e.g. the
    train ones), inside the twin's separation limit: the shapes a twin task with
    ``shapes: recorded`` draws its starts and goals from."""
    limit = twin.spec.task.max_separation * twin.spec.backend.rod.length
    poses = np.concatenate([twin.poses(r)[::every] for r in recordings])
    separation = np.linalg.norm(poses[:, 1, :3] - poses[:, 0, :3], axis=-1)
    return poses[separation <= limit]


def write_twin_task(twin: Twin, recordings: list[np.ndarray], folder: Path) -> Path:
    """FOLDER/twin.yaml, the twin's backend and task for any command's --spec, its starts and
    goals drawn from FOLDER/poses.npy (:func:`recorded_poses` of ``recordings``)."""
    import yaml

    folder.mkdir(parents=True, exist_ok=True)
    with atomic_path(folder / "poses.npy") as tmp, open(tmp, "wb") as f:
        np.save(f, recorded_poses(twin, recordings))
    task = twin.spec.task.model_copy(
        update={"shapes": "recorded", "recorded_poses": folder / "poses.npy"}
    )
    fields = {"backend": twin.spec.backend, "task": task}
    dumped = {k: v.model_dump(mode="json") for k, v in fields.items()}
    write_text_atomic(folder / "twin.yaml", yaml.safe_dump(dumped, sort_keys=False))
    return folder / "twin.yaml"


def marker_observation(
    arc: np.ndarray, grip: tuple[int, int], length: float, noise_mm: float
) -> ObservationSpec:
    """The recorded markers as the twin's observation: those between the grips on the rod,
    one behind each grip on its gripper (the mean of the two held pairs' spacings)."""
    if grip[0] > 1 or grip[1] < len(arc) - 2:
        raise BadInput(
            "the twin observes at most one held marker behind each grip (on its gripper); "
            "import the cable with at most two held markers at each end (--held)"
        )
    inside = arc[grip[0] : grip[1] + 1] / length
    behind = [arc[grip[0]] - arc[0], arc[-1] - arc[grip[1]]]
    return ObservationSpec(
        kind="markers",
        markers=len(inside),
        marker_arc_lengths=tuple(np.clip(inside, 0.0, 1.0).tolist()),
        gripper_markers=float(np.mean(behind)) / length if grip[0] > 0 else 0.0,
        noise_mm=noise_mm,
    )


def goal_gap_mm(env: object, recorded: np.ndarray, twin: Twin) -> float:
    """Mean distance (mm) of the free markers of ``env``'s goal from the recorded frame's."""
    goal = env.goal_markers() - twin.offset  # type: ignore[attr-defined]
    free = ~twin.held
    return float(np.linalg.norm(goal[free] - recorded[free], axis=-1).mean() * 1e3)
