"""A planner through the learned model: random shooting, the best of sampled plans."""

from __future__ import annotations

from typing import ClassVar

import torch
from pydantic import Field

from dlocli.controllers.planning import ModelPlanner
from dlocli.controllers.specs import PlannerSpec


class ShootingSpec(PlannerSpec):
    samples: int = Field(8, ge=1, le=256, description="Random plans besides the warm start.")


class RandomShooting(ModelPlanner):
    """The plan of lowest predicted cost among the warm start and uniform random plans."""

    name = "shooting"
    spec_cls: ClassVar[type[ShootingSpec]] = ShootingSpec
    spec: ShootingSpec

    def _optimise(
        self, state: torch.Tensor, init: torch.Tensor
    ) -> tuple[torch.Tensor, dict[str, float]]:
        shape = (self.spec.samples, *init.shape)
        random = torch.rand(shape, generator=self.generator).to(self.device) * 2 - 1
        plans = torch.cat([init[None], random])
        with torch.inference_mode():
            cost = self.predict_cost(state, plans)
        best = int(cost.argmin())
        stats = {"cost_initial": float(cost[0]), "cost_final": float(cost[best])}
        return plans[best].clone(), stats
