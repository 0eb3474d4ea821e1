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

import numpy as np
import torch
from pydantic import Field

from dlocli.controllers.planning import ModelPlanner, PlannerSpec, shift_plan

ADAM_BETAS = (0.9, 0.999)


class MPCSpec(PlannerSpec):
    """Gradient MPC options (paper-like: iterations 50, warm_start false, restarts 1)."""

    iterations: int = Field(1, ge=1, le=1000, description="Gradient steps per re-plan.")
    step_size: float = Field(
        0.2,
        gt=0,
        description="Optimiser step size: Adam's learning rate in action units "
        "(SGD: per unit gradient).",
    )
    adam_eps: float = Field(
        1e-8,
        gt=0,
        description="Adam's epsilon, in gradient units (m^2 per unit action): gradients well "
        "below it get steps proportional to them instead of about step_size.",
    )
    rms_decay: float = Field(
        0.9, ge=0, lt=1, description="rmsprop: decay of the squared-gradient average per step."
    )
    optimizer: Literal["adam", "rmsprop", "normalized", "sgd"] = Field(
        "adam",
        description="Update rule on the actions: adam; normalized (gradient divided by its RMS "
        "over the plan: steps of RMS step_size along the steepest descent); sgd.",
    )
    restarts: int = Field(
        1,
        ge=1,
        le=256,
        description="Plans optimised together in one batch: the warm start plus restarts-1 "
        "uniform random ones; the one with the lowest predicted cost is executed.",
    )
    line_search: float = Field(
        0.0,
        ge=0,
        description="If > 0: scale each step by the minimiser of a parabola fitted to the cost "
        "along it (one extra forward rollout), at most this factor.",
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
        moments = (torch.zeros_like(plans), self._initial_square(plans))
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
                delta = self._update(grad, moments, step)
                if self.spec.line_search > 0:
                    delta = delta * self._step_scale(state, plans, cost, grad, delta)
                plans -= delta
                plans.clamp_(-1.0, 1.0)
            done = step
        assert first is not None and last is not None
        best = int(torch.argmin(last))  # by the latest evaluated cost (before its update)
        self._square = moments[1][best]
        stats = {
            "iterations": float(done),
            "cost_initial": float(first[0]),
            "cost_final": float(last[best]),
        }
        return plans.detach()[best], stats

    def _step_scale(
        self,
        state: torch.Tensor,
        plans: torch.Tensor,
        cost: torch.Tensor,
        grad: torch.Tensor,
        delta: torch.Tensor,
    ) -> torch.Tensor:
        """(R, 1, 1) multiple of the step ``-delta`` minimising the parabola through the cost
        and slope at the plans and the cost one full step away (one batched forward, no
        gradient); within [0, line_search], and line_search where the cost is not convex."""
        with torch.inference_mode():
            trial = self.predict_cost(state, (plans - delta).clamp(-1.0, 1.0))
        slope = -(grad * delta).sum(dim=(1, 2))  # d cost / d eta at eta = 0
        curvature = 2.0 * (trial - cost - slope)
        best = -slope / curvature.clamp_min(torch.finfo(cost.dtype).tiny)
        scale = torch.where(curvature > 0, best, torch.full_like(best, self.spec.line_search))
        return scale.clamp(0.0, self.spec.line_search).view(-1, 1, 1)

    def reset(self, goal: np.ndarray) -> None:
        super().reset(goal)
        self._square: torch.Tensor | None = None

    def _initial_square(self, plans: torch.Tensor) -> torch.Tensor:
        """rmsprop's squared-gradient average (R, H, A): the previous re-plan's, shifted like
        the plan, for the warm start; zeros (= not seen yet) elsewhere."""
        square = torch.zeros_like(plans)
        if self.spec.optimizer == "rmsprop" and self.spec.warm_start and self._square is not None:
            square[0] = shift_plan(self._square, self._cursor)  # the plan's shift (see _act)
        return square

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
        if self.spec.optimizer == "normalized":
            rms = grad.square().mean(dim=(1, 2), keepdim=True).sqrt()
            return self.spec.step_size * grad / rms.clamp_min(torch.finfo(grad.dtype).tiny)
        mean, square = moments
        if self.spec.optimizer == "rmsprop":
            decay = self.spec.rms_decay
            square.copy_(
                torch.where(square == 0, grad * grad, decay * square + (1 - decay) * grad * grad)
            )
            return self.spec.step_size * grad / square.sqrt().add_(self.spec.adam_eps)
        b1, b2 = ADAM_BETAS
        mean.mul_(b1).add_(grad, alpha=1 - b1)
        square.mul_(b2).addcmul_(grad, grad, value=1 - b2)
        denom = (square / (1 - b2**step)).sqrt_().add_(self.spec.adam_eps)
        return (self.spec.step_size / (1 - b1**step)) * mean / denom
