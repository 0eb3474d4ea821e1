"""The spec of `dlo calibrate` (torch-free: the CLI builds its --help without torch)."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Any, ClassVar, Literal

from pydantic import BeforeValidator, Field, field_validator, model_validator

from dlocli.calibration.parameters import PARAMETERS
from dlocli.executors import ExecutorChoice
from dlocli.limits import MAX_CLUSTER_WORKERS, MAX_COUNT, MAX_SEED
from dlocli.specs import BackendSpec, RodSpec, Spec

#: the longest source rod (m) `dlo family` takes
MAX_SOURCE_ROD = 3.0


def _as_list(value: Any) -> Any:
    """One value where a list is taken (a spec written before the field became a list)."""
    return [] if value is None else value if isinstance(value, (list, tuple)) else [value]


class CableRodSpec(RodSpec):
    """A cable's rod: 1 cm thick (the radius only sets the scale of E, since E I is fitted),
    segments of about 4 cm (with rigid clamps a held marker pair, 2-3 cm apart, lies in the
    held segment)."""

    radius: float = Field(
        0.005, ge=1e-4, le=0.1, description="Rod cross-section radius in metres (1e-4 to 0.1)."
    )
    n_segments: int = Field(24, ge=4, le=200, description="Number of rigid segments.")
    clamp_compliance: Literal["half-segment", "rigid"] = Field(
        "half-segment",
        description="How a held rod end bends in its gripper, and so where the gripper holds "
        "it: 'half-segment' (a free rod's default) bends at the grip, which is then the inner "
        "marker of each held pair (the outer one rides on the gripper); 'rigid' makes the end "
        "segment part of the gripper, which then holds the rod at the end markers.",
    )


class CableBackendSpec(BackendSpec):
    """The simulator of a calibration, holding a :class:`CableRodSpec`."""

    rod: CableRodSpec = Field(
        default_factory=CableRodSpec, description="Rod geometry and material."
    )


class ReplaySpec(Spec):
    """How a recorded cable's held-marker motion is replayed on a simulated rod: the fields
    `dlo calibrate` and `dlo family` share (:class:`dlocli.calibration.replay.ReplaySettings`)."""

    roll: Literal["transported", "level"] = Field(
        "transported",
        description="How the grippers' unrecorded roll about the cable axis is chosen: "
        "'transported' turns it with the axis (no spin), 'level' keeps the gripper's y axis "
        "horizontal.",
    )
    approach_s: float = Field(
        1.0, gt=0, le=10, description="Seconds to move the grippers from rest to frame 0."
    )
    settle_s: float = Field(
        1.0, ge=0, le=10, description="Seconds the rod settles at frame 0 before the replay."
    )


class CalibrateSpec(ExecutorChoice, ReplaySpec):
    """`dlo calibrate`: fit a simulated rod's material to a recorded cable's motion. Its jobs
    are the replays of each generation's candidates (local processes or Ray tasks)."""

    cli_flags: ClassVar[tuple[str, ...]] = (
        "source", "cable_length", "cable_mass", "rod_length", "backend.name", "parameters",
        "roll", "train_trajectories", "generations", "population", "workers", "executor",
        "ray_address", "seed", "out",
    )  # fmt: skip

    source: Path | None = Field(
        None,
        description="One cable's recordings: a folder in the DEFORM layout (train/*.pkl and "
        "eval/*.pkl, each a pickled (frames, 3, markers) list of metres), or a `dlo import` "
        "run directory (any format it reads).",
    )
    cable_length: float | None = Field(
        None, gt=0, le=10, description="The real cable's length in metres."
    )
    cable_mass: float | None = Field(
        None, gt=0, le=100, description="The real cable's mass in kilograms."
    )
    rod_length: float | None = Field(
        None,
        gt=0,
        le=10,
        description="Length (m) of the simulated rod, the cable between its grip markers "
        "(see clamp_compliance); None = the markers' mean polyline length between them over "
        "the train recordings.",
    )
    rate_hz: float = Field(100.0, gt=0, le=10000, description="Frames per second recorded.")
    backend: CableBackendSpec = Field(
        default_factory=CableBackendSpec,
        description="Simulator and rod; the rod's length and density come from the cable, "
        "its material is the optimiser's start (the 'default material').",
    )
    parameters: list[str] = Field(
        ["young_bending", "bending_damping", "air_damping"],
        min_length=1,
        description="Rod fields the optimiser fits "
        "(see `dlocli.calibration.parameters.PARAMETERS`).",
    )
    train_trajectories: int = Field(
        8, ge=1, le=10000, description="Train recordings the optimiser replays (a seeded draw)."
    )
    generations: int = Field(8, ge=1, le=1000, description="CMA-ES generations.")
    population: int = Field(8, ge=2, le=256, description="CMA-ES candidates per generation.")
    sigma0: float = Field(
        0.25, gt=0, le=1, description="CMA-ES initial step, in units of each parameter's range."
    )
    workers: int = Field(
        2, ge=1, le=MAX_CLUSTER_WORKERS,
        description="Processes replaying trajectories in parallel (at most one per CPU); with "
        "--executor ray and no --ray-address, the CPUs of the local Ray instance; with "
        "--ray-address, at most the cluster's CPUs.",
    )  # fmt: skip
    seed: int = Field(0, ge=0, le=MAX_SEED, description="Seed of the draw and of CMA-ES.")
    out: Path = Field(Path("runs/calibrate"), description="Run directory.")

    @field_validator("parameters")
    @classmethod
    def _known(cls, value: list[str]) -> list[str]:
        unknown = [p for p in value if p not in PARAMETERS]
        if unknown:
            raise ValueError(
                f"unknown parameter {unknown[0]!r}; choose from {', '.join(PARAMETERS)}"
            )
        if len(set(value)) != len(value):
            raise ValueError("a parameter is listed twice; list each once")
        return value


