"""The one episode loop, and the random episodes every part of dlocli collects.

An episode records the true state, whatever the policy observed; with the markers
observation it also records the tracker's reports (what a learner of the marker model gets).

A *policy* is anything with ``reset(goal)`` and ``act(obs)``: every registered controller,
:class:`ActionSequence` (fixed actions, e.g. random ones) and :class:`NoisyPolicy` (another
policy's actions with random exploration noise). :func:`rollout` resets the env from a seed,
then the policy with the env's goal, and steps until the episode is truncated or the
simulation diverges; the diverged step is not recorded (its reward and the missing steps'
count at the clip, :func:`dlocli.env.metrics.episode_result`).

Seeds: :func:`stream_seed` derives every independent stream (an episode's start, its actions,
an iteration's trials) from the run's seed and integer keys.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from dlocli.data import Episode
from dlocli.env.metrics import episode_result, shape_error_mm
from dlocli.events import Callback, Event

#: the most control steps a random action is held (random holds explore further than noise)
MAX_HOLD = 10


def stream_seed(seed: int, *keys: int) -> int:
    """An independent, reproducible seed for the stream ``keys`` of the run ``seed``."""
    return int(np.random.SeedSequence([seed, *keys]).generate_state(1)[0])


def random_actions(rng: np.random.Generator, steps: int, action_dim: int) -> np.ndarray:
    """(steps, action_dim) uniform actions in [-1, 1], each held for 1..MAX_HOLD steps."""
    actions = np.empty((steps, action_dim), dtype=np.float32)
    t = 0
    while t < steps:
        hold = int(rng.integers(1, MAX_HOLD + 1))
        actions[t : t + hold] = rng.uniform(-1.0, 1.0, action_dim)
        t += hold
    return actions


class ActionSequence:
    """A policy that plays fixed actions, one per step."""

    def __init__(self, actions: np.ndarray) -> None:
        self.actions = actions
        self.t = 0

    def reset(self, goal: np.ndarray) -> None:
        self.t = 0

    def act(self, obs: np.ndarray) -> np.ndarray:
        self.t += 1
        return self.actions[self.t - 1]


class NoisyPolicy:
    """``policy``'s action, with probability ``probability`` plus Gaussian noise of ``std``,
    clipped to [-1, 1] (the exploration of the paper's Algorithm 1)."""

    def __init__(self, policy: Any, rng: np.random.Generator, probability: float, std: float):
        self.policy, self.rng, self.probability, self.std = policy, rng, probability, std

    def reset(self, goal: np.ndarray) -> None:
        self.policy.reset(goal)

    def act(self, obs: np.ndarray) -> np.ndarray:
        action = self.policy.act(obs)
        if self.rng.random() < self.probability:
            action = action + self.rng.normal(0.0, self.std, action.shape)
        return np.clip(action, -1.0, 1.0)


def rollout(
    env: Any,
    policy: Any,
    seed: int,
    progress: Callback | None = None,
    options: dict[str, Any] | None = None,
) -> Episode:
    """One episode of ``policy`` on ``env`` from ``env.reset(seed=seed, options=options)``.

    ``progress`` gets an Event after every recorded step: unit "step", ``done`` t = 1, 2, ...
    of ``episode_steps``, ``values`` the step's ``reward`` and the env's ``info``.
    """
    obs, _ = env.reset(seed=seed, options=options)
    policy.reset(env.goal)
    states, observations, commands, rewards = [env.state_parts()], [obs], [], []
    diverged = False
    for t in range(1, env.task_spec.episode_steps + 1):
        obs, reward, _, truncated, info = env.step(policy.act(obs))
        if info["diverged"]:
            diverged = True
            break
        states.append(env.state_parts())
        observations.append(obs)
        commands.append(info["commands"])
        rewards.append(reward)
        if progress is not None:
            step = {"reward": reward, "info": info}
            progress(Event("step", t, env.task_spec.episode_steps, step))
        if truncated:
            break
    tracked = getattr(env, "tracker", None) is not None
    seen = env.split_observation(np.array(observations)) if tracked else {}
    return Episode(
        positions=np.array([s["positions"] for s in states]),
        quaternions=np.array([s["quaternions"] for s in states]),
        grippers=np.array([s["grippers"] for s in states]),
        actions=np.array(commands, dtype=np.float32).reshape(-1, 2, 6),
        rewards=np.array(rewards, dtype=np.float32),
        goal=np.asarray(env.goal),
        diverged=diverged,
        markers=seen.get("markers"),
        visible=None if not seen else seen["visible"][..., 0] > 0.5,
    )


def random_episode(env: Any, reset_seed: int, action_seed: Any) -> Episode:
    """One episode of held uniform random actions (:func:`random_actions`)."""
    rng = np.random.default_rng(action_seed)
    actions = random_actions(rng, env.task_spec.episode_steps, env.action_space.shape[0])
    return rollout(env, ActionSequence(actions), reset_seed)


def episode_scores(episode: Episode, steps: int) -> dict[str, float]:
    """Initial and final error (mm), score and cumulative reward of a recorded episode of
    ``steps`` steps (a diverged episode's missing steps at the clip, a shorter one's not)."""
    return episode_result(
        shape_error_mm(episode.positions[0], episode.goal),
        shape_error_mm(episode.positions[-1], episode.goal),
        float(np.sum(episode.rewards)),
        len(episode.rewards),
        steps,
        diverged=bool(episode.diverged),
    )
