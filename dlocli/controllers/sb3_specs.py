"""The options of the SAC and TD3 agents (:mod:`dlocli.controllers.sb3_agents`): SB3's
constructor keywords, at the defaults the sweep on this task chose.

The candidates came from two documented sources: stable-baselines3's constructor defaults
(SAC: Haarnoja et al. 2018; TD3: Fujimoto et al. 2018, with no action noise) and
rl-baselines3-zoo's tuned values for the PyBullet locomotion envs (``hyperparams/sac.yml`` and
``hyperparams/td3.yml``, ``HalfCheetahBulletEnv-v0``: continuous actions in [-1, 1] and a
dense reward, the nearest tuned match to our task). ``benchmarks/rl_sweep.py`` compared them
and one-knob variants on this task against doing nothing (docs/results.md has its numbers), and
the defaults are its winners:

- SAC: the zoo's values. ``gamma`` 0.98, ``net_arch`` [400, 300], ``learning_rate`` 7.3e-4,
  ``tau`` 0.02, ``train_freq`` = ``gradient_steps`` = 8, ``buffer_size`` 300k, gSDE
  exploration with ``log_std_init`` -3, and ``learning_starts`` 1000 instead of the zoo's
  10000 (half of a 20k budget; five random episodes from five starts).
- TD3: SB3's defaults. The zoo's once-per-episode updates with action noise 0.1 drove the
  policy to the action bounds on this task whatever the discount.

``train_freq`` also takes "episode" (the zoo's ``[1, "episode"]``) as the task's episode
length in steps: ``learn(n)`` must stop after exactly ``n`` transitions, which SB3 guarantees
only for step counts.
"""

from __future__ import annotations

from typing import Annotated, Any, Literal

import numpy as np
from pydantic import BeforeValidator, Field

from dlocli.limits import MAX_COUNT, MAX_TRANSITIONS, refuse_unless_fits
from dlocli.specs import Device, Spec, new_default


def _check_train_freq(value: Any) -> Any:
    if value == "episode" or (type(value) is int and value > 0):
        return value
    raise ValueError("must be a positive number of env steps or 'episode'")


#: env steps between updates, or "episode": the task's episode length
TrainFreq = Annotated[int | Literal["episode"], BeforeValidator(_check_train_freq)]
TRAIN_FREQ_HELP = "Env steps between updates, or 'episode': once per task episode (its length)."


def _check_ent_coef(value: Any) -> Any:
    """What SB3 reads as an entropy coefficient, checked here: SB3 takes a negative one
    (which rewards certainty) and fails on a bad 'auto_X' only when the agent is built."""
    if isinstance(value, (int, float)) and not isinstance(value, bool) and value >= 0:
        return value
    if value == "auto":
        return value
    if isinstance(value, str) and value.startswith("auto_"):
        try:
            start = float(value.removeprefix("auto_"))
        except ValueError:
            start = 0.0
        if 0 < start < float("inf"):
            return value
    raise ValueError("must be a number >= 0, 'auto', or 'auto_X' with X > 0 (its start)")


#: the entropy coefficient of SAC: fixed, or learned from a start (1 for 'auto')
EntCoef = Annotated[str | float, BeforeValidator(_check_ent_coef)]


