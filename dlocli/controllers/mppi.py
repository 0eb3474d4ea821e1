"""Sampling MPC (MPPI) through the learned dynamics model: the gradient-free alternative.

Model Predictive Path Integral control (Williams et al., "Information Theoretic MPC for
Model-Based Reinforcement Learning", ICRA 2017), with the same objective as the gradient MPC
(:mod:`dlocli.controllers.mpc`): J(a) = sum_{k=1..H} ||p_hat_{t+k} - p_goal||_2^2. Per iteration,
from the nominal plan U (H, A):

    a^(j) = clip(U + eps^(j), -1, 1),  eps^(j) ~ N(0, sigma^2 I),  j = 1..K  (a^(1) = U)
    w_j   = softmax_j( -(J(a^(j)) - min J) / (lambda (max J - min J)) )
    U    <- sum_j w_j a^(j)

so ``temperature`` lambda is relative to the spread of the sampled costs (scale-free: the
best sample weighs e^(1/lambda) times the worst). The K rollouts are one batch, without
gradients. Warm start and receding horizon as for every :class:`ModelPlanner`.
"""

from __future__ import annotations

from typing import ClassVar

import torch

from dlocli.controllers.planning import ModelPlanner
from dlocli.controllers.specs import MPPISpec


class MPPI(ModelPlanner):
    """Sampling MPC: cost-weighted average of perturbed plans rolled out by the model."""

    name = "mppi"
    spec_cls: ClassVar[type[MPPISpec]] = MPPISpec
    spec: MPPISpec

    def _optimise(
        self, state: torch.Tensor, init: torch.Tensor
    ) -> tuple[torch.Tensor, dict[str, float]]:
        plan = init
        first = cost = None
        with torch.inference_mode():
            for _ in range(self.spec.iterations):
                plans = self._perturb(plan)  # (K, H, A)
                cost = self.predict_cost(state, plans)  # (K,)
                first = cost[0] if first is None else first
                plan = (self._weights(cost)[:, None, None] * plans).sum(0)
        assert first is not None and cost is not None
        stats = {"iterations": float(self.spec.iterations), "cost_initial": float(first)}
        return plan.clone(), stats

    def _perturb(self, plan: torch.Tensor) -> torch.Tensor:
        """(K, H, A) samples around ``plan`` (H, A), clipped to [-1, 1]; sample 0 is the plan."""
        shape = (self.spec.samples - 1, *plan.shape)
        noise = torch.randn(shape, generator=self.generator).to(self.device)
        samples = (plan + self.spec.noise * noise).clamp_(-1.0, 1.0)
        return torch.cat([plan[None], samples])

    def _weights(self, cost: torch.Tensor) -> torch.Tensor:
        """(K,) softmax weights of the costs, temperature relative to their spread."""
        low = cost.min()
        spread = (cost.max() - low).clamp_min(torch.finfo(cost.dtype).tiny)
        return torch.softmax(-(cost - low) / (self.spec.temperature * spread), dim=0)
