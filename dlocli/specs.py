"""Run specs: one pydantic model per command, the single source of truth of a run.

Every field has a description; the CLI turns it into ``--help`` text, and flags override
fields of the same name. The resolved spec is saved as ``spec.json`` in every run directory,
so ``dlo <command> --spec RUN/spec.json`` re-runs it. Units: metres, seconds, radians, Pa.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from types import UnionType
from typing import Annotated, Any, ClassVar, Literal, TypeVar, Union, get_args, get_origin

import yaml
from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    ValidationError,
    field_validator,
    model_validator,
)
from pydantic.fields import FieldInfo

from dlocli.errors import BadInput
from dlocli.limits import MAX_COUNT, MAX_PROCESSES, MAX_SEED
from dlocli.registry import backends


def new_default(spec_cls: type[Spec], name: str, default: Any) -> Any:
    """The field ``name`` of ``spec_cls`` with another default, its bounds and description
    kept: a subclass's own value of an inherited option."""
    return FieldInfo.merge_field_infos(spec_cls.model_fields[name], default=default)


#: in a spec's ``cli_flags``: the options of every registered model (``model.FIELD``)
MODEL_OPTIONS = "model.*"


class Spec(BaseModel):
    """Base of all specs: unknown fields are refused, values validated on assignment.

    ``moved`` maps the names of fields that moved to their new dotted path, so spec files
    and saved runs written before the move still load.
    """

    model_config = ConfigDict(extra="forbid", validate_assignment=True, allow_inf_nan=False)
    moved: ClassVar[dict[str, str]] = {}
    #: the fields the spec's command offers as flags, dotted, in --help order (every field is
    #: reachable through --spec FILE); MODEL_OPTIONS stands for every registered model's options
    cli_flags: ClassVar[tuple[str, ...]] = ()
    #: the flagged fields the run cannot do without (--help says "required")
    cli_required: ClassVar[tuple[str, ...]] = ()

    @classmethod
    def field_of(cls, name: str) -> Any:
        """The FieldInfo of the field ``name`` (KeyError if there is none)."""
        return cls.model_fields[name]

    @model_validator(mode="before")
    @classmethod
    def _move_fields(cls, data: Any) -> Any:
        if not isinstance(data, dict) or not any(old in data for old in cls.moved):
            return data
        data = dict(data)
        for old, dotted in cls.moved.items():
            if old in data:
                _set_dotted(data, dotted, data.pop(old), copy=True)
        return data

    @field_validator("*")
    @classmethod
    def _utf8_paths(cls, value: Any) -> Any:
        # a path of undecodable bytes cannot be saved in spec.json, nor the run re-run from it
        if isinstance(value, Path):
            require_utf8_path(value)
        return value


#: the torch device a run computes on (one meaning in every spec that has one)
Device = Annotated[
    str,
    Field(description="Torch device: auto (CUDA if present, else the CPU), cpu, cuda or cuda:K."),
]


def require_utf8_path(path: Path) -> None:
    """Refuse a path whose name is not valid UTF-8 (bytes the shell passed undecoded)."""
    try:
        str(path).encode("utf-8")
    except UnicodeEncodeError:
        shown = os.fsencode(path).decode("utf-8", "backslashreplace")
        raise ValueError(
            f"the path {shown} is not valid UTF-8; use a name of UTF-8 characters"
        ) from None


# --------------------------------------------------------------------------- physics
#: most control steps of a reset's motion or settling: each is a control period of physics
MAX_RESET_STEPS = 10_000

STANDARD_GRAVITY = 9.81  # m/s^2
#: s, the rod's bending and twist damping time: the paper rod's first mode gets ratio 0.044
DEFAULT_DAMPING_TIME = 0.05
INEXTENSIBLE_YOUNG_TENSION = 1e8  # Pa, the paper's; the only value a spec may give


