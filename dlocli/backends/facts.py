"""What a backend tells before its simulator is imported: class attributes of a light base
class that the backend's class inherits, read through ``dlocli.registry.backends.facts``
(spec validation and ``--help`` import no simulator).

A plugin backend sets these on its own :class:`~dlocli.backends.base.Backend` subclass."""

from __future__ import annotations

from collections.abc import Mapping
from typing import TYPE_CHECKING, ClassVar

if TYPE_CHECKING:
    from dlocli.backend_spec import RodSpec


#: the ``json_schema_extra`` of a planner option a backend's ``planner_defaults`` may set
#: (--help says so beside its default)
BACKEND_DEFAULT = {"backend_default": True}


class BackendFacts:
    """The facts every backend has; the defaults suit a backend without limits."""

    #: the most rod segments it can simulate (None: the rod spec's own bound)
    max_segments: ClassVar[int | None] = None
    #: the value a rod field left at None stands for in this backend (its own constant)
    unset_rod_values: ClassVar[Mapping[str, float]] = {}
    #: per planner name, options (fields of its spec) that a run on this backend plans with
    #: unless it sets them: what its rod's motion asks of the planner (none: the paper's)
    planner_defaults: ClassVar[Mapping[str, Mapping[str, float | bool]]] = {}

    @classmethod
    def effective_rod(cls, rod: RodSpec) -> RodSpec:
        """The rod with each field as this backend simulates it, where it cannot have the
        value asked for (the same physics, said truly)."""
        return rod


#: the pull of every planned action towards the held-end servo's, on the rods where it was
#: measured (docs/benchmarks.md, the held ends decide the shape)
SERVO_COST = 1e-3


class MujocoFacts(BackendFacts):
    """MuJoCo's composite cable."""

    planner_defaults: ClassVar[Mapping[str, Mapping[str, float | bool]]] = {
        "mpc": {"servo_cost": SERVO_COST}
    }

    # the cable's own damping: stiffness-proportional joint damping of time 0.05 s (twist
    # (1 + poisson) times that) and no air damping
    unset_rod_values: ClassVar[Mapping[str, float]] = {
        "bending_damping": 0.05,
        "twist_damping": 0.066,
        "air_damping": 0.0,
    }


class PybulletFacts(BackendFacts):
    """PyBullet's chain of capsules."""

    # PyBullet reports at most 128 joint coordinates, 7 for the floating base and 4 per
    # spherical joint, so a chain of 32 segments would have its last joint locked
    max_segments: ClassVar[int | None] = 31
    # two physics steps of joint damping at the default 2 ms step, PyBullet's own velocity
    # damping in the air
    unset_rod_values: ClassVar[Mapping[str, float]] = {
        "bending_damping": 0.004,
        "twist_damping": 0.004,
        "air_damping": 5.0,
    }


class FlexFacts(BackendFacts):
    """MuJoCo 4's flex rod."""

    # its sideways swing decays 4x slower than the cable's: the plan pays for the motion it
    # leaves (it damps the swing instead of chasing it), and Gauss-Newton steps are damped as
    # much as the curvature they scale (docs/benchmarks.md, a planner that damps the swing);
    # the servo's roll is read from the rod's earlier rest states (docs/benchmarks.md, the roll
    # the rod rests best at). Measured for the gradient MPC only.
    planner_defaults: ClassVar[Mapping[str, Mapping[str, float | bool]]] = {
        "mpc": {"motion_cost": 32.0, "damping": 1.0, "servo_cost": SERVO_COST, "rest_roll": True}
    }

    # MuJoCo's flex damping time for bending and twist
    unset_rod_values: ClassVar[Mapping[str, float]] = {
        "bending_damping": 0.05,
        "twist_damping": 0.05,
        "air_damping": 0.0,
    }

    @classmethod
    def effective_rod(cls, rod: RodSpec) -> RodSpec:
        """MuJoCo's flex damping damps twist with the bending time: a shorter twist time is
        the bending time (a calibration that fits only the bending time writes what the rod
        does, and its twin does not warn on every use)."""
        bending = cls.unset_rod_values["bending_damping"]
        if rod.bending_damping is not None:
            bending = rod.bending_damping
        if rod.twist_damping is None or rod.twist_damping >= bending:
            return rod
        return rod.model_copy(update={"twist_damping": bending})
