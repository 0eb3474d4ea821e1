"""SAC and TD3 benchmark agents: stable-baselines3 behind the :class:`LearningAgent` contract.

One adapter, :class:`SB3Agent`, drives any SB3 off-policy algorithm on the env's flat Box
observation (rod positions, quaternions, gripper poses and the goal, so a policy trained on a
fixed goal can be evaluated on random goals, paper Fig. 6). The reward is the env's paper
eq. 12, already clipped to [-1.5, 0]. ``learn(n)`` consumes exactly ``n`` env transitions of
the training env; the episode in progress carries over between calls.

The candidates came from two documented sources: stable-baselines3's constructor defaults
(SAC: Haarnoja et al. 2018; TD3: Fujimoto et al. 2018, with no action noise) and
rl-baselines3-zoo's tuned values for the PyBullet locomotion envs (``hyperparams/sac.yml`` and
``hyperparams/td3.yml``, ``HalfCheetahBulletEnv-v0``: continuous actions in [-1, 1] and a
dense reward, the nearest tuned match to our task). ``benchmarks/rl_sweep.py`` compared them
and one-knob variants on this task against doing nothing (the README has its numbers), and
the defaults are its winners:

- SAC: the zoo's values. ``gamma`` 0.98, ``net_arch`` [400, 300], ``learning_rate`` 7.3e-4,
  ``tau`` 0.02, ``train_freq`` = ``gradient_steps`` = 8, ``buffer_size`` 300k, gSDE
  exploration with ``log_std_init`` -3, and ``learning_starts`` 1000 instead of the zoo's
  10000 (half of a 20k budget; five random episodes from five starts).
- TD3: SB3's defaults. The zoo's once-per-episode updates with action noise 0.1 drove the
  policy to the action bounds on this task whatever the discount.

``train_freq`` also takes "episode" (the zoo's ``[1, "episode"]``) as the task's episode
length in steps: ``learn(n)`` must stop after exactly ``n`` transitions, which SB3 guarantees
only for step counts. The buffers hold the whole budget, so nothing is ever discarded.

Seeding: SB3's ``seed=`` seeds Python's, NumPy's and torch's global generators, the action
space and the env's first reset, so the same seed on CPU gives the same agent. Torch's thread
count is the caller's choice; on a busy 2-core CPU one thread learns several times faster.
"""

from __future__ import annotations

import io
import json
import warnings
import zipfile
from collections import deque
from pathlib import Path
from pickle import UnpicklingError  # what torch's weights_only loader raises
from typing import Annotated, Any, ClassVar, Literal, TypeVar

import numpy as np
from pydantic import BeforeValidator, Field, ValidationError

from dlocli.controllers.base import LearningAgent
from dlocli.errors import BadInput
from dlocli.io import read_json, write_bytes_atomic, write_json_atomic
from dlocli.limits import MAX_COUNT, MAX_TRANSITIONS, refuse_unless_fits
from dlocli.specs import Device, Spec, format_validation_error, new_default

SpecT = TypeVar("SpecT", bound=Spec)


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


def resolve_agent_spec(cls: type[SpecT], spec: Spec | None, fields: dict[str, Any]) -> SpecT:
    """The agent's spec from a spec instance and/or keyword fields (fields override)."""
    data = spec.model_dump() if spec is not None else {}
    try:
        return cls.model_validate({**data, **fields})
    except ValidationError as exc:
        raise BadInput(format_validation_error(exc, f"{cls.__name__} options")) from exc


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
    """Soft Actor-Critic with automatic entropy tuning (zoo's Bullet values, see module doc)."""

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
        from dlocli.tensorboard import available

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
        from dlocli.io import atomic_path

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


#: where a replay buffer's chunks live in a checkpoint's shared directory
REPLAY_DIR = "replay"
#: the rows of an SB3 replay buffer (``next_observations`` is absent when memory is optimised)
BUFFER_FIELDS = ("observations", "next_observations", "actions", "rewards", "dones", "timeouts")


def _chunks(directory: Path) -> list[tuple[int, int, Path]]:
    """(first row, end row, file) of every chunk in ``directory``, by first row."""
    found = []
    for path in directory.glob("rows-*.npz"):
        first, _, end = path.stem[len("rows-") :].partition("-")
        if first.isdigit() and end.isdigit():
            found.append((int(first), int(end), path))
    return sorted(found)


def save_buffer_rows(buffer: Any, directory: Path) -> None:
    """Write the rows of ``buffer`` that no chunk in ``directory`` holds yet as one chunk."""
    directory.mkdir(parents=True, exist_ok=True)
    written = max((end for first, end, _ in _chunks(directory) if end <= buffer.pos), default=0)
    if written >= buffer.pos:
        return
    rows = slice(written, buffer.pos)
    arrays = {name: getattr(buffer, name)[rows] for name in BUFFER_FIELDS if hasattr(buffer, name)}
    image = io.BytesIO()
    np.savez(image, **arrays)
    write_bytes_atomic(directory / f"rows-{written}-{buffer.pos}.npz", image.getbuffer())


def load_buffer_rows(buffer: Any, directory: Path, rows: int) -> None:
    """Fill a fresh ``buffer`` with its first ``rows`` rows from the chunks in ``directory``."""
    filled = 0
    for first, end, path in _chunks(directory):
        if first != filled or end > rows:
            continue  # a chunk of a later, unfinished checkpoint
        with np.load(path) as chunk:
            for name in chunk.files:
                getattr(buffer, name)[first:end] = chunk[name]
        filled = end
    if filled != rows:
        raise RuntimeError(f"replay buffer chunks in {directory} hold {filled} of {rows} rows")
    for _, end, path in _chunks(directory):
        if end > rows:
            path.unlink()  # written again from here on
    buffer.pos, buffer.full = rows, False


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
