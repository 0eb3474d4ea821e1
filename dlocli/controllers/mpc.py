"""Gradient-based shooting MPC through the learned dynamics model (the paper's controller).

Yang, Stork, Stoyanov, "Online Model Learning for Shape Control of Deformable Linear
Objects", Section IV-B, eqs. 8-10. At a re-plan from the observed state s_t the planner solves

    min_{a_t..a_{t+H-1} in [-1, 1]^A}  J(a) = sum_{k=1..H} || p_hat_{t+k} - p_goal ||_2^2
                                              + lambda sum_{k=0..H-1} || a_{t+k} ||_2^2
    with  s_hat_t = s_t,  s_hat_{t+k} = f_theta(s_hat_{t+k-1}, a_{t+k-1}),

where p_hat are the predicted segment positions (N, 3) and f_theta the learned model, by
iterating on the actions through the H-step rollout, projecting onto [-1, 1] after every
step, and executes a_t (receding horizon). The first term is the paper's objective; the
control-effort weight lambda (``action_cost``, default 1e-4 m^2) is ours and keeps
directions the model barely sees (e.g. the gripper's roll about the rod axis) near zero.
Two more terms are ours, each off in the paper's objective and on by a backend's planner
defaults where they pay: ``motion_cost`` x the predicted motion (a plan that leaves the rod
swinging pays for it) and ``servo_cost`` x each action's distance from the held-end servo's
(:mod:`dlocli.controllers.held_end`: the grippers pulled to where the goal holds the ends,
which decide the shape the rod rests in; the model refines the rest).

Update rules (``optimizer``):

- ``adam`` / ``sgd``: the paper's gradient descent, the gradient back-propagated through the
  rollout. Paper-like setting: ``optimizer=adam iterations=50 warm_start=false``.
- ``gauss-newton`` (default): J is a sum of squares, J = ||r(a)||^2 with r the predicted
  position errors and sqrt(lambda) a, so the step (J_r^T J_r + mu I)^-1 J_r^T r uses its
  curvature. The Jacobian J_r (H*A columns) is refreshed by forward differences (one
  batched forward rollout) every ``curvature_every`` re-plans and reused in between, where
  one forward rollout gives r and J_r^T r the (lagged) gradient: no back-propagation. Steps
  are clipped to ``max_step`` per action coordinate. ``refresh="background"`` computes the
  refresh in a second thread, off the control step. ``jacobian="shifted"`` nudges the first
  action alone (A+1 plans) and delays its effect for the later actions.

Why gauss-newton by default (measured by ``benchmarks/control_goals.py``): with one iteration
per control step, Adam's first step is a sign step of ``step_size`` in every coordinate, so
the warm-started plan's actions sit on a lattice of multiples of step_size and the executed
actions dither by at least that much (the rod never settles). The Gauss-Newton step vanishes
with the residual's gradient, and it needs forward rollouts only, which cost well under a
rollout + backward. The update rules are small classes (:data:`UPDATE_RULES`).

What else makes it fast (``benchmarks/mpc_latency.py``): the previous plan shifted by the
executed steps is the starting point, so each action is refined over H consecutive
re-plans (a real-time iteration scheme) and one iteration per control step suffices;
gradients are taken with respect to the actions only (never the weights); restarts are
one batch; no host-device syncs inside the loop unless early stopping is on.
"""

from __future__ import annotations

from concurrent.futures import Future, ThreadPoolExecutor
from typing import Any, ClassVar

import numpy as np
import torch

from dlocli.controllers.planning import ModelPlanner
from dlocli.controllers.specs import MPCSpec

ADAM_BETAS = (0.9, 0.999)
ADAM_EPS = 1e-8
FD_STEP = 0.05  # finite-difference step of the Gauss-Newton Jacobian, in action units


