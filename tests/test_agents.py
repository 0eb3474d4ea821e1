"""Learning agents (SAC, TD3, PILCO and every other registered one) on the real MuJoCo env,
and PILCO's math vs Monte Carlo."""

from __future__ import annotations

import functools
from typing import Any

import numpy as np
import pytest
import torch

import dlocli
from dlocli.controllers import pilco_math
from dlocli.controllers.base import LearningAgent, make_controller
from dlocli.controllers.pilco_math import (
    DTYPE,
    GaussianProcess,
    RBFPolicy,
    expected_return_cost,
    expected_saturating_cost,
    rbf_moments,
    sin_moments,
)
from dlocli.errors import BadInput
from dlocli.registry import controllers

from tiny import MUJOCO_ROD, TINY_AGENTS

#: every registered learning agent: one is tested here the moment it registers (a plugin's
#: too, when its package is installed), at its defaults unless TINY_AGENTS makes it smaller
AGENTS = [n for n in controllers.names() if issubclass(controllers.facts(n), LearningAgent)]


pytestmark = pytest.mark.usefixtures("one_thread")  # conftest.py


def small_env() -> Any:
    env = dlocli.make_env(backend=MUJOCO_ROD, task="single", seed=0, episode_steps=20)
    env.step_calls = 0
    step = env.step

    def counting_step(action: np.ndarray) -> Any:
        env.step_calls += 1
        return step(action)

    env.step = counting_step
    return env


def train(name: str, seed: int = 0) -> tuple[LearningAgent, Any]:
    env = small_env()
    agent = controllers.get(name)(env, seed=seed, **TINY_AGENTS.get(name, {}))
    agent.learn(25)  # cuts an episode: the next call carries on with it
    agent.learn(35)
    return agent, env


@functools.cache
def trained(name: str) -> tuple[LearningAgent, Any]:
    """One agent per name trained for 60 transitions, shared by the tests (do not step it)."""
    return train(name)


@pytest.fixture(scope="module")
def probe_obs() -> np.ndarray:
    env = dlocli.make_env(backend=MUJOCO_ROD, task="single", seed=3, episode_steps=20)
    obs, _ = env.reset(seed=3)
    return obs


@pytest.mark.parametrize("name", AGENTS)
def test_agent_uses_exact_budget_and_acts_deterministically(name: str, probe_obs: np.ndarray):
    agent, env = trained(name)
    assert isinstance(agent, LearningAgent)
    assert agent.transitions == 60
    assert env.step_calls == 60
    agent.reset(env.goal)
    action = agent.act(probe_obs)
    assert action.shape == (6,) and action.dtype == np.float32
    assert np.all(np.isfinite(action)) and np.all(np.abs(action) <= 1.0)
    twin, _ = train(name)
    twin.reset(env.goal)
    np.testing.assert_allclose(twin.act(probe_obs), action, atol=1e-6)


@pytest.mark.parametrize("name", AGENTS)
def test_agent_acts_on_the_bimanual_task(name: str):
    env = dlocli.make_env(backend=MUJOCO_ROD, task="bimanual", seed=0, episode_steps=20)
    obs, _ = env.reset()
    agent = controllers.get(name)(env, seed=0, **TINY_AGENTS.get(name, {}))
    agent.reset(env.goal)
    action = agent.act(obs)
    assert action.shape == (12,) and np.all(np.abs(action) <= 1.0)


def test_pilco_updates_its_policy_within_the_budget(probe_obs: np.ndarray):
    agent, _ = trained("pilco")
    assert len(agent.history) == 2  # at the starts of the 2nd and 3rd episodes
    assert all(np.isfinite(h.expected_cost) for h in agent.history)
    assert agent.history[-1].gp_points == 15  # 20 held-action transitions, subsampled
    assert np.any(agent.policy_action(probe_obs) != 0.0)


def first_pilco_policy(**options: Any) -> Any:
    """PILCO's policy after one random episode on the bimanual task (its first update)."""
    env = dlocli.make_env(backend=MUJOCO_ROD, task="bimanual", seed=0, episode_steps=20)
    agent = make_controller("pilco", env, options={**TINY_AGENTS["pilco"], **options}, seed=0)
    agent.learn(21)
    assert len(agent.history) == 1
    return agent.policy


