"""Gradient-based shooting MPC through the learned dynamics model (the paper's controller).

Yang, Stork, Stoyanov, "Online Model Learning for Shape Control of Deformable Linear
Objects", Section IV-B, eqs. 8-10. At a re-plan from the observed state s_t the planner solves

    min_{a_t..a_{t+H-1} in [-1, 1]^A}  J(a) = sum_{k=1..H} || p_hat_{t+k} - p_goal ||_2^2
                                              + lambda sum_{k=0..H-1} || a_{t+k} ||_2^2
    with  s_hat_t = s_t,  s_hat_{t+k} = f_theta(s_hat_{t+k-1}, a_{t+k-1}),

where p_hat are the predicted segment positions (N, 3) and f_theta the learned model, by
gradient descent on the actions through the H-step rollout (back-propagation through time),
projecting onto [-1, 1] after every step, and executes a_t (receding horizon). The first
term is the paper's objective; the control-effort weight lambda (``action_cost``, default
1e-4 m^2) is ours: Adam moves every action coordinate by about ``step_size`` whatever the
size of its gradient, so with lambda = 0 tiny, model-error gradients (e.g. on the gripper's
roll about the rod axis) accumulate over the warm-started plans into sustained motions that
twist the rod away from the goal (measured: 3 of 10 goals ended farther than they started).
The effort term gives such directions an equilibrium near zero.

What makes it fast (``benchmarks/mpc_latency.py``): the previous plan shifted by the executed
steps is the starting point, so each action is refined over H consecutive re-plans (a
real-time iteration scheme) and one Adam step per control step suffices by default; the
gradient is taken with respect to the actions only (never the weights); restarts are one
batch; no host-device syncs inside the loop unless early stopping is on.
"""

from __future__ import annotations

from typing import ClassVar, Literal

import torch
from pydantic import Field

from dlocli.controllers.planning import ModelPlanner, PlannerSpec

ADAM_BETAS = (0.9, 0.999)
ADAM_EPS = 1e-8


class MPCSpec(PlannerSpec):
    """Gradient MPC options (paper-like: iterations 50, warm_start false, restarts 1)."""

    iterations: int = Field(1, ge=1, le=1000, description="Gradient steps per re-plan.")
    step_size: float = Field(
        0.2,
        gt=0,
        description="Optimiser step size: Adam's learning rate in action units "
        "(SGD: per unit gradient).",
    )
    optimizer: Literal["adam", "sgd"] = Field(
        "adam", description="Update rule on the actions: adam, or sgd (step_size x gradient)."
    )
    restarts: int = Field(
        1,
        ge=1,
        le=256,
        description="Plans optimised together in one batch: the warm start plus restarts-1 "
        "uniform random ones; the one with the lowest predicted cost is executed.",
    )
    tolerance: float = Field(
        0.0,
        ge=0,
        lt=1,
        description="Stop early once an iteration lowers the predicted cost by less than this "
        "fraction (0 = always run every iteration).",
    )


class GradientMPC(ModelPlanner):
    """Shooting MPC: Adam (or SGD) on the action sequence through ``model.rollout``."""

    name = "mpc"
    spec_cls: ClassVar[type[MPCSpec]] = MPCSpec
    spec: MPCSpec

    def _optimise(
        self, state: torch.Tensor, init: torch.Tensor
    ) -> tuple[torch.Tensor, dict[str, float]]:
        plans = self._candidates(init).requires_grad_(True)  # (R, H, A)
        moments = (torch.zeros_like(plans), torch.zeros_like(plans))  # Adam's
        first = last = None
        done = 0
        for step in range(1, self.spec.iterations + 1):
            cost = self.predict_cost(state, plans)  # (R,)
            (grad,) = torch.autograd.grad(cost.sum(), plans)  # actions only, never the weights
            cost = cost.detach()
            first = cost if first is None else first
            converged, last = self._converged(last, cost), cost
            if converged:
                break
            with torch.no_grad():
                plans -= self._update(grad, moments, step)
                plans.clamp_(-1.0, 1.0)
            done = step
        assert first is not None and last is not None
        best = int(torch.argmin(last))  # by the latest evaluated cost (before its update)
        stats = {
            "iterations": float(done),
            "cost_initial": float(first[0]),
            "cost_final": float(last[best]),
        }
        return plans.detach()[best], stats

    def _candidates(self, init: torch.Tensor) -> torch.Tensor:
        """(R, H, A): the warm start then R-1 uniform random plans."""
        if self.spec.restarts == 1:
            return init[None].clone()
        return torch.cat([init[None], self.random_plans(self.spec.restarts - 1)])

    def _converged(self, last: torch.Tensor | None, cost: torch.Tensor) -> bool:
        """True once the summed cost improved by less than ``tolerance`` (a host sync)."""
        if self.spec.tolerance == 0.0 or last is None:
            return False
        previous, now = float(last.sum()), float(cost.sum())
        return previous - now < self.spec.tolerance * previous

    def _update(
        self, grad: torch.Tensor, moments: tuple[torch.Tensor, torch.Tensor], step: int
    ) -> torch.Tensor:
        """The step to subtract from the plans: Adam (bias-corrected) or plain SGD."""
        if self.spec.optimizer == "sgd":
            return self.spec.step_size * grad
        mean, square = moments
        b1, b2 = ADAM_BETAS
        mean.mul_(b1).add_(grad, alpha=1 - b1)
        square.mul_(b2).addcmul_(grad, grad, value=1 - b2)
        denom = (square / (1 - b2**step)).sqrt_().add_(ADAM_EPS)
        return (self.spec.step_size / (1 - b1**step)) * mean / denom
