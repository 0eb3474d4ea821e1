"""SAC and TD3 benchmark agents: stable-baselines3 behind the :class:`LearningAgent` contract.

One adapter, :class:`SB3Agent`, drives any SB3 off-policy algorithm on the env's flat Box
observation (rod positions, quaternions, gripper poses and the goal, so a policy trained on a
fixed goal can be evaluated on random goals, paper Fig. 6). The reward is the env's paper
eq. 12, already clipped to [-1.5, 0]. ``learn(n)`` consumes exactly ``n`` env transitions of
the training env; the episode in progress carries over between calls. Their options and the
defaults chosen: :mod:`dlocli.controllers.sb3_specs`; the buffers hold the whole budget, so
nothing is ever discarded.

Seeding: SB3's ``seed=`` seeds Python's, NumPy's and torch's global generators, the action
space and the env's first reset, so the same seed on CPU gives the same agent. Torch's thread
count is the caller's choice; on a busy CPU one thread learns faster than several.
"""

from __future__ import annotations

import json
import warnings
import zipfile
from collections import deque
from pathlib import Path
from pickle import UnpicklingError  # what torch's weights_only loader raises
from typing import Any, ClassVar

import numpy as np

from dlocli.controllers.base import LearningAgent, resolve_agent_spec
from dlocli.controllers.sb3_replay import REPLAY_DIR, load_buffer_rows, save_buffer_rows
from dlocli.controllers.sb3_specs import SACSpec, SB3Spec, TD3Spec
from dlocli.errors import BadInput
from dlocli.io import atomic_path, read_json, write_json_atomic
from dlocli.tensorboard import available


