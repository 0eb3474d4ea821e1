"""Run specs: one pydantic model per command, the single source of truth of a run.

Every field has a description; the CLI turns it into ``--help`` text, and flags override
fields of the same name. The resolved spec is saved as ``spec.json`` in every run directory,
so ``dlo <command> --spec RUN/spec.json`` re-runs it. Units: metres, seconds, radians, Pa.

Here: the task, its safety envelope and the specs of the commands that build an env. The
base and the loaders (:mod:`dlocli.spec_base`) and the rod and backend specs
(:mod:`dlocli.backend_spec`) are importable from here as well.
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Any, ClassVar, Literal

from pydantic import Field, ValidationInfo, model_validator

from dlocli.backend_spec import (
    DEFAULT_DAMPING_TIME,
    INEXTENSIBLE_YOUNG_TENSION,
    STANDARD_GRAVITY,
    BackendSpec,
    RodSpec,
    default_backend,
    segment_limit_error,
)
from dlocli.camera_spec import CameraSpec, TrackerSpec
from dlocli.limits import MAX_COUNT, MAX_PROCESSES, MAX_SEED
from dlocli.spec_base import (
    GIVEN,
    MAX_SPEC_BYTES,
    MAX_YAML_ALIASES,
    MAX_YAML_NODES,
    MODEL_OPTIONS,
    SAVED_SPEC,
    Device,
    RetiredField,
    Spec,
    SpecT,
    field_info,
    format_validation_error,
    is_given,
    load_spec_file,
    new_default,
    require_utf8_path,
    resolve_spec,
    strip_none,
    validated,
)

__all__ = [
    "DEFAULT_DAMPING_TIME", "GIVEN", "INEXTENSIBLE_YOUNG_TENSION", "MAX_RESET_STEPS",
    "MAX_SPEC_BYTES", "MAX_YAML_ALIASES", "MAX_YAML_NODES", "MODEL_OPTIONS", "SAVED_SPEC",
    "STANDARD_GRAVITY", "BackendSpec", "Box", "CollectSpec", "Device", "EnvSpec",
    "EnvelopeSpec", "GoalSpec", "RetiredField", "RodSpec", "Spec", "SpecT", "TaskSpec",
    "default_backend", "field_info", "format_validation_error", "is_given", "load_spec_file",
    "new_default", "require_utf8_path", "resolve_spec", "segment_limit_error", "strip_none",
    "validated",
]  # fmt: skip

#: most control steps of a reset's motion or settling: each is a control period of physics
MAX_RESET_STEPS = 10_000


Box = tuple[float, float, float]


class EnvelopeSpec(Spec):
    """Limits on the grippers' commands beyond the task's (None: no such limit)."""

    max_linear_speed: float | None = Field(
        None, gt=0.0, le=2.0, description="Largest linear speed of a gripper (m/s, its norm)."
    )
    max_angular_speed: float | None = Field(
        None, gt=0.0, le=10.0, description="Largest angular speed of a gripper (rad/s, norm)."
    )
    max_linear_acceleration: float | None = Field(
        None, gt=0.0, le=100.0,
        description="Largest change of a gripper's linear velocity per second (m/s^2, norm).",
    )  # fmt: skip
    max_angular_acceleration: float | None = Field(
        None, gt=0.0, le=1000.0,
        description="Largest change of a gripper's angular velocity per second (rad/s^2, norm).",
    )  # fmt: skip
    stop_after_lost_s: float | None = Field(
        None, gt=0.0, le=60.0,
        description="With the cable's tracking lost for longer than this (s), the grippers "
        "stop (zero velocity) and hold until it returns.",
    )  # fmt: skip
    left_low: Box | None = Field(None, description="Left gripper's box, low corner (metres).")
    left_high: Box | None = Field(None, description="Left gripper's box, high corner (metres).")
    right_low: Box | None = Field(None, description="Right gripper's box, low corner (metres).")
    right_high: Box | None = Field(None, description="Right gripper's box, high corner (metres).")

    @model_validator(mode="after")
    def _boxes_whole(self) -> EnvelopeSpec:
        for side in ("left", "right"):
            low, high = getattr(self, f"{side}_low"), getattr(self, f"{side}_high")
            if (low is None) != (high is None):
                raise ValueError(f"envelope: give both {side}_low and {side}_high, or neither")
            if low is not None and any(lo >= hi for lo, hi in zip(low, high, strict=True)):
                raise ValueError(f"envelope: {side}_low must lie below {side}_high on every axis")
        return self


class ObservationSpec(Spec):
    """What every controller, agent and online trial observes of the rod: the simulator's
    exact state ("full"), tracked marker positions ("markers") with a tracker's faults, or
    the markers a tracker finds in a depth camera's point clouds ("pointcloud")."""

    kind: Literal["full", "markers", "pointcloud"] = Field(
        "full",
        description="'full': every segment's position, orientation and velocity, exact and "
        "at once; 'markers': positions of tracked markers only, with the faults below; "
        "'pointcloud': the markers the tracker finds in a depth camera's clouds (the camera "
        "and tracker options, through --spec).",
    )
    markers: int = Field(
        10, ge=2, le=1000,
        description="Markers M, evenly spaced from the rod's left end to its right end, where "
        "the grippers hold it (unless marker_arc_lengths places them).",
    )  # fmt: skip
    marker_arc_lengths: tuple[Annotated[float, Field(ge=-0.5, le=1.5)], ...] | None = Field(
        None,
        description="Where the markers sit, as fractions of the rod length from its left end, "
        "increasing: 0 to 1 on the rod (those on a held end segment move with its gripper), "
        "below 0 or above 1 on the left or right gripper, that far behind the rod's end along "
        "its axis (as gripper_markers places one; then set gripper_markers 0).",
    )
    gripper_markers: float = Field(
        0.05, ge=0.0, le=0.5,
        description="A marker on each gripper, this far behind the rod's end along the "
        "gripper's axis (a fraction of the rod length; 0: none): the rod's end point does not "
        "show how the gripper turns, this marker does.",
    )  # fmt: skip
    noise_mm: float = Field(
        0.0, ge=0.0, le=1000.0, allow_inf_nan=False,
        description="Standard deviation of the Gaussian noise on each marker coordinate (mm).",
    )  # fmt: skip
    latency_steps: int = Field(
        0, ge=0, le=MAX_COUNT,
        description="The tracker's delay in control steps: a frame shows the rod as it was "
        "this many steps earlier (the gripper poses are the robot's own, current).",
    )  # fmt: skip
    dropout: float = Field(
        0.0, ge=0.0, lt=1.0,
        description="Probability that a frame is lost: every marker is reported missing and "
        "keeps its last seen position.",
    )  # fmt: skip
    occlusion_probability: float = Field(
        0.0, ge=0.0, le=1.0,
        description="Probability per frame that an occlusion starts: occlusion_markers "
        "neighbouring markers at a random place go missing for occlusion_steps frames.",
    )  # fmt: skip
    occlusion_markers: int = Field(
        3, ge=1, le=1000, description="Neighbouring markers an occlusion hides."
    )
    occlusion_steps: int = Field(10, ge=1, le=MAX_COUNT, description="Frames an occlusion lasts.")
    camera: CameraSpec | None = Field(
        None, description="The depth camera of the pointcloud observation (None: the defaults)."
    )
    tracker: TrackerSpec | None = Field(
        None, description="The tracker of the pointcloud observation (None: the defaults)."
    )

    def faults(self) -> dict[str, Any]:
        """The tracker faults set away from their defaults (a clean tracker: empty)."""
        names = ("noise_mm", "latency_steps", "dropout", "occlusion_probability")
        fields = type(self).model_fields
        return {n: getattr(self, n) for n in names if getattr(self, n) != fields[n].default}

    @model_validator(mode="after")
    def _markers_consistent(self, info: ValidationInfo) -> ObservationSpec:
        arcs = self.marker_arc_lengths
        counted = "markers" in self.model_fields_set and is_given(info)  # saved runs: as saved
        if arcs is not None and counted and self.markers != len(arcs):
            raise ValueError(
                f"markers {self.markers}, but marker_arc_lengths places {len(arcs)}: drop "
                "--markers (the arc lengths count them) or give as many arc lengths"
            )
        if arcs is not None and any(b <= a for a, b in zip(arcs, arcs[1:], strict=False)):
            raise ValueError("marker_arc_lengths must increase along the rod")
        if arcs is not None and len(arcs) < 2:
            raise ValueError("marker_arc_lengths: give at least 2 markers")
        if arcs is not None and self.gripper_markers > 0 and (arcs[0] < 0 or arcs[-1] > 1):
            raise ValueError(
                "marker_arc_lengths below 0 or above 1 place markers on the grippers: set "
                "gripper_markers 0 (--gripper-markers 0)"
            )
        if self.kind == "pointcloud" and self.faults():
            raise ValueError(
                f"{', '.join(self.faults())} fault tracked markers; a pointcloud observation's "
                "faults are its camera's: set camera.noise_mm, camera.invalid_fraction, ..."
            )
        if self.kind == "full" and self.faults():
            raise ValueError(
                f"{', '.join(self.faults())} apply to tracked markers: set observation kind "
                "'markers' (--observation markers)"
            )
        return self

    @property
    def reports_markers(self) -> bool:
        """Whether the controller sees markers (tracked ones, or found in point clouds)."""
        return self.kind != "full"

    def marker_count(self) -> int:
        """M: the markers on the rod, and those on the grippers."""
        on_rod = self.markers if self.marker_arc_lengths is None else len(self.marker_arc_lengths)
        return on_rod + (2 if self.gripper_markers > 0 else 0)


