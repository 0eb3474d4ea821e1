"""What a planner's model sees of the rod, per model form: the state it plans from, the goal
it plans to, and the positions it predicts for candidate plans.

- ``rod`` models (the full observation): the state is every segment's position and
  orientation (1, N, 7), read from the observation as it is.
- ``markers`` models (the markers observation, :mod:`dlocli.env.observation`): the state is
  M marker positions (1, M, 3). The tracker's report is noisy, late and gappy, so the view
  keeps an estimate: each report is blended with the model's one-step prediction (the
  steady-state Kalman gain of a marker whose prediction errs by ``MODEL_ERROR_MM`` per step,
  measured by ``noise_mm``; gain 1 without noise), missing markers take the prediction, and
  a latency of k steps is bridged by rolling the model k steps forward through the gripper
  poses the robot has taken since (it knows them). A plan's held markers follow the
  grippers' commanded motion: the robot's own kinematics, not the model's guess.
"""

from __future__ import annotations

import math
from collections import deque
from typing import Any

import numpy as np
import torch

from dlocli.env.observation import axis_x
from dlocli.env.shapes import max_twist
from dlocli.errors import BadInput
from dlocli.models.base import check_control_rate

#: what the marker model's one-step prediction is taken to err by, per coordinate (mm)
MODEL_ERROR_MM = 1.0


class RodView:
    """The full observation: segment positions and orientations, as observed."""

    def __init__(
        self, env: Any, model: torch.nn.Module, device: torch.device, raw: bool = False
    ) -> None:
        if getattr(env, "tracker", None) is not None:
            raise BadInput(
                "this model predicts the rod's segments, but the task observes markers: plan "
                "with a marker model (`dlo online --observation markers` learns one)"
            )
        self.env, self.model, self.device = env, model, device

    def reset(self) -> None:
        """A new episode."""

    def observe(self, obs: np.ndarray) -> tuple[torch.Tensor, torch.Tensor | None]:
        """The state (1, N, 7) to plan from, and None: the planner's own last state is the
        one before it."""
        parts = self.env.split_observation(obs)
        state = np.concatenate([parts["positions"], parts["quaternions"]], axis=-1)
        return torch.as_tensor(state[None], dtype=torch.float32, device=self.device), None

    def goal(self, obs: np.ndarray, goal: np.ndarray) -> torch.Tensor:
        """The goal positions (N, 3) the predicted positions are compared with."""
        return torch.as_tensor(goal, dtype=torch.float32, device=self.device)

    def predict(
        self, state: torch.Tensor, commands: torch.Tensor, previous: torch.Tensor | None
    ) -> torch.Tensor:
        """Predicted positions (B, H, N, 3) under gripper commands (B, H, 2, 6) in [-1, 1]."""
        batch = commands.shape[0]
        if previous is not None:
            previous = previous.expand(batch, -1, -1)
        return self.model.rollout(state.expand(batch, -1, -1), commands, previous)[..., :3]