def test_pilco_policy_scale_floor_keeps_far_starts_in_reach():
    """Bimanual starts lie many times the first random episode's spread from its states: a
    policy scaled to that spread has vanishing basis functions there, so it outputs zero and
    so does its gradient (pilco did nothing on the bimanual task). The floor keeps them."""
    far = torch.full((9,), 0.15, dtype=torch.float64)  # every keypoint 26 cm off the goal
    narrow = first_pilco_policy(policy_scale_floor=0.01)  # the default before 2026-12-02
    floored = first_pilco_policy(policy_scale_floor=0.2)
    assert torch.all(floored.scale >= 0.2)

    def reach(policy: Any) -> tuple[float, float]:
        """The largest action at ``far`` and its largest gradient by a basis weight (the
        basis function's value there: what the policy's update can move)."""
        policy.zero_grad()
        action = policy(far).abs()
        action.sum().backward()
        return action.max().item(), policy.weights.grad.abs().max().item()

    # the floored action is about 1e-3 on both MuJoCo rods (the flex rod's 0.9e-3), the
    # gradient about 3e-3: the gradient is what the policy's update needs
    assert max(reach(narrow)) < 1e-6
    assert reach(floored)[1] > 1e-3


def test_sb3_agent_state_roundtrip(tmp_path, probe_obs: np.ndarray):
    agent, _ = trained("sac")
    slot, shared = tmp_path / "slot", tmp_path / "shared"
    slot.mkdir()
    assert agent.save_state(slot, shared)
    fresh = controllers.get("sac")(small_env(), seed=1, **TINY_AGENTS["sac"])
    fresh.load_state(slot, shared)
    assert fresh.transitions == 60 and fresh.model.replay_buffer.pos == 60
    np.testing.assert_allclose(fresh.act(probe_obs), agent.act(probe_obs), atol=1e-6)
    fresh.learn(5)
    assert fresh.transitions == 65


def test_agents_build_from_registry_spec_and_refuse_unknown_options():
    env = dlocli.make_env(backend=MUJOCO_ROD, task="single", seed=0, episode_steps=20)
    agent = make_controller("td3", env, options={"batch_size": 8, "action_noise": 0.2}, seed=0)
    assert agent.spec.batch_size == 8 and agent.spec.net_arch == [400, 300]
    with pytest.raises(BadInput, match="unknown field 'bogus'"):
        make_controller("pilco", env, options={"bogus": 1})


def test_sb3_defaults_are_the_swept_values_and_reach_sb3():
    env = dlocli.make_env(backend=MUJOCO_ROD, task="single", seed=0, episode_steps=20)
    sac = make_controller("sac", env, options={"net_arch": [16, 16]}, seed=0)
    assert (sac.model.gamma, sac.model.tau, sac.model.learning_starts) == (0.98, 0.02, 1000)
    assert sac.model.use_sde and torch.all(sac.model.policy.actor.log_std == -3.0)
    plain = make_controller("sac", env, options={"net_arch": [16, 16], "use_sde": False})
    assert not plain.model.use_sde
    td3 = make_controller("td3", env, options={"net_arch": [16, 16]}, seed=0)
    assert (td3.model.gamma, td3.model.learning_starts, td3.model.gradient_steps) == (0.99, 100, 1)
    assert td3.model.action_noise is None  # SB3's default: no exploration noise
    zoo = {"net_arch": [16, 16], "train_freq": "episode", "gradient_steps": -1, "action_noise": 0.1}
    per_episode = make_controller("td3", env, options=zoo, seed=0)
    assert per_episode.model.train_freq.frequency == 20 and per_episode.model.gradient_steps == -1
    np.testing.assert_allclose(per_episode.model.action_noise._sigma, 0.1)


# ---------------------------------------------------------------------- PILCO math vs MC
def gaussian_samples(mean: torch.Tensor, cov: torch.Tensor, n: int, seed: int) -> torch.Tensor:
    gen = torch.Generator().manual_seed(seed)
    noise = torch.randn(n, mean.shape[0], generator=gen, dtype=DTYPE)
    return mean + noise @ torch.linalg.cholesky(cov).T


def random_problem() -> tuple[GaussianProcess, torch.Tensor, torch.Tensor]:
    gen = torch.Generator().manual_seed(0)
    x = torch.randn(25, 4, generator=gen, dtype=DTYPE)
    columns = [torch.sin(x[:, 0]) + 0.3 * x[:, 1], 0.5 * x[:, 2] * x[:, 3], torch.cos(x[:, 1])]
    y = torch.stack(columns, 1)
    gp = GaussianProcess(x, y + 0.01 * torch.randn(25, 3, generator=gen, dtype=DTYPE))
    gp.fit(30)
    root = 0.3 * torch.randn(4, 4, generator=gen, dtype=DTYPE)
    mean = torch.tensor([0.2, -0.1, 0.3, 0.1], dtype=DTYPE)
    return gp, mean, root @ root.T + 0.01 * torch.eye(4, dtype=DTYPE)