def default_backend() -> str:
    """The MuJoCo rod that the installed MuJoCo runs: the composite cable ("mujoco") on 3.x,
    the flex rod ("mujoco-flex") from 4.0 on, which removed the cable. Read from the installed
    package's metadata, so choosing it imports no MuJoCo."""
    from importlib.metadata import PackageNotFoundError, version

    try:
        major = int(version("mujoco").split(".")[0])
    except (PackageNotFoundError, ValueError):
        return "mujoco"
    return "mujoco" if major < 4 else "mujoco-flex"


def segment_limit_error(backend: str, limit: int | None, n_segments: int) -> str | None:
    """Why ``backend``, which simulates at most ``limit`` segments (None: no limit of its
    own), cannot simulate ``n_segments`` segments, or None if it can."""
    if limit is None or n_segments <= limit:
        return None
    return (
        f"the {backend} backend simulates at most {limit} rod segments, got {n_segments}; "
        "use fewer segments or another backend"
    )


class RodSpec(Spec):
    """The deformable linear object. Defaults are the paper's material."""

    length: float = Field(1.0, ge=0.05, le=3, description="Rod length in metres (0.05 to 3).")
    n_segments: int = Field(20, ge=4, le=200, description="Number of rigid segments.")
    radius: float = Field(
        0.01, ge=1e-4, le=0.1, description="Rod cross-section radius in metres (1e-4 to 0.1)."
    )
    density: float = Field(
        1000.0, ge=10, le=1e5, description="Material density in kg/m^3 (10 to 1e5)."
    )
    young_tension: float = Field(
        INEXTENSIBLE_YOUNG_TENSION,
        gt=0,
        description="Young's modulus in tension (Pa). Every backend's rod is inextensible, so "
        "only the paper's 1e8 is accepted.",
    )
    young_bending: float = Field(
        1e7, ge=1e4, le=1e12, description="Young's modulus in bending/twist (Pa, 1e4 to 1e12)."
    )
    poisson: float = Field(0.33, ge=0, lt=0.5, description="Poisson's ratio (0 to 0.5).")
    clamp_compliance: Literal["half-segment", "rigid"] = Field(
        "half-segment",
        description="How a held rod end bends in its gripper. 'half-segment': a joint at the "
        "gripper with the compliance of the half segment it stands for (stiffnesses 2 E I / l "
        "and 2 G J / l), so statics converge to the continuum's as 1/N^2 (within 1% at N = "
        "20). 'rigid': the end segment is rigid in the gripper, the rod of runs made before "
        "this field (a cantilever deflects about (1 - 1/N)^2 of the continuum's).",
    )
    bending_damping: float | None = Field(
        DEFAULT_DAMPING_TIME,
        ge=0,
        description="Bending damping time beta in seconds (Kelvin-Voigt: each joint's bending "
        "moment is (E I / l) (angle + beta * angular rate), a material of viscosity beta E). "
        "A bending mode of angular frequency w gets the damping ratio beta w / 2: the first "
        "mode of the 1 m paper rod (1.76 rad/s) 0.044 at the default 0.05. None = each "
        "backend's earlier constant (mujoco 0.05, pybullet two physics steps), the rod of runs "
        "saved before this field. MuJoCo's elasticity is explicit: with little damping it "
        "needs a smaller physics_dt; PyBullet's springs and damping are explicit: at its 2 ms "
        "default it adds rotary inertia to the segments (see the README's rod physics).",
    )
    twist_damping: float | None = Field(
        DEFAULT_DAMPING_TIME,
        ge=0,
        description="Twist damping time in seconds: each joint's twisting moment is (G J / l) "
        "(angle + time * angular rate); a twist mode of angular frequency w gets the damping "
        "ratio time * w / 2. None = each backend's earlier constant (mujoco the bending "
        "coefficient, a time of (1 + poisson) * 0.05; pybullet two physics steps).",
    )
    air_damping: float | None = Field(
        0.0,
        ge=0,
        description="Air damping d in 1/s: every segment's velocity v and angular velocity w "
        "decay at d (1 + |v|) v and d (1 + |w|) w (|v| in m/s, |w| in rad/s; PyBullet's "
        "velocity damping law); slow motions of every mode of angular frequency w get the "
        "damping ratio d / (2 w). None = each backend's earlier constant (mujoco 0, pybullet "
        "5).",
    )

    @field_validator("young_tension")
    @classmethod
    def _inextensible(cls, value: float) -> float:
        # kept as a field so that specs and runs saved with it still load
        if value != INEXTENSIBLE_YOUNG_TENSION:
            raise ValueError(
                "every backend's rod is inextensible, so young_tension changes nothing; "
                f"remove it or leave it at {INEXTENSIBLE_YOUNG_TENSION:g}"
            )
        return value

    @property
    def segment_length(self) -> float:
        return self.length / self.n_segments

    @property
    def area(self) -> float:
        return 3.141592653589793 * self.radius**2

    @property
    def second_moment(self) -> float:
        """Area second moment I = pi r^4 / 4 (m^4)."""
        return 3.141592653589793 * self.radius**4 / 4

    @property
    def bending_stiffness(self) -> float:
        """EI in N m^2, with E the bending modulus."""
        return self.young_bending * self.second_moment

    @property
    def torsional_stiffness(self) -> float:
        """GJ in N m^2, G = E / (2 (1 + nu)), J = 2 I."""
        shear = self.young_bending / (2 * (1 + self.poisson))
        return shear * 2 * self.second_moment

    @property
    def mass(self) -> float:
        return self.density * self.area * self.length