class TaskSpec(Spec):
    """The shape-control task on top of a backend (DLOShapeEnv)."""

    name: str = Field(
        "single", description="'single' (6-D action, right gripper) or 'bimanual' (12-D)."
    )
    goal: Literal["fixed", "random"] = Field(
        "fixed",
        description="'fixed': one goal for the whole run (paper); 'random': new each episode.",
    )
    goal_file: Path | None = Field(
        None, description="Goal shape .npy (N,3) in metres; overrides `goal`."
    )
    episode_steps: int = Field(
        200, gt=0, le=MAX_COUNT, description="Control steps per episode (T)."
    )
    control_dt: float = Field(
        0.02, ge=1e-3, le=1, description="Control period in seconds (50 Hz; 1e-3 to 1)."
    )
    max_linear_velocity: float = Field(
        0.1, gt=0, le=2, description="Gripper speed at action 1 (m/s, at most 2)."
    )
    max_angular_velocity: float = Field(
        0.5, gt=0, le=10, description="Gripper angular speed at action 1 (rad/s, at most 10)."
    )
    max_separation: float = Field(
        0.95,
        gt=0,
        lt=1,
        description="Largest gripper separation as a fraction of the rod length (at least the "
        "grippers' rest separation, 0.9).",
    )
    min_separation: float = Field(
        0.2,
        ge=0,
        lt=1,
        description="Smallest gripper separation as a fraction of the rod length (at most the "
        "grippers' rest separation, 0.9).",
    )
    workspace_low: tuple[float, float, float] = Field(
        (-0.8, -0.6, 0.3), description="Gripper workspace lower corner (x, y, z) in metres."
    )
    workspace_high: tuple[float, float, float] = Field(
        (0.8, 0.6, 1.4), description="Gripper workspace upper corner (x, y, z) in metres."
    )
    shapes: Literal["random-pose", "near-rest", "recorded"] = Field(
        "random-pose",
        description="How episode starts and goals are made: 'random-pose' drives the moving "
        "grippers to random poses in the pose region and lets the rod settle (the paper's "
        "scale: tens of cm apart); 'near-rest' moves them randomly for reset_motion_steps "
        "from rest (a few cm apart; fast tests); 'recorded' drives them to poses drawn from "
        "recorded_poses (a recorded cell's).",
    )
    recorded_poses: Path | None = Field(
        None,
        description="recorded shapes: a .npy of (K, 2, 7) gripper poses (x y z in metres, "
        "then the w x y z unit quaternion; norms within 1% of 1 are normalised) that starts "
        "and goals are drawn from.",
    )
    pose_offset_low: tuple[float, float, float] = Field(
        (-0.3, -0.15, -0.15),
        description="Lower corner of the right gripper's position offset from rest, in rod "
        "lengths (the left gripper's region is its mirror image through x = 0).",
    )
    pose_offset_high: tuple[float, float, float] = Field(
        (0.0, 0.15, 0.15),
        description="Upper corner of the right gripper's position offset from rest, in rod "
        "lengths.",
    )
    pose_max_rotation: float = Field(
        0.5,
        ge=0,
        le=1.5,
        allow_inf_nan=False,
        description="Bound (rad) of each component of the world-frame rotation vector that "
        "turns a gripper from its rest orientation.",
    )
    reset_motion_steps: int = Field(
        40,
        ge=0,
        le=MAX_RESET_STEPS,
        description="near-rest shapes: random gripper-motion steps (then settle).",
    )
    reset_settle_steps: int = Field(
        40, ge=0, le=MAX_RESET_STEPS, description="Zero-velocity steps to let the rod settle."
    )
    observe_velocity: bool = Field(
        True,
        description="Append each segment's velocity (its position and quaternion change over "
        "the last control step, divided by the step) to the observation: the information the "
        "learned model's velocity input gets, for every agent.",
    )
    envelope: EnvelopeSpec = Field(
        default_factory=EnvelopeSpec,
        description="Safety envelope every command passes through (limits beyond the task's).",
    )
    observation: ObservationSpec = Field(
        default_factory=ObservationSpec,
        description="What the controller observes: the exact state or tracked markers.",
    )

    def inert_fields(self) -> set[str]:
        """Fields that do not change any result under this spec's ``shapes``."""
        pose_region = {"pose_offset_low", "pose_offset_high", "pose_max_rotation"}
        if self.shapes == "near-rest":
            return pose_region | {"recorded_poses"}
        if self.shapes == "recorded":
            return pose_region | {"reset_motion_steps"}
        return {"reset_motion_steps", "recorded_poses"}

    @model_validator(mode="after")
    def _regions_ordered(self) -> TaskSpec:
        for low, high in (("pose_offset_low", "pose_offset_high"),
                          ("workspace_low", "workspace_high")):  # fmt: skip
            pairs = zip(getattr(self, low), getattr(self, high), strict=True)
            if any(lo > hi for lo, hi in pairs):
                raise ValueError(f"{low} must not exceed {high} in any axis")
        if (self.shapes == "recorded") != (self.recorded_poses is not None):
            raise ValueError(
                "recorded_poses is the file of shapes 'recorded' (and of no other): give both "
                "or neither"
            )
        if self.min_separation > self.max_separation:
            raise ValueError(
                f"min_separation {self.min_separation} exceeds max_separation {self.max_separation}"
            )
        if self.observation.latency_steps >= self.episode_steps:
            raise ValueError(
                f"observation latency_steps {self.observation.latency_steps} must be shorter "
                f"than the episode ({self.episode_steps} steps)"
            )
        return self