# ----------------------------------------------------------------------------- update rules
class UpdateRule:
    """How the plans move at each iteration: :meth:`start` at every re-plan, then per
    iteration :meth:`cost_and_gradient` and :meth:`step` (the change to subtract)."""

    #: whether the plans need autograd (the gradient is back-propagated through the rollout)
    backprop = True

    def __init__(self, spec: MPCSpec) -> None:
        self.spec = spec

    def reset(self) -> None:
        """A new episode."""

    def start(self, planner: ModelPlanner, state: torch.Tensor, plans: torch.Tensor) -> None:
        """A new re-plan from ``state`` with candidate ``plans`` (R, H, A)."""

    def cost_and_gradient(
        self, planner: ModelPlanner, state: torch.Tensor, plans: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Cost (R,) and its gradient (R, H, A) with respect to the actions only (never the
        weights), back-propagated through the rollout."""
        cost = planner.predict_cost(state, plans)
        (grad,) = torch.autograd.grad(cost.sum(), plans)
        return cost.detach(), grad

    def step(self, grad: torch.Tensor, iteration: int) -> torch.Tensor:
        raise NotImplementedError


class SGD(UpdateRule):
    """Plain gradient descent: ``step_size`` x gradient."""

    def step(self, grad: torch.Tensor, iteration: int) -> torch.Tensor:
        return self.spec.step_size * grad


class Adam(UpdateRule):
    """Adam on the actions (the paper's), bias-corrected, its moments fresh at each re-plan."""

    def start(self, planner: ModelPlanner, state: torch.Tensor, plans: torch.Tensor) -> None:
        self.mean, self.square = torch.zeros_like(plans), torch.zeros_like(plans)

    def step(self, grad: torch.Tensor, iteration: int) -> torch.Tensor:
        b1, b2 = ADAM_BETAS
        self.mean.mul_(b1).add_(grad, alpha=1 - b1)
        self.square.mul_(b2).addcmul_(grad, grad, value=1 - b2)
        denom = (self.square / (1 - b2**iteration)).sqrt_().add_(ADAM_EPS)
        return (self.spec.step_size / (1 - b1**iteration)) * self.mean / denom


class GaussNewton(UpdateRule):
    """Gauss-Newton steps on J = ||r||^2 with a lagged finite-difference Jacobian (see the
    module docstring): forward rollouts only, unless ``exact_gradient``."""

    def __init__(self, spec: MPCSpec) -> None:
        super().__init__(spec)
        self.backprop = spec.exact_gradient
        self._pool: ThreadPoolExecutor | None = None
        self.reset()

    def reset(self) -> None:
        self.curvature: torch.Tensor | None = None  # Cholesky factor of J^T J + damping
        self.jacobian_t: torch.Tensor | None = None  # J^T (H*A, residuals)
        self.replans = 0
        self._pending: Future | None = None  # a background refresh (its result is dropped)
        self._fresh: torch.Tensor | None = None  # the refreshed plan's residuals (1, R)
        self._install_at = 0

    def start(self, planner: ModelPlanner, state: torch.Tensor, plans: torch.Tensor) -> None:
        self.refresh(planner, state, plans[0])

    def refresh(self, planner: ModelPlanner, state: torch.Tensor, plan: torch.Tensor) -> None:
        """Every ``curvature_every`` re-plans: the Gauss-Newton matrix J^T J of the residuals
        (:meth:`ModelPlanner.residuals`) at ``plan`` (H, A), J by forward differences in one
        batched rollout (:meth:`jacobian`). Between refreshes the matrix is reused while the
        gradient is exact (a lagged-Hessian real-time scheme: the matrix changes slowly with
        the rod's state, the gradient does not). With ``refresh="background"`` the rollout
        runs in a second thread (see :class:`MPCSpec`); the first one is always inline."""
        self.replans += 1
        self._fresh = None
        due = (self.replans - 1) % self.spec.curvature_every == 0
        if self.curvature is None or (due and self.spec.refresh == "inline"):
            jacobian_t, predicted = self.jacobian(planner, state, plan, planner.previous_of(state))
            self._install(jacobian_t)
            if self.spec.jacobian == "shifted":
                # its rollout of the plan itself is the re-plan's first evaluation: not twice
                # (the full refresh's plans run as one batch on another path: its results
                # are kept as they were measured)
                planner.evaluated(predicted)
                self._fresh = planner.residuals_of(state, plan[None], predicted)
            return
        if self._pending is not None and self.replans == self._install_at:
            self._install(self._pending.result()[0])
            self._pending = None
        if due:  # background
            if self._pool is None:
                self._pool = ThreadPoolExecutor(1, thread_name_prefix="dlo-jacobian")
            previous = planner.previous_of(state)
            # plan is a view of the plans the optimiser updates in place: a copy
            self._pending = self._pool.submit(self.jacobian, planner, state, plan.clone(), previous)
            self._install_at = self.replans + max(self.spec.curvature_every - 1, 1)

    def jacobian(
        self,
        planner: ModelPlanner,
        state: torch.Tensor,
        plan: torch.Tensor,
        previous: torch.Tensor | None,
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """J^T (H*A, residuals) at ``plan`` (H, A), as ``spec.jacobian`` says, and the
        predicted positions (1, H+S, N, 3) along ``plan``."""
        if self.spec.jacobian == "shifted":
            return shifted_jacobian(planner, state, plan, previous)
        return full_jacobian(planner, state, plan, previous)

    def _install(self, jacobian_t: torch.Tensor) -> None:
        self.jacobian_t = jacobian_t
        gram = jacobian_t @ jacobian_t.T
        damping = self.spec.damping * gram.diagonal().mean().clamp_min(1e-12)
        gram.diagonal().add_(damping)
        self.curvature = torch.linalg.cholesky(gram)

    def cost_and_gradient(
        self, planner: ModelPlanner, state: torch.Tensor, plans: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """2 J^T r from a forward rollout, J from the latest refresh (or back-propagated)."""
        if self.spec.exact_gradient:
            return super().cost_and_gradient(planner, state, plans)
        assert self.jacobian_t is not None
        if self._fresh is not None and plans.shape[0] == 1:  # this re-plan's refreshed plan
            res, self._fresh = self._fresh, None
        else:
            with torch.no_grad():
                res = planner.residuals(state, plans)
        grad = 2.0 * (res @ self.jacobian_t.T).view_as(plans)
        return res.square().sum(dim=1), grad

    def step(self, grad: torch.Tensor, iteration: int) -> torch.Tensor:
        """(R, H, A) step from the cost's gradient (2 J^T r): (J^T J)^-1 J^T r, clipped to
        ``max_step`` per action so a stale matrix cannot throw the plan far; it vanishes
        with the gradient, unlike Adam's sign-like first step, so a converged plan stays."""
        assert self.curvature is not None
        flat = grad.flatten(1).T / 2  # (n, R)
        step = torch.cholesky_solve(flat, self.curvature).T.view_as(grad)
        return step.clamp(-self.spec.max_step, self.spec.max_step)


def _inward(actions: torch.Tensor) -> torch.Tensor:
    """Finite-difference steps towards the inside of [-1, 1], one per action coordinate."""
    return torch.where(actions > 0, -FD_STEP, FD_STEP)


def full_jacobian(
    planner: ModelPlanner, state: torch.Tensor, plan: torch.Tensor, previous: torch.Tensor | None
) -> tuple[torch.Tensor, torch.Tensor]:
    """J^T (H*A, residuals) at ``plan`` (H, A) by forward differences, each action nudged
    towards the inside of [-1, 1]; one batched rollout, no gradient. Also the predicted
    positions (1, H+S, N, 3) along ``plan``."""
    n = plan.numel()
    steps = _inward(plan.flatten())
    plans = torch.cat([plan[None], plan[None] + torch.diag(steps).view(n, *plan.shape)])
    with torch.no_grad():
        predicted = planner.predicted(state, plans, previous)
        res = planner.residuals_of(state, plans, predicted)
    return (res[1:] - res[:1]) / steps[:, None], predicted[:1]


def shifted_jacobian(
    planner: ModelPlanner, state: torch.Tensor, plan: torch.Tensor, previous: torch.Tensor | None
) -> tuple[torch.Tensor, torch.Tensor]:
    """J^T (H*A, residuals) at ``plan`` (H, A) from the first action's nudges alone (A+1
    rollouts): the predicted positions' change under action j's coordinate i is taken as
    under the first action's, delayed by j steps; the residuals are affine in the
    predictions and the actions, so their Jacobian follows exactly from that one. Also the
    predicted positions (1, H+S, N, 3) along ``plan``."""
    horizon, size = plan.shape
    steps = _inward(plan[0])
    nudges = plan.new_zeros(size, horizon, size)
    nudges[:, 0] = torch.diag(steps)
    with torch.no_grad():
        predicted = planner.predicted(state, torch.cat([plan[None], plan[None] + nudges]), previous)
        base, response = predicted[:1], (predicted[1:] - predicted[:1]) / steps[:, None, None, None]
        length = response.shape[1]
        delayed = [
            torch.nn.functional.pad(response[:, : length - j], (0, 0, 0, 0, j, 0))
            for j in range(horizon)
        ]  # each (A, K, N, 3): action j's coordinates
        change = torch.cat(delayed)  # (H*A, K, N, 3), in plan.flatten()'s order
        unit = torch.eye(horizon * size, device=plan.device).view(-1, horizon, size)
        before = planner.residuals_of(state, plan[None], base)
        after = planner.residuals_of(state, plan[None] + unit, base + change)
    return after - before, base


#: the update rules by ``MPCSpec.optimizer``
UPDATE_RULES: dict[str, type[UpdateRule]] = {"gauss-newton": GaussNewton, "adam": Adam, "sgd": SGD}


# ----------------------------------------------------------------------------- the planner
class GradientMPC(ModelPlanner):
    """Shooting MPC: iterations of an update rule on the action sequence through the model."""

    name = "mpc"
    spec_cls: ClassVar[type[MPCSpec]] = MPCSpec
    spec: MPCSpec

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.rule: UpdateRule = UPDATE_RULES[self.spec.optimizer](self.spec)

    def reset(self, goal: np.ndarray) -> None:
        super().reset(goal)
        self.rule.reset()

    def _optimise(
        self, state: torch.Tensor, init: torch.Tensor
    ) -> tuple[torch.Tensor, dict[str, float]]:
        plans = self._candidates(init)  # (R, H, A)
        self.rule.start(self, state, plans)
        plans.requires_grad_(self.rule.backprop)
        first = last = None
        done = 0
        for step in range(1, self.spec.iterations + 1):
            cost, grad = self.rule.cost_and_gradient(self, state, plans)
            first = cost if first is None else first
            converged, last = self._converged(last, cost), cost
            if converged:
                break
            with torch.no_grad():
                plans -= self.rule.step(grad, step)
                plans.clamp_(-1.0, 1.0)
            done = step
        assert first is not None and last is not None
        # by the latest evaluated cost, the one before its update: the plan returned is never
        # evaluated here (a run that reports it asks returned_cost())
        best = int(torch.argmin(last))
        return plans.detach()[best], {"iterations": float(done), "cost_initial": float(first[0])}

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