def test_gp_moment_matching_matches_monte_carlo():
    gp, m, s = random_problem()
    mean, cov, cross = rbf_moments(m, s, gp.x, gp.beta, gp.lengthscales, gp.signal_var, gp.inv_k)
    z = gaussian_samples(m, s, 200_000, seed=1)
    mu, var = gp.predict(z)
    # law of total covariance: Cov[f] = Cov[E[f|z]] + E[Var[f|z]] (independent GPs)
    mc_cov = torch.cov(mu.T) + torch.diag(var.mean(0))
    mc_cross = (z - z.mean(0)).T @ (mu - mu.mean(0)) / (len(z) - 1)
    torch.testing.assert_close(mean, mu.mean(0), atol=3e-3, rtol=0)
    torch.testing.assert_close(cov, mc_cov, atol=3e-3, rtol=0)
    torch.testing.assert_close(cross, mc_cross, atol=3e-3, rtol=0)


def test_sine_squashing_moments_match_monte_carlo():
    m = torch.tensor([0.3, -1.0], dtype=DTYPE)
    s = torch.tensor([[0.5, 0.2], [0.2, 0.3]], dtype=DTYPE)
    y = gaussian_samples(m, s, 200_000, seed=2)
    mean, cov, d_cos = sin_moments(m, s)
    u = torch.sin(y)
    torch.testing.assert_close(mean, u.mean(0), atol=3e-3, rtol=0)
    torch.testing.assert_close(cov, torch.cov(u.T), atol=3e-3, rtol=0)
    mc_cross = (y - y.mean(0)).T @ (u - u.mean(0)) / (len(y) - 1)
    torch.testing.assert_close(s @ d_cos, mc_cross, atol=3e-3, rtol=0)


def test_expected_saturating_cost_matches_monte_carlo():
    _, m, s = random_problem()
    target = torch.tensor([0.5, 0.0, -0.2, 0.1], dtype=DTYPE)
    weight = torch.eye(4, dtype=DTYPE) / 0.5**2
    x = gaussian_samples(m, s, 200_000, seed=3)
    diff = x - target
    mc = (1.0 - torch.exp(-0.5 * ((diff @ weight) * diff).sum(1))).mean()
    expected = expected_saturating_cost(m, s, target, weight)
    torch.testing.assert_close(expected, mc, atol=3e-3, rtol=0)


def test_checkpointed_rollout_gives_the_same_cost_and_gradient(monkeypatch):
    """Large GPs recompute each step in the backward pass; small ones keep every step. Both
    must give bitwise the same cost and policy gradient."""
    gp, m, s = random_problem()  # 4-D inputs: a 3-D state and a 1-D action
    state_m, state_s = m[:3], s[:3, :3]
    goal = torch.tensor([0.5, 0.0, -0.2], dtype=DTYPE)
    centres = torch.randn(5, 3, generator=torch.Generator().manual_seed(4), dtype=DTYPE)
    policy = RBFPolicy(centres, 1, torch.ones(3, dtype=DTYPE), torch.Generator().manual_seed(5))
    weight = torch.eye(3, dtype=DTYPE) / 0.5**2

    def cost_and_grads(threshold: int) -> tuple[torch.Tensor, list[torch.Tensor]]:
        monkeypatch.setattr(pilco_math, "CHECKPOINT_ELEMENTS", threshold)
        policy.zero_grad()
        cost = expected_return_cost(state_m, state_s, gp, policy, goal, weight, horizon=6)
        cost.backward()
        return cost.detach(), [p.grad.clone() for p in policy.parameters()]

    kept, checkpointed = cost_and_grads(10**12), cost_and_grads(0)
    assert torch.equal(kept[0], checkpointed[0])
    assert all(torch.equal(a, b) for a, b in zip(kept[1], checkpointed[1], strict=True))
    assert any(g.abs().sum() > 0 for g in kept[1])


def test_the_defaults_are_the_sweeps_winners():
    """SAC and TD3 default to the configurations benchmarks/rl_sweep.py picked."""
    import importlib.util
    from pathlib import Path

    from dlocli.controllers.sb3_specs import SACSpec, TD3Spec

    path = Path(__file__).parent.parent / "benchmarks" / "rl_sweep.py"
    module_spec = importlib.util.spec_from_file_location("rl_sweep", path)
    sweep = importlib.util.module_from_spec(module_spec)
    module_spec.loader.exec_module(sweep)
    assert SACSpec.model_validate(sweep.CONFIGS["sac/zoo"][1]) == SACSpec()
    assert TD3Spec.model_validate(sweep.CONFIGS["td3/sb3"][1]) == TD3Spec()
