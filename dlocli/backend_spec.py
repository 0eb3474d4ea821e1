"""The simulated rod and its simulator: :class:`RodSpec` (geometry and material, the paper's
by default) and :class:`BackendSpec` (which backend, its physics step, gravity, held ends).
Units: metres, seconds, Pa.
"""

from __future__ import annotations

from typing import Literal

from pydantic import Field, field_validator, model_validator

from dlocli.registry import backends
from dlocli.spec_base import Spec

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
        "20). 'rigid': the end segment is rigid in the gripper (a cantilever deflects about "
        "(1 - 1/N)^2 of the continuum's).",
    )
    bending_damping: float | None = Field(
        DEFAULT_DAMPING_TIME,
        ge=0,
        description="Bending damping time beta in seconds (Kelvin-Voigt: each joint's bending "
        "moment is (E I / l) (angle + beta * angular rate), a material of viscosity beta E). "
        "A bending mode of angular frequency w gets the damping ratio beta w / 2: the first "
        "mode of the 1 m paper rod (1.76 rad/s) 0.044 at the default 0.05. None = each "
        "backend's own constant (mujoco 0.05, pybullet two physics steps). MuJoCo's "
        "elasticity is explicit: with little damping it needs a smaller physics_dt; "
        "PyBullet's springs and damping are explicit: at its default step it adds rotary "
        "inertia to the segments (see docs/benchmarks.md, rod physics).",
    )
    twist_damping: float | None = Field(
        DEFAULT_DAMPING_TIME,
        ge=0,
        description="Twist damping time in seconds: each joint's twisting moment is (G J / l) "
        "(angle + time * angular rate); a twist mode of angular frequency w gets the damping "
        "ratio time * w / 2. None = each backend's own constant (mujoco the bending "
        "coefficient, a time of (1 + poisson) * 0.05; pybullet two physics steps).",
    )
    air_damping: float | None = Field(
        0.0,
        ge=0,
        description="Air damping d in 1/s: every segment's velocity v and angular velocity w "
        "decay at d (1 + |v|) v and d (1 + |w|) w (|v| in m/s, |w| in rad/s; PyBullet's "
        "velocity damping law); slow motions of every mode of angular frequency w get the "
        "damping ratio d / (2 w). None = each backend's own constant (mujoco 0, pybullet "
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
