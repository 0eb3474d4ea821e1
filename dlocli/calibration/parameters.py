"""The rod fields a calibration may fit, and the optimiser's view of them: each maps to
[0, 1] over its range (logarithmically for the scale-like ones), so one CMA-ES step size
fits all."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from dlocli.errors import BadInput
from dlocli.registry import backends
from dlocli.specs import RodSpec


@dataclass(frozen=True)
class Parameter:
    """One fitted rod field: its range."""

    low: float
    high: float
    log: bool

    def to_unit(self, value: float) -> float:
        value = min(max(value, self.low), self.high)
        if self.log:
            return (math.log(value) - math.log(self.low)) / (math.log(self.high / self.low))
        return (value - self.low) / (self.high - self.low)

    def from_unit(self, u: float) -> float:
        u = min(max(float(u), 0.0), 1.0)
        if self.log:
            return float(math.exp(math.log(self.low) + u * math.log(self.high / self.low)))
        return float(self.low + u * (self.high - self.low))


PARAMETERS: dict[str, Parameter] = {
    "young_bending": Parameter(1e4, 1e10, log=True),
    "poisson": Parameter(0.0, 0.49, log=False),
    # below ~1.5 physics steps MuJoCo's explicit elasticity is unstable at its default step
    "bending_damping": Parameter(0.005, 1.0, log=True),
    "twist_damping": Parameter(0.005, 1.0, log=True),
    "air_damping": Parameter(0.01, 20.0, log=True),
}


def start_value(name: str, rod: RodSpec, backend: str) -> float:
    """The rod's value of ``name`` (a None field: the value the backend says it stands for;
    BadInput if the backend does not say)."""
    value = getattr(rod, name)
    if value is None:
        value = backends.facts(backend).unset_rod_values.get(name)
    if value is None:
        raise BadInput(
            f"the {backend} backend does not say what rod.{name} None stands for; give "
            f"rod.{name} a value to start the calibration from"
        )
    return float(value)


def encode(names: list[str], rod: RodSpec, backend: str) -> np.ndarray:
    """The rod's fitted fields as a point in [0, 1]^n."""
    return np.array([PARAMETERS[n].to_unit(start_value(n, rod, backend)) for n in names])


def decode(names: list[str], unit: np.ndarray, rod: RodSpec) -> RodSpec:
    """The rod with the fitted fields set from a point in [0, 1]^n."""
    values = {n: PARAMETERS[n].from_unit(u) for n, u in zip(names, unit, strict=True)}
    return rod.model_copy(update=values)
