"""What every planner through a learned dynamics model shares (gradient MPC, MPPI).

A :class:`ModelPlanner` keeps a plan of H actions (H, A) in task space, optimises it through
the model's predictions at every re-plan (through a view of the model's form,
:mod:`dlocli.controllers.views`: the rod's segments or tracked markers), executes its first
action, and warm-starts the next re-plan from the remaining actions shifted forward (the
tail repeats the last action). Subclasses implement :meth:`ModelPlanner._optimise` only.

Shapes: B candidate plans, H horizon steps, A = task action size (6 or 12), N segments (or
M markers).
Plans live on the model's device; nothing here assumes a CPU.
"""

from __future__ import annotations

import time
from abc import abstractmethod
from types import EllipsisType
from typing import Any, ClassVar

import numpy as np
import torch

from dlocli.controllers.base import Planner
from dlocli.controllers.held_end import servo_pull, without
from dlocli.controllers.rest_roll import RestMap
from dlocli.controllers.specs import PlannerSpec
from dlocli.controllers.views import RodView, make_view

#: the roll rates (of the largest) a roll search tries per moving gripper
ROLL_RATES = (-1.0, 0.0, 1.0)


def shift_plan(plan: torch.Tensor, steps: int) -> torch.Tensor:
    """Drop the first ``steps`` actions of (..., H, A) and repeat the last one to refill H."""
    horizon = plan.shape[-2]
    steps = min(steps, horizon - 1)
    tail = plan[..., -1:, :].expand(*plan.shape[:-2], steps, plan.shape[-1])
    return torch.cat([plan[..., steps:, :], tail], dim=-2)


def model_device(model: torch.nn.Module) -> torch.device:
    """The device of the model's parameters (CPU for a parameter-free model)."""
    param = next(iter(model.parameters()), None)
    return param.device if param is not None else torch.device("cpu")