class BackendSpec(Spec):
    """Which simulator holds the rod, and how finely it integrates."""

    name: str = Field(
        default_factory=default_backend,
        description="Simulator backend (see `dlo list`); default: the MuJoCo rod of the "
        "installed MuJoCo, 'mujoco' (composite cable) on 3.x, 'mujoco-flex' on 4.x.",
    )
    physics_dt: float | None = Field(
        None,
        ge=1e-5,
        le=0.02,
        description="Physics step in seconds (1e-5 to 0.02); None = the backend's stable default. "
        "With little damping the explicit springs need the step of the rod's fastest mode, "
        "dlocli.backends.base.material_physics_dt (the 1 m paper rod 0.17 ms, a 0.2 m rod "
        "33 us); there PyBullet's segments also keep their real rotary inertia.",
    )
    gravity: float = Field(
        STANDARD_GRAVITY,
        ge=0,
        le=100,
        description="Gravitational acceleration in m/s^2, along -z (0 to 100; 0 puts the rod "
        "in free space, for physics checks).",
    )
    held_ends: Literal["both", "left"] = Field(
        "both", description="Which rod ends the grippers hold ('left' leaves a free cantilever)."
    )
    rod: RodSpec = Field(default_factory=RodSpec, description="Rod geometry and material.")

    @model_validator(mode="after")
    def _within_segment_limit(self) -> BackendSpec:
        if self.name not in backends:  # the run refuses it by name, with the valid ones
            return self
        limit = backends.facts(self.name).max_segments
        error = segment_limit_error(self.name, limit, self.rod.n_segments)
        if error:
            raise ValueError(error)
        return self


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
    exact state ("full"), or tracked marker positions ("markers") with a tracker's faults."""

    kind: Literal["full", "markers"] = Field(
        "full",
        description="'full': every segment's position, orientation and velocity, exact and "
        "at once; 'markers': positions of tracked markers only, with the faults below.",
    )
    markers: int = Field(
        10, ge=2, le=1000,
        description="Markers M, evenly spaced from the rod's left end to its right end, where "
        "the grippers hold it (unless marker_arc_lengths places them).",
    )  # fmt: skip
    marker_arc_lengths: tuple[Annotated[float, Field(ge=0.0, le=1.0)], ...] | None = Field(
        None,
        description="Where the markers sit, as fractions of the rod length from its left end "
        "(0 to 1, increasing); those on a held end segment move with its gripper.",
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
    occlusion_steps: int = Field(
        10, ge=1, le=MAX_COUNT, description="Frames an occlusion lasts."
    )

    def faults(self) -> dict[str, Any]:
        """The tracker faults set away from their defaults (a clean tracker: empty)."""
        names = ("noise_mm", "latency_steps", "dropout", "occlusion_probability")
        fields = type(self).model_fields
        return {n: getattr(self, n) for n in names if getattr(self, n) != fields[n].default}

    @model_validator(mode="after")
    def _markers_consistent(self) -> ObservationSpec:
        arcs = self.marker_arc_lengths
        if arcs is not None and any(b <= a for a, b in zip(arcs, arcs[1:])):
            raise ValueError("marker_arc_lengths must increase along the rod")
        if arcs is not None and len(arcs) < 2:
            raise ValueError("marker_arc_lengths: give at least 2 markers")
        if self.kind == "full" and self.faults():
            raise ValueError(
                f"{', '.join(self.faults())} apply to tracked markers: set observation kind "
                "'markers' (--observation markers)"
            )
        return self

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
        0.95, gt=0, lt=1, description="Largest gripper separation as a fraction of the rod length."
    )
    min_separation: float = Field(
        0.2, ge=0, lt=1, description="Smallest gripper separation as a fraction of the rod length."
    )
    workspace_low: tuple[float, float, float] = Field(
        (-0.8, -0.6, 0.3), description="Gripper workspace lower corner (x, y, z) in metres."
    )
    workspace_high: tuple[float, float, float] = Field(
        (0.8, 0.6, 1.4), description="Gripper workspace upper corner (x, y, z) in metres."
    )
    shapes: Literal["random-pose", "near-rest"] = Field(
        "random-pose",
        description="How episode starts and goals are made: 'random-pose' drives the moving "
        "grippers to random poses in the pose region and lets the rod settle (the paper's "
        "scale: tens of cm apart); 'near-rest' moves them randomly for reset_motion_steps "
        "from rest (a few cm apart; fast tests).",
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
        if self.shapes == "near-rest":
            return {"pose_offset_low", "pose_offset_high", "pose_max_rotation"}
        return {"reset_motion_steps"}

    @model_validator(mode="after")
    def _regions_ordered(self) -> TaskSpec:
        for low, high in (("pose_offset_low", "pose_offset_high"),
                          ("workspace_low", "workspace_high")):  # fmt: skip
            pairs = zip(getattr(self, low), getattr(self, high), strict=True)
            if any(lo > hi for lo, hi in pairs):
                raise ValueError(f"{low} must not exceed {high} in any axis")
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


SpecT = TypeVar("SpecT", bound=Spec)


#: limits of a spec file: a spec is a few hundred lines; YAML aliases can make a few hundred
#: bytes expand to gigabytes, so aliases and nodes are counted while the file is read
MAX_SPEC_BYTES = 1_000_000
MAX_YAML_NODES = 20_000
MAX_YAML_ALIASES = 20


class _BoundedLoader(yaml.SafeLoader):
    """yaml.SafeLoader that refuses documents with too many nodes or aliases."""

    def compose_node(self, parent: Any, index: Any) -> Any:
        if self.check_event(yaml.AliasEvent):
            self.aliases = getattr(self, "aliases", 0) + 1
            if self.aliases > MAX_YAML_ALIASES:
                raise yaml.YAMLError(f"more than {MAX_YAML_ALIASES} aliases")
        self.nodes = getattr(self, "nodes", 0) + 1
        if self.nodes > MAX_YAML_NODES:
            raise yaml.YAMLError(f"more than {MAX_YAML_NODES} nodes")
        return super().compose_node(parent, index)


def _load_yaml(text: str) -> Any:
    loader = _BoundedLoader(text)
    try:
        return loader.get_single_data()
    finally:
        loader.dispose()


def load_spec_file(path: Path) -> dict[str, Any]:
    """Read a YAML or JSON spec file with safe loaders; BadInput on any problem."""
    path = Path(path)
    if not path.is_file():
        raise BadInput(f"spec file {path} does not exist; pass an existing .yaml/.json file")
    if path.stat().st_size > MAX_SPEC_BYTES:
        raise BadInput(
            f"spec file {path} is {path.stat().st_size} bytes, more than a spec needs "
            f"({MAX_SPEC_BYTES}); pass the run spec file, not data"
        )
    try:
        text = path.read_text()
        data = json.loads(text) if path.suffix == ".json" else _load_yaml(text)
    except (OSError, ValueError, yaml.YAMLError, RecursionError) as exc:  # Recursion: nesting
        first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise BadInput(
            f"spec file {path} is not valid YAML/JSON ({first}); fix or remove it"
        ) from exc
    if data is None:
        data = {}
    if not isinstance(data, dict):
        raise BadInput(f"spec file {path} must hold a mapping of fields, not {type(data).__name__}")
    return data


def _set_dotted(data: dict[str, Any], dotted: str, value: Any, copy: bool = False) -> None:
    """Set ``data[a][b]... = value`` for ``dotted`` "a.b...", making the dicts on the way
    (with ``copy``: fresh copies of those there, so the caller's nested dicts stay as they were)."""
    keys = dotted.split(".")
    for key in keys[:-1]:
        node = data.get(key)
        if isinstance(node, BaseModel):  # a spec given as an instance, e.g. task=TaskSpec(...)
            node = node.model_dump()
        node = (dict(node) if copy else node) if isinstance(node, dict) else {}
        data[key] = node
        data = node
    data[keys[-1]] = value


def format_validation_error(exc: ValidationError, source: str = "spec") -> str:
    """One line naming the first bad field and what is expected."""
    err = exc.errors()[0]
    field = ".".join(str(p) for p in err["loc"]) or "(root)"
    if err["type"] == "extra_forbidden":
        return f"{source}: unknown field '{field}'; remove it (see --help for valid fields)"
    return f"{source}: field '{field}': {err['msg']} (got {_bounded_repr(err.get('input'))})"


def _bounded_repr(value: Any) -> str:
    """repr of a value cut to a few elements and levels: an input built from YAML aliases
    can expand to gigabytes if printed whole."""
    import reprlib

    short = reprlib.Repr()
    short.maxlevel, short.maxlist, short.maxdict, short.maxstring, short.maxother = 2, 4, 4, 60, 60
    return short.repr(value)


def resolve_spec(
    cls: type[SpecT], spec_file: Path | None = None, overrides: dict[str, Any] | None = None
) -> SpecT:
    """Build a spec: defaults, then the spec file, then non-None overrides (dotted field paths)."""
    data: dict[str, Any] = load_spec_file(spec_file) if spec_file is not None else {}
    for dotted, value in (overrides or {}).items():
        if value is not None:
            _set_dotted(data, dotted, value)
    try:
        return cls.model_validate(data)
    except ValidationError as exc:
        raise BadInput(format_validation_error(exc, str(spec_file or "spec"))) from exc


def field_info(cls: type[Spec], dotted: str) -> Any:
    """The pydantic FieldInfo of a possibly nested field (``task.episode_steps``)."""
    model: Any = cls
    info = None
    for key in dotted.split("."):
        info = model.field_of(key)
        model = strip_none(info.annotation)
    return info


def strip_none(annotation: Any) -> Any:
    """``X`` of ``X | None``; other annotations as they are."""
    if get_origin(annotation) in (Union, UnionType):
        return next(a for a in get_args(annotation) if a is not type(None))
    return annotation