class SB3Agent(LearningAgent):
    """Adapter for one SB3 off-policy algorithm; subclasses name the algorithm and spec."""

    algorithm: ClassVar[str] = ""
    spec_cls: ClassVar[type[SB3Spec]] = SB3Spec

    def __init__(
        self, env: Any, seed: int = 0, spec: SB3Spec | None = None, **spec_fields: Any
    ) -> None:
        super().__init__(env, seed=seed)
        self.spec: SB3Spec = resolve_agent_spec(self.spec_cls, spec, spec_fields)
        self.episode_steps = int(env.task_spec.episode_steps)
        self.model = self._build_model()
        self.log_directory: Path | None = None  # TensorBoard events of learning (log_to)
        self._logging: Any = None  # the model whose logger writes there

    # ------------------------------------------------------------------ construction
    @classmethod
    def warm_up(cls) -> None:
        import stable_baselines3.common.monitor  # noqa: F401  (seconds to import)

    def _algorithm_class(self) -> Any:
        import stable_baselines3

        return getattr(stable_baselines3, self.algorithm)

    def _build_model(self) -> Any:
        from gymnasium.spaces import flatdim
        from stable_baselines3.common.monitor import Monitor

        self.spec.refuse_oversized(self.name, flatdim(self.env.observation_space), self.action_dim)
        kwargs = self.spec.sb3_kwargs(self.action_dim, self.episode_steps)
        return self._algorithm_class()(
            "MlpPolicy", Monitor(self.env), seed=self.seed, verbose=0, **kwargs
        )

    # ------------------------------------------------------------------ LearningAgent
    def learn(self, transitions: int) -> None:
        """Run SB3's learner for exactly ``transitions`` more env steps."""
        if transitions <= 0:
            return
        self._attach_logger()
        start = self.model.num_timesteps
        full = transitions - transitions % self.spec.steps_per_update(self.episode_steps)
        if full:
            self.model.learn(full, reset_num_timesteps=False)
        if transitions - full:
            self._learn_remainder(transitions - full)
        used = self.model.num_timesteps - start
        if used != transitions:
            raise RuntimeError(f"{self.name} used {used} transitions instead of {transitions}")
        self.transitions += used

    def _learn_remainder(self, steps: int) -> None:
        """Collect a last, shorter update period so the total is exact (train_freq > 1)."""
        from stable_baselines3.common.type_aliases import TrainFreq, TrainFrequencyUnit

        saved = self.model.train_freq
        self.model.train_freq = TrainFreq(steps, TrainFrequencyUnit.STEP)
        try:
            self.model.learn(steps, reset_num_timesteps=False)
        finally:
            self.model.train_freq = saved

    def _act(self, obs: np.ndarray) -> np.ndarray:
        action, _ = self.model.predict(np.asarray(obs, dtype=np.float32), deterministic=True)
        return action

    def log_to(self, directory: Path) -> None:
        """SB3's own logger writes its training curves (losses, entropy, episode reward)
        there as TensorBoard events, when TensorBoard is installed: one logger for every
        ``learn`` call (SB3 would open a new event file per call)."""
        if available():
            self.log_directory = Path(directory) / f"{self.algorithm}_0"

    def _attach_logger(self) -> None:
        """Give the current model (a loaded one is new) the logger, once, as it learns."""
        from stable_baselines3.common.logger import configure

        if self.log_directory is not None and self._logging is not self.model:
            self.model.set_logger(configure(str(self.log_directory), ["tensorboard"]))
            self._logging = self.model

    # ------------------------------------------------------------------ checkpoints
    def save_policy(self, directory: Path) -> bool:
        """Write ``model.zip`` (SB3's own format: networks and optimizer, no replay buffer)
        and ``agent.json`` (algorithm, transitions, seed, spaces) into ``directory``."""
        directory = Path(directory)
        directory.mkdir(parents=True, exist_ok=True)
        with atomic_path(directory / "model.zip") as tmp, open(tmp, "wb") as file:
            self.model.save(file)
        meta = {
            "algorithm": self.algorithm,
            "transitions": self.transitions,
            "seed": self.seed,
            "observation_shape": list(self.env.observation_space.shape),
            "action_shape": list(self.env.action_space.shape),
        }
        write_json_atomic(directory / "agent.json", meta)
        return True

    def load_policy(self, directory: Path, saved: dict[str, Any] | None = None) -> None:
        """Act with a policy :meth:`save_policy` wrote; nothing in it is unpickled (see
        :meth:`_load_model`). ``saved``: a checkpoint's learning state (:meth:`load_state`),
        to continue learning in the saved episode."""
        directory = Path(directory)
        meta = self._saved_meta(directory)
        for key, space in (("observation_shape", self.env.observation_space),
                           ("action_shape", self.env.action_space)):  # fmt: skip
            if meta.get(key) != list(space.shape):
                raise BadInput(
                    f"--policy {directory} was trained with {key.split('_')[0]}s of shape "
                    f"{meta.get(key)}, this task has {list(space.shape)}; pass the same --task "
                    "and observation settings as its bench"
                )
        values = self._unpickled_values(saved)
        self.model = self._load_model(directory, values, force_reset=saved is None)
        self.transitions = int(meta["transitions"])

    def _unpickled_values(self, saved: dict[str, Any] | None = None) -> dict[str, Any]:
        """What stands in for each cloudpickled entry of the zip's ``data``: the agent's own
        objects (built from its spec and env) and, for the learning state, ``saved`` (a
        checkpoint's ``learner.json``); without it the state of a fresh agent."""
        saved = saved or {}
        model = self.model
        window = model._stats_window_size
        last_obs = saved.get("last_obs")
        if last_obs is not None:
            last_obs = np.asarray(last_obs, dtype=model.observation_space.dtype)
        return {
            "policy_class": model.policy_class,
            "lr_schedule": model.lr_schedule,
            "observation_space": model.observation_space,
            "action_space": model.action_space,
            "replay_buffer_class": model.replay_buffer_class,
            "train_freq": model.train_freq,
            "action_noise": model.action_noise,
            "_last_obs": last_obs,
            # checkpoints are taken between episodes only (save_state)
            "_last_episode_starts": np.ones((model.n_envs,), dtype=bool),
            "_last_original_obs": None,  # only read through a VecNormalize, which is not used
            "ep_info_buffer": deque(saved.get("episode_infos", []), maxlen=window),
            "ep_success_buffer": deque(saved.get("episode_successes", []), maxlen=window),
        }

    def _load_model(self, directory: Path, values: dict[str, Any], force_reset: bool) -> Any:
        """SB3's model from ``directory/model.zip`` without running code from the file.

        SB3 stores some attributes cloudpickled (``:serialized:``): unpickling them would run
        whatever a crafted zip holds. The zips this agent writes pickle only the entries of
        ``values``, which SB3 then takes from ``values`` instead; a zip pickling anything else
        is refused. Its tensors are read with ``torch.load(weights_only=True)`` by SB3."""
        path = directory / "model.zip"
        try:
            with zipfile.ZipFile(path) as archive:
                data = json.loads(archive.read("data"))
        except (OSError, KeyError, ValueError, zipfile.BadZipFile) as exc:
            raise BadInput(
                f"--policy {directory}: model.zip is not a stable-baselines3 zip ({exc}); "
                "pass the policy directory of a `dlo bench` job"
            ) from exc
        entries = data.items() if isinstance(data, dict) else []
        pickled = {k for k, v in entries if isinstance(v, dict) and ":serialized:" in v}
        if not entries or pickled - values.keys():
            raise BadInput(
                f"--policy {directory}: model.zip holds pickled entries dlo never writes "
                f"({', '.join(sorted(pickled - values.keys())) or 'data'}); loading them could "
                "run code. Pass a policy saved by `dlo bench`"
            )
        try:
            with warnings.catch_warnings():  # torch's on a crafted pickle: the error says it
                warnings.simplefilter("ignore")
                return self._algorithm_class().load(
                    path,
                    env=self.model.get_env(),
                    device=self.spec.device,
                    force_reset=force_reset,
                    custom_objects=values,
                )
        except (RuntimeError, ValueError, KeyError, TypeError, AttributeError, AssertionError,
                EOFError, UnpicklingError, zipfile.BadZipFile) as exc:  # fmt: skip
            raise BadInput(
                f"--policy {directory}: model.zip does not load as this agent's "
                f"{self.algorithm} policy ({str(exc).splitlines()[0][:200]}); pass the "
                "policy directory of a `dlo bench` job with the same options"
            ) from exc

    def _saved_meta(self, directory: Path) -> dict[str, Any]:
        meta_path = directory / "agent.json"
        if not meta_path.is_file() or not (directory / "model.zip").is_file():
            raise BadInput(
                f"--policy {directory} holds no agent.json and model.zip; pass the policy "
                f"directory of a {self.name} job of `dlo bench` (OUT/work/.../{self.name}-sSEED/"
                "policy)"
            )
        try:
            meta = json.loads(meta_path.read_text())
        except ValueError as exc:
            raise BadInput(
                f"--policy {directory}: agent.json is not JSON; re-run the bench"
            ) from exc
        transitions = meta.get("transitions") if isinstance(meta, dict) else None
        if not isinstance(transitions, int) or isinstance(transitions, bool) or transitions < 0:
            raise BadInput(
                f"--policy {directory}: agent.json is not one `dlo bench` wrote (no count of "
                "transitions); pass the policy directory of a `dlo bench` job"
            )
        if meta.get("algorithm") != self.algorithm:
            found = meta.get("algorithm")
            raise BadInput(
                f"--policy {directory} holds a {found} policy, not {self.algorithm}; pass "
                f"--controller {str(found).lower()} or another --policy"
            )
        return meta

    def save_state(self, slot: Path, shared: Path) -> bool:
        """Between episodes: the policy (SB3's zip holds networks, optimizers and counters),
        the replay buffer's new rows as a chunk in ``shared``, and as JSON what the zip holds
        only pickled (the first observation of the next episode, the episode statistics) and
        the generators of the action space and of the env's next episodes."""
        buffer = self.model.replay_buffer
        episode_starts = getattr(self.model, "_last_episode_starts", None)
        if buffer is None or buffer.full or episode_starts is None or not episode_starts.all():
            return False  # inside an episode, or a wrapped buffer: not worth a full copy
        self.save_policy(slot)
        save_buffer_rows(buffer, Path(shared) / REPLAY_DIR)
        state = {
            "buffer_rows": int(buffer.pos),
            "last_obs": self.model._last_obs.tolist(),
            "episode_infos": list(self.model.ep_info_buffer),
            "episode_successes": list(self.model.ep_success_buffer),
            "action_space": self.model.action_space.np_random.bit_generator.state,
            # SB3 has already reset the env for the next episode: continue from that reset
            "env_generator": self.env.reset_generator_state,
            "episode_returns": list(self.env.episode_returns),
        }
        write_json_atomic(Path(slot) / "learner.json", state)
        return True

    def load_state(self, slot: Path, shared: Path) -> None:
        """Continue from :meth:`save_state` (nothing there is unpickled)."""
        slot = Path(slot)
        state = read_json(slot / "learner.json")
        self.load_policy(slot, saved=state)
        load_buffer_rows(self.model.replay_buffer, Path(shared) / REPLAY_DIR, state["buffer_rows"])
        self.model.action_space.np_random.bit_generator.state = state["action_space"]
        self.env.restore_generator(state["env_generator"], state["episode_returns"])
        monitor = self.model.get_env().envs[0]
        obs, _ = monitor.reset()  # the same reset again: its monitor and env start the episode
        if not np.array_equal(obs, self.model._last_obs[0]):
            raise RuntimeError("resumed env does not reproduce the saved episode start")


class SACAgent(SB3Agent):
    """Soft Actor-Critic (stable-baselines3) on the flat observation."""

    name = "sac"
    algorithm = "SAC"
    spec_cls = SACSpec


class TD3Agent(SB3Agent):
    """TD3 (stable-baselines3) with Gaussian exploration noise on the flat observation."""

    name = "td3"
    algorithm = "TD3"
    spec_cls = TD3Spec