# --------------------------------------------------------------------------- commands
class EnvSpec(Spec):
    """Backend + task: everything needed to build a DLOShapeEnv."""

    backend: BackendSpec = Field(default_factory=BackendSpec, description="Simulator.")
    task: TaskSpec = Field(default_factory=TaskSpec, description="Task.")
    seed: int = Field(0, ge=0, le=MAX_SEED, description="Seed of every random stream of the run.")


class GoalSpec(EnvSpec):
    """`dlo goal`: a reachable goal shape from moving the grippers and letting the rod settle."""

    cli_flags: ClassVar[tuple[str, ...]] = (
        "out", "backend.name", "task.name", "task.shapes", "seed",
    )  # fmt: skip

    out: Path = Field(Path("goal.npy"), description="Output .npy file (N,3), metres.")


class CollectSpec(EnvSpec):
    """`dlo collect --random`: random-action trajectories into an HDF5 dataset."""

    moved: ClassVar[dict[str, str]] = {"steps": "task.episode_steps"}
    cli_flags: ClassVar[tuple[str, ...]] = (
        "out", "backend.name", "task.name", "task.shapes", "task.goal", "episodes",
        "task.episode_steps", "seed", "workers",
    )  # fmt: skip

    episodes: int = Field(10, gt=0, le=MAX_COUNT, description="Number of episodes.")
    workers: int = Field(
        1, gt=0, le=MAX_PROCESSES,
        description="Parallel worker processes (same data as 1 worker; at most one per CPU).",
    )  # fmt: skip
    out: Path = Field(Path("runs/collect"), description="Run directory for the dataset.")