class SB3Spec(Spec):
    """Fields shared by the SB3 off-policy algorithms (constructor keywords of SB3)."""

    learning_rate: float = Field(3e-4, gt=0, description="Adam learning rate of actor and critics.")
    buffer_size: int = Field(
        1_000_000, gt=0, description="Replay buffer capacity (transitions; oldest dropped)."
    )
    learning_starts: int = Field(
        1000,
        ge=0,
        le=MAX_TRANSITIONS,
        description="Uniform random transitions before the first gradient step.",
    )
    batch_size: int = Field(
        256, gt=0, le=MAX_COUNT, description="Minibatch size of each gradient step."
    )
    gamma: float = Field(0.98, gt=0, le=1, description="Discount factor.")
    tau: float = Field(0.005, gt=0, le=1, description="Polyak coefficient of the target networks.")
    train_freq: TrainFreq = Field(1, description=TRAIN_FREQ_HELP)
    gradient_steps: int = Field(
        1,
        ge=-1,
        le=MAX_COUNT,
        description="Gradient steps per update (-1: one per env step since the last).",
    )
    net_arch: list[Annotated[int, Field(gt=0, le=65536)]] = Field(
        default_factory=lambda: [400, 300], description="Hidden layer sizes of actor and critics."
    )
    device: Device = "auto"

    def steps_per_update(self, episode_steps: int) -> int:
        """``train_freq`` in env steps for a task of ``episode_steps`` steps per episode."""
        return episode_steps if self.train_freq == "episode" else self.train_freq

    def sb3_kwargs(self, action_dim: int, episode_steps: int) -> dict[str, Any]:
        """Keyword arguments for the SB3 algorithm's constructor (|A|, steps per episode)."""
        data = self.model_dump(exclude={"net_arch"})
        data["train_freq"] = self.steps_per_update(episode_steps)
        data["policy_kwargs"] = {"net_arch": list(self.net_arch)}
        return data

    def refuse_oversized(self, agent: str, obs_dim: int, action_dim: int) -> None:
        """BadInput if the replay buffer (observation, next observation, action, reward,
        done, timeout per row) and the networks (actor and two critics with their targets,
        with gradients and Adam's two moments), all float32, exceed the usable memory."""
        actor = _mlp_parameters([obs_dim, *self.net_arch, 2 * action_dim])
        critic = _mlp_parameters([obs_dim + action_dim, *self.net_arch, 1])
        networks = 2 * actor + 4 * critic
        buffer = self.buffer_size * (2 * obs_dim + action_dim + 3)
        refuse_unless_fits(
            f"{agent} (net_arch {self.net_arch}, buffer_size {self.buffer_size})",
            4.0 * (4 * networks + buffer),
            "choose a smaller net_arch or buffer_size",
        )


def _mlp_parameters(sizes: list[int]) -> int:
    """Weights and biases of fully connected layers ``sizes[0] -> ... -> sizes[-1]``."""
    return sum((a + 1) * b for a, b in zip(sizes, sizes[1:], strict=False))


class SACSpec(SB3Spec):
    """Soft Actor-Critic with automatic entropy tuning (the zoo's Bullet values, see the module
    docstring)."""

    learning_rate: float = Field(
        7.3e-4, gt=0, description="Adam learning rate of actor, critics and entropy coefficient."
    )
    buffer_size: int = new_default(SB3Spec, "buffer_size", 300_000)
    tau: float = new_default(SB3Spec, "tau", 0.02)
    train_freq: TrainFreq = new_default(SB3Spec, "train_freq", 8)
    gradient_steps: int = new_default(SB3Spec, "gradient_steps", 8)
    ent_coef: EntCoef = Field(
        "auto",
        description="Entropy coefficient (>= 0), or 'auto' to learn it (target -|A|; "
        "'auto_X' starts it at X).",
    )
    use_sde: bool = Field(
        True,
        description="Generalized state-dependent exploration (gSDE) instead of independent "
        "Gaussian noise per step; false: SB3's default SAC exploration.",
    )
    sde_sample_freq: int = Field(
        -1,
        ge=-1,
        le=MAX_COUNT,
        description="gSDE: env steps between new noise matrices (-1: once per update).",
    )
    log_std_init: float = Field(
        -3.0, le=2, description="gSDE: initial log std of the exploration noise matrix."
    )

    def sb3_kwargs(self, action_dim: int, episode_steps: int) -> dict[str, Any]:
        data = super().sb3_kwargs(action_dim, episode_steps)
        data["policy_kwargs"]["log_std_init"] = data.pop("log_std_init")
        return data


class TD3Spec(SB3Spec):
    """Twin Delayed DDPG at stable-baselines3's defaults, which the sweep on this task picked
    over the zoo's Bullet values (see the module docstring)."""

    learning_rate: float = new_default(SB3Spec, "learning_rate", 1e-3)
    learning_starts: int = new_default(SB3Spec, "learning_starts", 100)
    gamma: float = new_default(SB3Spec, "gamma", 0.99)
    action_noise: float = Field(
        0.0,
        ge=0,
        description="Std of the Gaussian exploration noise on actions in [-1, 1] (0: none, "
        "SB3's default; the zoo uses 0.1).",
    )
    policy_delay: int = Field(2, gt=0, le=MAX_COUNT, description="Critic updates per actor update.")
    target_policy_noise: float = Field(0.2, ge=0, description="Std of target policy smoothing.")
    target_noise_clip: float = Field(0.5, ge=0, description="Clip of target policy smoothing.")

    def sb3_kwargs(self, action_dim: int, episode_steps: int) -> dict[str, Any]:
        from stable_baselines3.common.noise import NormalActionNoise

        data = super().sb3_kwargs(action_dim, episode_steps)
        sigma = data.pop("action_noise")
        noise = NormalActionNoise(np.zeros(action_dim), np.full(action_dim, sigma))
        data["action_noise"] = noise if sigma > 0 else None
        return data