class ModelPlanner(Planner):
    """Receding-horizon planning through ``model.rollout``; subclasses optimise the plan."""

    spec_cls: ClassVar[type[PlannerSpec]] = PlannerSpec

    def __init__(
        self, env: Any, model: torch.nn.Module, spec: PlannerSpec | None = None, seed: int = 0
    ) -> None:
        super().__init__(env)
        self.spec = spec if spec is not None else self.spec_cls()
        self.model = model.eval()
        self.device = model_device(model)
        self.generator = torch.Generator(device="cpu").manual_seed(seed)
        self.view = make_view(env, self.model, self.device, self.spec.tracking == "raw")
        self._goal: torch.Tensor | None = None
        self._plan: torch.Tensor | None = None  # (H, A), the latest optimised plan
        self._cursor = 0  # actions of self._plan already executed
        self._observed: torch.Tensor | None = None  # (1, N, 7), the state at the latest act
        self._previous: torch.Tensor | None = None  # (1, N, 7), the state one step before it
        self._goal_pending = False  # the goal is read from the episode's first observation
        self._evaluated: torch.Tensor | None = None  # (B, H, N, 3) the latest predictions
        # the latest re-plan's state and the one before it
        self._replanned_from: tuple[torch.Tensor, torch.Tensor | None] | None = None
        self._expected: torch.Tensor | None = None  # (N, 3) positions predicted for this step
        self._disturbance: torch.Tensor | None = None  # (N, 3) averaged one-step error
        self._miss: float | None = None  # m, the averaged one-step error's mean distance
        self._servo: torch.Tensor | None = None  # (A,) the held-end servo's latest action
        self._servo_read: torch.Tensor | None = None  # (A, A) what of it the goal shows
        # the roll the rod's earlier rest states say it rests best at (rest_roll)
        self.rest = RestMap.of_model(model, self.task.moving) if self.spec.rest_roll else None

    def reset(self, goal: np.ndarray) -> None:
        """New episode towards ``goal`` (N, 3) metres: forget the plan."""
        super().reset(goal)
        self._goal = torch.as_tensor(self.goal, dtype=torch.float32, device=self.device)
        self._goal_pending = True
        self._plan = None
        self._cursor = 0
        self._observed = self._previous = self._evaluated = self._replanned_from = None
        self._expected = self._disturbance = self._servo = self._servo_read = None
        self._miss = None
        self.view.reset()

    @property
    def plan(self) -> torch.Tensor | None:
        """The latest optimised plan (H, A) on the model's device, None before the first act."""
        return self._plan

    def planned_path(self) -> tuple[np.ndarray | None, np.ndarray | None]:
        """For a run's recording, at no cost: the latest plan as gripper commands (H, 2, 6)
        in [-1, 1], and the model's predicted positions (H, N, 3) along the plan as the
        planner last evaluated it (one update before the plan it executes; None when it
        evaluated several candidates); (None, None) before the first act."""
        if self._plan is None:
            return None, None
        commands = self.task.to_grippers(self._plan).cpu().numpy()
        evaluated = self._evaluated
        if evaluated is None or evaluated.shape[0] != 1:
            return commands, None
        return commands, evaluated[0].detach().cpu().numpy()

    # ------------------------------------------------------------------ control loop
    def _act(self, obs: np.ndarray) -> np.ndarray:
        if self._goal is None:
            raise RuntimeError("call reset(goal) before act()")
        if self._goal_pending:
            self._goal, self._goal_pending = self.view.goal(obs, self.goal), False
        state, before = self.view.observe(obs)
        # act() is called once per control step, so the last state is s_{t-1} unless the
        # view estimates it itself
        self._previous = self._observed if before is None else before
        self._observed = state
        self._update_servo(obs)
        self._update_disturbance(state)
        if self._plan is not None and self._cursor < min(self.spec.replan_every, self.spec.horizon):
            action = self._plan[self._cursor]
            self._cursor += 1
            self.last_stats = {"replanned": 0.0}
        else:
            init = self._initial_plan()
            start = time.perf_counter()
            plan, stats = self._optimise(state, init)
            stats["plan_ms"] = 1000.0 * (time.perf_counter() - start)
            stats["replanned"] = 1.0
            self._plan, self._cursor = plan.detach(), 1
            self._replanned_from = (state, self._previous)
            self.last_stats = stats
            action = self._plan[0]
        if self._serving():
            assert self._servo is not None
            action = self._servo
            self.last_stats = {**self.last_stats, "served": 1.0}
        self._expect(state, action)
        return action.cpu().numpy()

    def _serving(self) -> bool:
        """With ``servo_above_mm``: whether the model's recent one-step error is above it, so
        the servo's action goes out instead of the plan's."""
        threshold = self.spec.servo_above_mm / 1000.0
        return bool(threshold) and self._servo is not None and (self._miss or 0.0) > threshold

    # ------------------------------------------------------------------ held-end servo
    def _update_servo(self, obs: np.ndarray) -> None:
        """With ``servo_cost`` (or ``servo_above_mm``): the held-end servo's action for this
        observation, the point every planned action is pulled towards in all but the
        grippers' roll (kept from the last step where the held ends cannot be read); with
        ``roll_search``, in everything, the roll the model predicts best; with ``rest_roll``,
        in everything where the rest states say which roll rests best."""
        if self.spec.servo_cost == 0.0 and not self.spec.servo_above_mm:
            return
        pull = servo_pull(self.env, self.task, obs)
        if pull is None:
            return
        action, rolls = pull
        tensor = lambda a: torch.as_tensor(a, dtype=torch.float32, device=self.device)  # noqa: E731
        rested = self._rested(obs, action, rolls)
        self._servo = tensor(action if rested is None else rested)
        if self.spec.roll_search > 0 and len(rolls):
            self._servo, self._servo_read = self._search_roll(self._servo, tensor(rolls)), None
        else:
            self._servo_read = None if rested is not None else tensor(without(rolls))

    def _rested(self, obs: np.ndarray, action: np.ndarray, rolls: np.ndarray) -> np.ndarray | None:
        """The servo's ``action`` (A,) with each moving gripper's roll (``rolls`` (K, A)) turned
        towards the roll the rest states say the rod rests nearest the goal at, at most at the
        largest rate; None without rest states near the grippers' poses."""
        if self.rest is None or not len(rolls):
            return None
        grippers = self.env.split_observation(obs)["grippers"]
        offsets = self.rest.roll_offsets(grippers, np.asarray(self.goal, dtype=np.float64))
        if offsets is None:
            return None
        spec = self.env.task_spec
        rates = np.clip(offsets / (spec.max_angular_velocity * spec.control_dt), -1.0, 1.0)
        return action @ without(rolls) + rates @ rolls

    def _search_roll(self, servo: torch.Tensor, rolls: torch.Tensor) -> torch.Tensor:
        """The servo's action (A,) with each moving gripper's roll (rolls (K, A)) turned at
        one of ROLL_RATES, the candidate whose positions the model predicts nearest the goal
        after the horizon and ``roll_search`` steps standing still."""
        assert self._observed is not None and self._goal is not None
        rates = torch.tensor(ROLL_RATES, device=self.device)
        grid = torch.cartesian_prod(*[rates] * len(rolls)).reshape(-1, len(rolls))  # (C, K)
        actions = (servo + grid @ rolls).clamp(-1.0, 1.0)  # (C, A)
        moving = actions[:, None].expand(-1, self.spec.horizon, -1)
        still = actions.new_zeros(len(actions), self.spec.roll_search, actions.shape[1])
        commands = self.task.to_grippers(torch.cat([moving, still], dim=1))
        with torch.no_grad():
            predicted = self.view.predict(self._observed, commands, self._previous)
        miss = (predicted[:, -1] - self._goal).square().sum(dim=(1, 2))
        return actions[int(torch.argmin(miss))]

    # ------------------------------------------------------------------ disturbance
    def _expect(self, state: torch.Tensor, action: torch.Tensor) -> None:
        """With the disturbance or servo_above_mm option: the positions (N, 3) the model
        predicts for the next observation under ``action`` (A,), one step of its rollout."""
        if self.spec.disturbance == "none" and not self.spec.servo_above_mm:
            return
        commands = self.task.to_grippers(action.clamp(-1.0, 1.0)[None, None])
        with torch.no_grad():
            self._expected = self.view.predict(state, commands, self._previous)[0, 0]

    def _update_disturbance(self, state: torch.Tensor) -> None:
        """Average the one-step prediction error of the positions into the disturbance (and
        its mean distance into the miss the servo_above_mm option reads)."""
        if self._expected is None:
            return
        error = state[0, :, :3] - self._expected
        gain = self.spec.disturbance_gain
        if self.spec.servo_above_mm:
            miss = float(error.norm(dim=-1).mean())  # a host sync, with the option only
            self._miss = miss if self._miss is None else self._miss + gain * (miss - self._miss)
        if self.spec.disturbance == "none":
            return
        old = self._disturbance
        self._disturbance = error * gain if old is None else old + gain * (error - old)

    def _corrected(self, state: torch.Tensor, predicted: torch.Tensor) -> torch.Tensor:
        """Predictions (B, K, N, 3) from the latest observation plus the disturbance."""
        if self._disturbance is None or state is not self._observed:
            return predicted
        if self.spec.disturbance == "offset":
            return predicted + self._disturbance
        steps = torch.arange(1, predicted.shape[1] + 1, device=predicted.device)
        return predicted + steps[:, None, None] * self._disturbance

    def returned_cost(self) -> float | None:
        """The model-predicted cost of the plan the latest re-plan returned, from that
        re-plan's state (None before one): what the optimisation reached. One forward
        rollout, outside :meth:`act` (a run that records it pays for it, the planner not)."""
        if self._plan is None or self._replanned_from is None:
            return None
        state, previous = self._replanned_from
        with torch.no_grad():
            return float(self.residuals(state, self._plan[None], previous).square().sum())

    def state_tensor(self, obs: np.ndarray) -> torch.Tensor:
        """The model's state (1, N, 7) = concat(positions, quaternions) of a full observation
        (a marker view's state needs the episode so far: :meth:`act` keeps it)."""
        return RodView.observe(self.view, obs)[0]

    def _initial_plan(self) -> torch.Tensor:
        """(H, A) start of the optimisation: the shifted previous plan, or zeros."""
        if self._plan is None or not self.spec.warm_start:
            return torch.zeros(self.spec.horizon, self.action_dim, device=self.device)
        return shift_plan(self._plan, self._cursor)

    def random_plans(self, count: int) -> torch.Tensor:
        """(count, H, A) plans uniform in [-1, 1] from the controller's seeded generator."""
        plans = torch.rand(count, self.spec.horizon, self.action_dim, generator=self.generator)
        return (2.0 * plans - 1.0).to(self.device)

    def predict_cost(self, state: torch.Tensor, plans: torch.Tensor) -> torch.Tensor:
        """Cost (B,) of plans (B, H, A) from state (1, N, 7): the model-predicted shape cost
        plus ``action_cost * sum ||a||^2`` and the optional terms (see
        :mod:`dlocli.controllers.mpc`)."""
        return self.residuals(state, plans).square().sum(dim=1)

    def residuals(
        self,
        state: torch.Tensor,
        plans: torch.Tensor,
        previous: torch.Tensor | None | EllipsisType = ...,
    ) -> torch.Tensor:
        """(B, (H+S)*N*3 + H*A + ...): the terms whose squares sum to :meth:`predict_cost`,
        the predicted position errors (m) over the horizon and the S settle steps, then
        sqrt(action_cost) x the actions, and where asked the motion and the servo terms
        (:meth:`residuals_of`). ``previous`` is the state one
        step before ``state`` (None: at rest); by default :meth:`previous_of` finds it."""
        return self.residuals_of(state, plans, self.predicted(state, plans, previous))

    def predicted(
        self,
        state: torch.Tensor,
        plans: torch.Tensor,
        previous: torch.Tensor | None | EllipsisType = ...,
    ) -> torch.Tensor:
        """(B, H+S, N, 3) the positions the model predicts along plans (B, H, A) and the S
        settle steps (``previous`` as in :meth:`residuals`)."""
        commands = self.task.to_grippers(self._with_settling(plans))  # (B, H+S, 2, 6)
        planning = previous is ...  # not a Jacobian's nudged plans (maybe on another thread)
        if planning:
            previous = self.previous_of(state)
        predicted = self._corrected(state, self.view.predict(state, commands, previous))
        if planning:
            self._evaluated = predicted[:, : plans.shape[1]].detach()
        return predicted

    def evaluated(self, predicted: torch.Tensor) -> None:
        """Note predictions (1, H+S, N, 3) along the plan being optimised, computed elsewhere
        (a Jacobian's rollout), as the latest evaluation (:meth:`planned_path`)."""
        self._evaluated = predicted[:, : self.spec.horizon].detach()

    def residuals_of(
        self, state: torch.Tensor, plans: torch.Tensor, predicted: torch.Tensor
    ) -> torch.Tensor:
        """:meth:`residuals` given the predicted positions (B, H+S, N, 3): affine in both
        plans and predictions. With ``servo_cost``, sqrt(servo_cost) x each action's
        distance from the held-end servo's but for the grippers' roll
        (:mod:`dlocli.controllers.held_end`)."""
        assert self._goal is not None
        errors = (predicted - self._goal).flatten(1)
        effort = self.spec.action_cost**0.5 * plans.flatten(1)
        terms = [errors, effort]
        if self.spec.motion_cost > 0.0:
            terms.append(self._motion(state, predicted))
        if self._servo is not None and self.spec.servo_cost > 0.0:
            pulled = plans - self._servo
            if self._servo_read is not None:  # None: the roll too (a roll search chose it)
                pulled = pulled @ self._servo_read
            terms.append(self.spec.servo_cost**0.5 * pulled.flatten(1))
        return torch.cat(terms, dim=1)

    def _motion(self, state: torch.Tensor, predicted: torch.Tensor) -> torch.Tensor:
        """(B, K*N*3) sqrt(motion_cost) x the predicted change of every position per step."""
        start = state[..., :3].expand(predicted.shape[0], -1, -1)[:, None]
        path = torch.cat([start, predicted], dim=1)
        steps = path[:, 1:] - path[:, :-1]
        return self.spec.motion_cost**0.5 * steps.flatten(1)

    def _with_settling(self, plans: torch.Tensor) -> torch.Tensor:
        """(B, H+S, A): the plans then ``settle_steps`` standing still (zero actions), so the
        cost sees where the cable swings once the plan has run out."""
        settle = self.spec.settle_steps
        if settle == 0:
            return plans
        still = plans.new_zeros(plans.shape[0], settle, plans.shape[2])
        return torch.cat([plans, still], dim=1)

    def previous_of(self, state: torch.Tensor) -> torch.Tensor | None:
        """The observed state one step before ``state`` if ``state`` is the latest observation
        (the model's velocity input); None (at rest) at an episode's first step or for any
        other state. An identity test: no device sync in the planning loop."""
        if state is not self._observed:
            return None
        return self._previous

    @abstractmethod
    def _optimise(
        self, state: torch.Tensor, init: torch.Tensor
    ) -> tuple[torch.Tensor, dict[str, float]]:
        """Optimise the plan from ``init`` (H, A) for ``state`` (1, N, 7).

        Returns the plan (H, A) in [-1, 1] and statistics for ``last_stats`` (numbers only).
        """
