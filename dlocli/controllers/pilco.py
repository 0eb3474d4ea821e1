"""PILCO benchmark agent (Deisenroth & Rasmussen 2011, [DR11]) on a reduced rod state.

Reduced state: the positions of ``n_keypoints`` segments (with the markers observation:
free markers), one at the centre of each of ``n_keypoints`` equal stretches of the rod (for
20 segments and 3 keypoints: segments 3, 10 and 16), flattened to D = 3 * n_keypoints
metres. The goal is mapped the same way, and the saturating cost of [DR11] eq. 24 measures
the keypoints' distance to the goal's keypoints
with width ``cost_width`` (0.1 m: about that distance from a random start, so the start lies
on the cost's slope rather than its flat tail). Segment orientations and gripper poses are
left out: the GP treats their effect as noise. A PILCO step holds one action for
``action_repeat`` env steps, so a 200-step episode is a 20-step horizon at the default 10.

The loop ([DR11] Alg. 1), with episodes that carry over between ``learn`` calls:

1. ``initial_random_episodes`` episodes of uniform random actions (held like policy actions);
2. at the start of every later episode: fit the GP dynamics model on (reduced state, action)
   -> change of reduced state, subsampled to ``max_gp_points``; propagate the start
   distribution through policy and GP by moment matching for ``horizon`` steps; minimise the
   summed expected cost over the RBF policy's parameters with Adam (autograd gradients);
3. run the policy for the episode, adding its transitions to the data.

The policy acts on the error x - x_goal (reduced state minus reduced goal, both read from the
observation) and each update optimises it for the goal of the episode about to start, so an
agent trained on the fixed goal can be evaluated on random goals (paper Fig. 6).

``learn(n)`` consumes exactly ``n`` env transitions; an episode cut by the budget goes on at
the next call. The math (GP, moment matching, squashing, cost) is in
:mod:`dlocli.controllers.pilco_math`, written here in torch rather than wrapped from a
library, so that it carries no extra dependency and is tested against Monte Carlo.
"""

from __future__ import annotations

import io
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from dlocli.controllers.base import LearningAgent, resolve_agent_spec
from dlocli.controllers.pilco_math import (
    DTYPE,
    GaussianProcess,
    RBFPolicy,
    expected_return_cost,
)
from dlocli.controllers.specs import PilcoSpec
from dlocli.io import read_json, write_bytes_atomic, write_json_atomic


def keypoint_indices(n_segments: int, n_keypoints: int) -> np.ndarray:
    """Segment at the centre of each of ``n_keypoints`` equal stretches of the rod."""
    k = min(n_keypoints, n_segments)
    return np.floor((np.arange(k) + 0.5) * n_segments / k).astype(int)


@dataclass
class PilcoUpdate:
    """What one policy update did (kept in ``PilcoAgent.history``)."""

    transitions: int
    gp_points: int
    gp_seconds: float
    policy_seconds: float
    expected_cost: float