class FamilySpec(ReplaySpec):
    """`dlo family`: many simulated cables whose materials span and exceed calibrated rods',
    each driven by a recorded cable's held-marker motion, written as marker datasets."""

    cli_flags: ClassVar[tuple[str, ...]] = (
        "calibrated", "source", "cables", "widen", "length_scale", "train", "eval",
        "rod_length", "rate_hz", "roll", "seed", "out",
    )  # fmt: skip
    cli_required: ClassVar[tuple[str, ...]] = ("calibrated", "source")

    calibrated: list[Path] = Field(
        [],
        description="A calibrated rod (a `dlo calibrate` run's calibrated.yaml, or the run "
        "directory); repeat the flag, one per rod. Their materials set the span drawn from; "
        "the first sets everything not drawn (backend, segments, radius, clamps).",
    )
    source: Annotated[list[Path], BeforeValidator(_as_list)] = Field(
        [],
        description="A recorded cable whose recordings drive simulated ones: a folder in the "
        "DEFORM layout (train/ and eval/) or a `dlo import` run directory; repeat the flag, "
        "one per cable: cable k is driven by source k mod the sources' count. A source's held "
        "markers' motion, marker layout and frame rate are its simulated cables'.",
    )
    cables: int = Field(8, ge=1, le=10_000, description="Simulated cables to draw.")
    widen: float = Field(
        2.0,
        ge=1.0,
        le=1000.0,
        description="How far the draw reaches past the calibrated rods: each material field "
        "(young_bending, density, bending_damping, air_damping) is drawn log-uniformly between "
        "the smallest calibrated value / widen and the largest * widen (within the range the "
        "simulator takes; 1: between the calibrated values).",
    )
    length_scale: tuple[float, float] = Field(
        (0.8, 1.2),
        description="Range of the factor (drawn uniformly) on the source cable's rod length; "
        "the recorded motion is scaled about its centre by the same factor.",
    )
    train: int = Field(
        16, ge=1, le=MAX_COUNT, description="Simulated train trajectories per cable."
    )  # fmt: skip
    eval: int = Field(
        4, ge=0, le=MAX_COUNT, description="Simulated eval trajectories per cable (driven by "
        "the source's eval recordings)."
    )  # fmt: skip
    rod_length: Annotated[list[float], BeforeValidator(_as_list)] = Field(
        [],
        description="Length (m) of each source cable's rod, the cable between its grip "
        f"markers (at most {MAX_SOURCE_ROD:g}), one per --source in their order; unset = each "
        "source's markers' mean polyline length between them over its train recordings.",
    )
    rate_hz: float | None = Field(
        None, ge=1.0, le=1000.0,
        description="Frames per second of the sources' recordings; unless given, a `dlo "
        "import` run's own rate, else 100 (DEFORM's).",
    )  # fmt: skip
    seed: int = Field(0, ge=0, le=MAX_SEED, description="Seed of the materials and motions.")
    out: Path = Field(Path("runs/family"), description="Run directory.")

    @model_validator(mode="after")
    def _a_length_per_source(self) -> FamilySpec:
        if not all(0 < length <= MAX_SOURCE_ROD for length in self.rod_length):
            raise ValueError(
                f"--rod-length {','.join(f'{v:g}' for v in self.rod_length)}: each length "
                f"must be above 0 and at most {MAX_SOURCE_ROD:g} m"
            )
        if self.rod_length and len(self.rod_length) != len(self.source):
            raise ValueError(
                f"{len(self.rod_length)} rod lengths for {len(self.source)} sources; give "
                "--rod-length one length per --source, in their order, or none"
            )
        return self

    @field_validator("length_scale")
    @classmethod
    def _ordered(cls, value: tuple[float, float]) -> tuple[float, float]:
        low, high = value
        if not 0.25 <= low <= high <= 4.0:
            raise ValueError("give two factors LOW,HIGH with 0.25 <= LOW <= HIGH <= 4")
        return value