class MarkerView:
    """The markers observation, through a marker-form model (see the module docstring)."""

    def __init__(
        self, env: Any, model: torch.nn.Module, device: torch.device, raw: bool = False
    ) -> None:
        layout = getattr(env, "marker_layout", None)
        if layout is None:
            raise BadInput(
                "this is a marker model, but the task observes the full state: add "
                "--observation markers (with the markers it was trained on)"
            )
        held = model.held.cpu().numpy()
        if len(held) != len(layout) or not np.array_equal(held, layout.held):
            raise BadInput(
                f"the marker model was trained on {len(held)} markers ({int(held.sum())} held) "
                f"but the task observes {len(layout)} ({int(layout.held.sum())} held); "
                "observe the markers it was trained on"
            )
        self.env, self.model, self.device = env, model, device
        spec = env.task_spec
        #: ``raw``: plan from the report as it is (no blending, gaps or latency bridged)
        self.raw = raw
        self.latency = 0 if raw else spec.observation.latency_steps
        self.gain = 1.0 if raw else kalman_gain(spec.observation.noise_mm, MODEL_ERROR_MM)
        self.dt = spec.control_dt
        twist = np.array(np.broadcast_to(max_twist(spec), (2, 6)))
        self.scale = torch.as_tensor(twist, dtype=torch.float32, device=device)
        self.held = torch.as_tensor(layout.held, device=device)
        self.holder = torch.as_tensor(np.maximum(layout.holder, 0), device=device)
        self.lever = torch.as_tensor(layout.lever, dtype=torch.float32, device=device)
        self.reset()

    def reset(self) -> None:
        self._poses: deque[torch.Tensor] = deque(maxlen=self.latency + 1)
        self._frame: torch.Tensor | None = None  # (1, M, 3) estimate of the reported frame
        self._frame_before: torch.Tensor | None = None  # the one a step before it
        self._goal: torch.Tensor | None = None
        self.grippers: torch.Tensor | None = None  # (2, 7) poses now

    def goal(self, obs: np.ndarray, goal: np.ndarray) -> torch.Tensor:
        """The goal's markers (M, 3), as the observation states them."""
        if self._goal is None:
            markers = self.env.split_observation(obs)["goal"]
            self._goal = torch.as_tensor(markers, dtype=torch.float32, device=self.device)
        return self._goal

    # ------------------------------------------------------------------ estimation
    def observe(self, obs: np.ndarray) -> tuple[torch.Tensor, torch.Tensor | None]:
        """The estimate of the markers now (1, M, 3) and one step before (None: at rest)."""
        parts = self.env.split_observation(obs)
        tensor = lambda a: torch.as_tensor(a, dtype=torch.float32, device=self.device)  # noqa: E731
        self.grippers = tensor(parts["grippers"])
        if not self._poses:  # at rest since before the reported frame
            self._poses.extend([self.grippers] * self._poses.maxlen)
        else:
            self._poses.append(self.grippers)
        seen, visible = tensor(parts["markers"])[None], tensor(parts["visible"])[None] > 0.5
        with torch.no_grad():
            self._update_frame(seen, visible)
            return self._bridge_latency()

    def _update_frame(self, seen: torch.Tensor, visible: torch.Tensor) -> None:
        """Blend the report of the delayed frame with the model's prediction of it."""
        held_now = self._held_at(self._poses[0])
        if self._frame is None or self.raw or (self.gain == 1.0 and bool(visible.all())):
            frame = seen  # the first report, or a clean and whole one: nothing to blend
        else:
            before = self._frame if self._frame_before is None else self._frame_before
            predicted = self.model(self._frame, before, held_now)
            blended = predicted + self.gain * (seen - predicted)
            frame = torch.where(visible, seen if self.gain == 1.0 else blended,
                                predicted)  # fmt: skip
        frame = torch.where(self.held[:, None], held_now, frame)
        self._frame_before, self._frame = self._frame, frame

    def _bridge_latency(self) -> tuple[torch.Tensor, torch.Tensor | None]:
        """Roll the estimate of the delayed frame forward to now through the poses since."""
        if self.latency == 0:
            return self._frame, self._frame_before
        held = torch.stack([self._held_at(p) for p in list(self._poses)[1:]], 1)
        before = self._frame if self._frame_before is None else self._frame_before
        rolled = self.model.rollout(self._frame, before, held)  # (1, k, M, 3)
        previous = self._frame if self.latency == 1 else rolled[:, -2]
        return rolled[:, -1], previous

    def _held_at(self, poses: torch.Tensor) -> torch.Tensor:
        """(1, M, 3) the held markers at gripper poses (2, 7) (free rows: 0)."""
        pose = poses[self.holder]
        placed = pose[:, :3] + self.lever[:, None] * axis_x(pose[:, 3:])
        return torch.where(self.held[:, None], placed, 0.0)[None]

    # ------------------------------------------------------------------ planning
    def predict(
        self, state: torch.Tensor, commands: torch.Tensor, previous: torch.Tensor | None
    ) -> torch.Tensor:
        """Predicted markers (B, H, M, 3) under gripper commands (B, H, 2, 6) in [-1, 1],
        the held ones carried by the grippers' integrated motion."""
        assert self.grippers is not None
        batch = commands.shape[0]
        held = self._held_along(commands)
        x = state.expand(batch, -1, -1)
        before = x if previous is None else previous.expand(batch, -1, -1)
        return self.model.rollout(x, before, held)

    def _held_along(self, commands: torch.Tensor) -> torch.Tensor:
        """(B, H, M, 3) the held markers after each step of commands (B, H, 2, 6): positions
        advance by v dt, each lever arm turns by w dt x arm (first order in w dt, a
        hundredth of a radian per step)."""
        twist = commands * self.scale * self.dt
        pose = self.grippers[self.holder]  # (M, 7)
        points = pose[:, :3] + torch.cumsum(twist[..., :3], 1)[:, :, self.holder]
        arm = (self.lever[:, None] * axis_x(pose[:, 3:])).expand(commands.shape[0], -1, -1)
        arms = []
        for k in range(commands.shape[1]):
            arm = arm + torch.cross(twist[:, k, self.holder, 3:], arm, dim=-1)
            arms.append(arm)
        return points + torch.stack(arms, 1)


def kalman_gain(noise_mm: float, model_error_mm: float) -> float:
    """The steady-state gain of a scalar random walk with process noise ``model_error_mm``
    measured with noise ``noise_mm`` (1 without noise: the report is the state)."""
    if noise_mm == 0:
        return 1.0
    q, r = model_error_mm**2, noise_mm**2
    predicted = 0.5 * (q + math.sqrt(q * q + 4 * q * r))  # the prior variance, P- = P + q
    return predicted / (predicted + r)


#: the view of each model form (a model's ``form`` attribute)
VIEWS: dict[str, type[RodView] | type[MarkerView]] = {"rod": RodView, "markers": MarkerView}


def make_view(
    env: Any, model: torch.nn.Module, device: torch.device, raw: bool = False
) -> RodView | MarkerView:
    """The view of ``model``'s form on ``env``; BadInput if the env observes another form.
    ``raw``: a marker view plans from the report as it is; BadInput if the model learned
    from data at another control period than the task's."""
    task = getattr(env, "task_spec", None)
    if task is not None:
        check_control_rate(model, task.control_dt, "the planner's model", "the task runs",
                           "re-train it on data at {used_hz} Hz, or set the task's control_dt "
                           "to {dt}")  # fmt: skip
    return VIEWS[getattr(model, "form", "rod")](env, model, device, raw)