class PilcoAgent(LearningAgent):
    """PILCO: GP dynamics, moment-matching rollouts, RBF policy, saturating cost."""

    name = "pilco"
    spec_cls = PilcoSpec

    def __init__(
        self, env: Any, seed: int = 0, spec: PilcoSpec | None = None, **spec_fields: Any
    ) -> None:
        super().__init__(env, seed=seed)
        self.spec: PilcoSpec = resolve_agent_spec(PilcoSpec, spec, spec_fields)
        self.keypoints = keypoint_indices(env.n_segments, self.spec.n_keypoints)
        self._positions = "positions"
        layout = getattr(env, "marker_layout", None)
        if layout is not None:  # the markers observation: keypoints among the free markers
            free = np.flatnonzero(~layout.held)
            self.keypoints = free[keypoint_indices(len(free), self.spec.n_keypoints)]
            self._positions = "markers"
        self.rng = np.random.default_rng(seed)
        self.generator = torch.Generator().manual_seed(seed)
        self.policy: RBFPolicy | None = None
        self.history: list[PilcoUpdate] = []
        self._inputs: list[np.ndarray] = []  # (x, u) per PILCO step
        self._targets: list[np.ndarray] = []  # x' - x
        self._starts: list[np.ndarray] = []  # reduced state at each episode start
        self._episodes = 0
        self._stale = False  # new data since the last update
        self._obs: np.ndarray | None = None  # training episode in progress
        self._random_episode = True
        self._block_state = np.zeros(0)
        self._block_action = np.zeros(self.action_dim)
        self._block_steps = 0
        self._diverged = False
        self._hold_action = np.zeros(self.action_dim)  # for act(): actions held like in training
        self._hold_steps = 0

    # ------------------------------------------------------------------ observations
    def reduce(self, obs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Reduced state and reduced goal (3 * n_keypoints each) of a flat observation."""
        parts = self.env.split_observation(obs)
        state = parts[self._positions][self.keypoints].ravel()
        goal = parts["goal"][self.keypoints].ravel()
        return state.astype(np.float64), goal.astype(np.float64)

    def policy_action(self, obs: np.ndarray) -> np.ndarray:
        """The deterministic policy's action (zeros before the first update)."""
        if self.policy is None:
            return np.zeros(self.action_dim)
        state, goal = self.reduce(obs)
        with torch.no_grad():
            error = torch.as_tensor(state - goal, dtype=DTYPE)
            return self.policy(error).numpy()

    # ------------------------------------------------------------------ Controller
    def reset(self, goal: np.ndarray) -> None:
        super().reset(goal)
        self._hold_steps = 0

    def _act(self, obs: np.ndarray) -> np.ndarray:
        if self._hold_steps % self.spec.action_repeat == 0:
            self._hold_action = self.policy_action(obs)
        self._hold_steps += 1
        return self._hold_action

    # ------------------------------------------------------------------ LearningAgent
    def learn(self, transitions: int) -> None:
        """Interact for exactly ``transitions`` env steps, updating at episode starts."""
        for _ in range(max(transitions, 0)):
            if self._obs is None:
                self._begin_episode()
            self._env_step()
            self.transitions += 1

    def _begin_episode(self) -> None:
        obs, _ = self.env.reset(seed=self.seed if self._episodes == 0 else None)
        self._obs = obs
        state, goal = self.reduce(obs)
        self._starts.append(state)
        ready = self._episodes >= self.spec.initial_random_episodes and len(self._targets) >= 2
        if ready and self._stale:
            self.update(goal)
        self._random_episode = self.policy is None
        self._block_steps = 0
        self._diverged = False
        self._episodes += 1

    def _env_step(self) -> None:
        assert self._obs is not None
        if self._block_steps == 0:
            self._block_state = self.reduce(self._obs)[0]
            if self._random_episode:
                self._block_action = self.rng.uniform(-1.0, 1.0, self.action_dim)
            else:
                self._block_action = self.policy_action(self._obs)
        obs, _, _, truncated, info = self.env.step(self._block_action.astype(np.float32))
        self._obs = obs
        self._block_steps += 1
        # a diverged episode runs on frozen until truncated: it spends budget and adds no data
        self._diverged |= bool(info["diverged"])
        if self._block_steps == self.spec.action_repeat and not self._diverged:
            self._record(self._block_state, self._block_action, self.reduce(obs)[0])
            self._block_steps = 0
        if truncated:
            self._obs = None

    def _record(self, state: np.ndarray, action: np.ndarray, next_state: np.ndarray) -> None:
        self._inputs.append(np.concatenate([state, action]))
        self._targets.append(next_state - state)
        self._stale = True

    # ------------------------------------------------------------------ checkpoints
    def save_state(self, slot: Path, shared: Path) -> bool:
        """Between episodes: the data, the policy and every generator (the env's too), as
        ``learner.json`` and tensors in ``learner.pt`` (read with ``weights_only=True``)."""
        if self._obs is not None:
            return False
        tensors = {
            "inputs": torch.from_numpy(np.asarray(self._inputs)),
            "targets": torch.from_numpy(np.asarray(self._targets)),
            "starts": torch.from_numpy(np.asarray(self._starts)),
            "generator": self.generator.get_state(),
            "policy": None if self.policy is None else self.policy.state_dict(),
        }
        image = io.BytesIO()
        torch.save(tensors, image)
        write_bytes_atomic(Path(slot) / "learner.pt", image.getbuffer())
        write_json_atomic(
            Path(slot) / "learner.json",
            {
                "transitions": self.transitions,
                "episodes": self._episodes,
                "stale": self._stale,
                "rng": self.rng.bit_generator.state,
                "history": [asdict(update) for update in self.history],
                "env_generator": self.env.generator_state(),
                "episode_returns": list(self.env.episode_returns),
            },
        )
        return True

    def load_state(self, slot: Path, shared: Path) -> None:
        """Continue from :meth:`save_state` (nothing there is unpickled)."""
        state = read_json(Path(slot) / "learner.json")
        tensors = torch.load(Path(slot) / "learner.pt", weights_only=True)
        self.transitions, self._episodes = state["transitions"], state["episodes"]
        self._stale = state["stale"]
        self.rng.bit_generator.state = state["rng"]
        self.history = [PilcoUpdate(**update) for update in state["history"]]
        self._inputs = list(tensors["inputs"].numpy())
        self._targets = list(tensors["targets"].numpy())
        self._starts = list(tensors["starts"].numpy())
        self.generator.set_state(tensors["generator"])
        self.policy = None if tensors["policy"] is None else self._saved_policy(tensors["policy"])
        self.env.restore_generator(state["env_generator"], state["episode_returns"])

    def _saved_policy(self, weights: dict[str, torch.Tensor]) -> RBFPolicy:
        """An RBF policy of the saved one's shape holding its ``weights``."""
        action_dim, n_basis = weights["weights"].shape
        centres = torch.zeros(n_basis, weights["centres"].shape[1], dtype=DTYPE)
        # its random initial weights are overwritten: drawn from a throwaway generator
        policy = RBFPolicy(centres, action_dim, weights["scale"], torch.Generator())
        policy.load_state_dict(weights)
        return policy

    # ------------------------------------------------------------------ PILCO update
    def update(self, goal: np.ndarray) -> PilcoUpdate:
        """Fit the GP on all data so far, then optimise the policy towards ``goal``."""
        start = time.perf_counter()
        gp = self._fit_gp()
        gp_seconds = time.perf_counter() - start
        if self.policy is None:
            self.policy = self._initial_policy(goal)
        start = time.perf_counter()
        cost = self._optimise_policy(gp, torch.as_tensor(goal, dtype=DTYPE))
        record = PilcoUpdate(
            transitions=self.transitions,
            gp_points=int(gp.x.shape[0]),
            gp_seconds=gp_seconds,
            policy_seconds=time.perf_counter() - start,
            expected_cost=cost,
        )
        self.history.append(record)
        self._stale = False
        return record

    def _training_data(self) -> tuple[torch.Tensor, torch.Tensor]:
        inputs, targets = np.asarray(self._inputs), np.asarray(self._targets)
        if len(inputs) > self.spec.max_gp_points:
            keep = self.rng.choice(len(inputs), self.spec.max_gp_points, replace=False)
            inputs, targets = inputs[keep], targets[keep]
        return torch.as_tensor(inputs, dtype=DTYPE), torch.as_tensor(targets, dtype=DTYPE)

    def _fit_gp(self) -> GaussianProcess:
        gp = GaussianProcess(*self._training_data())
        gp.fit(self.spec.gp_iterations)
        return gp

    def _initial_policy(self, goal: np.ndarray) -> RBFPolicy:
        """Centres on random visited error states, inputs scaled by their spread, small weights."""
        n_state = goal.shape[0]
        errors = np.asarray(self._inputs)[:, :n_state] - goal
        few = len(errors) < self.spec.n_basis
        pick = self.rng.choice(len(errors), self.spec.n_basis, replace=few)
        spread = np.maximum(errors.std(0), self.spec.policy_scale_floor)
        return RBFPolicy(
            torch.as_tensor(errors[pick]), self.action_dim, torch.as_tensor(spread), self.generator
        )

    def _start_distribution(self) -> tuple[torch.Tensor, torch.Tensor]:
        """Mean and covariance of the reduced start states seen so far (plus a jitter)."""
        starts = np.asarray(self._starts)
        cov = np.cov(starts.T) if len(starts) > 1 else np.zeros((starts.shape[1],) * 2)
        cov = cov + 1e-6 * np.eye(starts.shape[1])
        return torch.as_tensor(starts.mean(0), dtype=DTYPE), torch.as_tensor(cov, dtype=DTYPE)

    def _horizon(self) -> int:
        if self.spec.horizon is not None:
            return self.spec.horizon
        return max(1, self.env.task_spec.episode_steps // self.spec.action_repeat)

    def _optimise_policy(self, gp: GaussianProcess, goal: torch.Tensor) -> float:
        """Minimise J = sum_t E[c(x_t)] by Adam; keep the best parameters seen. Returns J."""
        assert self.policy is not None
        m0, s0 = self._start_distribution()
        weight = torch.eye(goal.shape[0], dtype=DTYPE) / self.spec.cost_width**2
        optimizer = torch.optim.Adam(self.policy.parameters(), lr=self.spec.policy_lr)
        best = (float("inf"), {k: v.clone() for k, v in self.policy.state_dict().items()})
        for _ in range(self.spec.policy_iterations):
            optimizer.zero_grad()
            loss = expected_return_cost(m0, s0, gp, self.policy, goal, weight, self._horizon())
            if not torch.isfinite(loss):
                break
            if loss.item() < best[0]:
                best = (loss.item(), {k: v.clone() for k, v in self.policy.state_dict().items()})
            loss.backward()
            optimizer.step()
        self.policy.load_state_dict(best[1])
        return best[0]
