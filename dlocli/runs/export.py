"""Export a dataset (:mod:`dlocli.data.rod`) as a Minari dataset (``dlo export --format minari``).

Offline-RL libraries read Minari datasets (``minari.load_dataset(id)``); Minari is optional
(``pip install 'dlocli[minari]'``) and imported only here, when used. Each dlocli episode of
T transitions becomes one Minari episode of T steps:

- ``observations`` (T+1, D) float32: the flat observation :class:`DLOShapeEnv` gives in each
  recorded state (:func:`episode_observations`; layout in :mod:`dlocli.env.shape_env`),
- ``actions`` (T, 6) for ``single`` or (T, 12) for ``bimanual``: the task's action that made
  the stored per-gripper commands (:meth:`dlocli.env.tasks.Task.from_grippers`),
- ``rewards`` (T,) the stored paper eq. 12 rewards; ``terminations`` all False (the task has no
  terminal state); ``truncations`` True on the last step only; ``infos`` empty.

A diverged episode (``diverged`` in the dataset) holds the steps before the diverged one; it
is exported as those steps, truncated after the last one (the task goes on, but the data
stop), or left out with ``skip_diverged``. An episode without a step (diverged at once) is
always left out. The exported episodes' source indices and which of them diverged are kept
in the Minari metadata under ``dlocli``.

The environment spec is recorded, so ``dataset.recover_environment()`` builds the data's env
(after ``import dlocli``, which registers the ids): the registered Gymnasium id of the data's
backend and task, with the task spec, seed and backend as keyword arguments of
:func:`dlocli.make_env`, and ``max_episode_steps`` the task's episode length.

Writing is atomic: the dataset is built in a hidden directory beside it in the Minari root
and renamed into place, so an existing dataset is replaced (``overwrite``) only by a complete
one, and a failed export leaves nothing behind.
"""

from __future__ import annotations

import dataclasses
import errno
import os
import shutil
import tempfile
import warnings
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np
from pydantic import ValidationError

from dlocli import __version__
from dlocli.backends.rotations import state_change
from dlocli.cancel import CancelToken
from dlocli.data import Dataset, Episode, load_dataset
from dlocli.env.shape_env import DLOShapeEnv, observation_space
from dlocli.env.tasks import make_task
from dlocli.errors import BadInput
from dlocli.events import Began, Callback, Event, ignore
from dlocli.extras import require
from dlocli.migrations import completed
from dlocli.specs import BackendSpec, EnvSpec, TaskSpec, format_validation_error

#: the Minari data format written (h5py is a dlocli dependency already)
DATA_FORMAT = "hdf5"
#: environment variable that sets Minari's datasets root
ROOT_ENV = "MINARI_DATASETS_PATH"
#: entry point recorded when the backend spec is not the named backend's default


# ----------------------------------------------------------------------------- data -> steps
def episode_observations(episode: Episode, task: TaskSpec) -> np.ndarray:
    """(T+1, D) float32: the observation :class:`DLOShapeEnv` gives in each state of
    ``episode`` — positions, quaternions, gripper poses, the goal and, with
    ``task.observe_velocity``, each segment's state change over the last step divided by the
    step (zero in the first state, right after the reset), clipped to the env's bounds."""
    states = np.concatenate([episode.positions, episode.quaternions], -1).astype(np.float64)
    steps, n = states.shape[:2]
    goal = np.broadcast_to(np.asarray(episode.goal, np.float64).reshape(1, n * 3), (steps, n * 3))
    parts = [
        states[:, :, :3].reshape(steps, -1),
        states[:, :, 3:].reshape(steps, -1),
        np.asarray(episode.grippers, np.float64).reshape(steps, -1),
        goal,
    ]
    if task.observe_velocity:
        change = np.zeros_like(states)
        change[1:] = state_change(states[:-1], states[1:])
        parts.append((change / task.control_dt).reshape(steps, -1))
    space = observation_space(n, task.observe_velocity)
    return np.clip(np.concatenate(parts, axis=1), space.low, space.high).astype(np.float32)


def episode_actions(episode: Episode, task: TaskSpec) -> np.ndarray:
    """(T, action_dim) float32: the task's actions behind the stored (T, 2, 6) commands."""
    return np.asarray(make_task(task.name).from_grippers(episode.actions), dtype=np.float32)


def check_layout(env: DLOShapeEnv, observations: np.ndarray, episode: Episode) -> None:
    """RuntimeError unless the env's own :meth:`~DLOShapeEnv.split_observation` gets the
    episode's states and goal back from ``observations`` (the layout has one definition)."""
    parts = env.split_observation(observations)
    for name in ("positions", "quaternions", "grippers"):
        stored = getattr(episode, name)
        if not np.array_equal(parts[name], np.asarray(stored, np.float32)):
            raise RuntimeError(f"exported observations disagree with the env's {name} layout")
    if not np.array_equal(parts["goal"][0], np.asarray(episode.goal, np.float32)):
        raise RuntimeError("exported observations disagree with the env's goal layout")


def observation_layout(env: DLOShapeEnv) -> dict[str, list[int]]:
    """``{part: [start, stop]}`` of the flat observation, from the env's own split."""
    dim = env.observation_space.shape[0]
    parts = env.split_observation(np.arange(dim))
    return {name: [int(idx.min()), int(idx.max()) + 1] for name, idx in parts.items()}


# ----------------------------------------------------------------------------- env spec
def dataset_env_spec(data: Dataset, source: Path) -> EnvSpec:
    """The backend, task and seed the dataset was collected with (its ``spec`` attribute),
    completed with the task fields it predates; BadInput if it has none."""
    saved = data.attrs.get("spec")
    if not isinstance(saved, dict) or not isinstance(saved.get("task", {}), dict):
        raise BadInput(
            f"dataset {source} records no env spec (attribute `spec`); export a dataset "
            "written by `dlo collect` (its run directory or dataset.h5)"
        )
    fields = {
        "backend": saved.get("backend", {}),
        "task": completed("task", saved.get("task", {})),
        "seed": saved.get("seed", 0),
    }
    try:
        spec = EnvSpec.model_validate(fields)
    except ValidationError as exc:
        raise BadInput(format_validation_error(exc, f"dataset {source} spec")) from exc
    if spec.backend.rod.n_segments != data.n_segments:
        raise BadInput(
            f"dataset {source} holds {data.n_segments} segments but its spec says "
            f"{spec.backend.rod.n_segments}; re-collect it"
        )
    return spec


def gym_env_spec(spec: EnvSpec) -> Any:
    """The ``gymnasium.envs.registration.EnvSpec`` that rebuilds ``spec``'s env: the id
    registered for its backend and task, with the task fields, seed and backend as kwargs."""
    import gymnasium as gym

    backend, task = spec.backend.name, spec.task.name
    wanted = {"backend": backend, "task": task}
    registered = [
        s
        for s in gym.registry.values()
        if s.namespace == "dlocli" and {k: s.kwargs.get(k) for k in wanted} == wanted
    ]
    if not registered:
        raise BadInput(
            f"no Gymnasium id is registered for backend {backend!r} and task {task!r}; "
            "register one with gymnasium.register (see dlocli/__init__.py)"
        )
    task_fields = spec.task.model_dump(mode="json", exclude={"name"})
    kwargs: dict[str, Any] = {"backend": backend, "task": task, "seed": spec.seed, **task_fields}
    if spec.backend != BackendSpec(name=backend):  # a rod or physics the name alone does not give
        kwargs["backend"] = spec.backend.model_dump(mode="json")  # DLOShapeEnv validates it
    return dataclasses.replace(
        registered[0],
        kwargs=kwargs,
        max_episode_steps=spec.task.episode_steps,
    )


# ----------------------------------------------------------------------------- ids and roots
def default_dataset_id(spec: EnvSpec) -> str:
    """``dlocli/<backend>-<task>-random-v0``: the datasets `dlo collect` writes hold random
    actions."""
    return f"dlocli/{spec.backend.name}-{spec.task.name}-random-v0"


def check_dataset_id(dataset_id: str) -> None:
    """BadInput unless ``dataset_id`` is a Minari id, ``(namespace/)name-vN``."""
    from minari.dataset.minari_dataset import parse_dataset_id

    try:
        parse_dataset_id(dataset_id)
    except (ValueError, TypeError) as exc:  # TypeError: Minari 0.5 on an id without -vN
        raise BadInput(
            f"--dataset-id {dataset_id!r} is not a Minari dataset id; pass one like "
            "dlocli/mujoco-single-random-v0 (namespace/name-vN)"
        ) from exc


def minari_root(root: Path | None) -> Path:
    """The Minari datasets root: ``root``, else Minari's own (``$MINARI_DATASETS_PATH``, else
    ``~/.minari/datasets``); created if missing."""
    from minari.storage import get_dataset_path

    # absolute: Minari joins a relative root onto itself (root/.../data/root/.../data)
    root = Path(root).absolute() if root is not None else Path(get_dataset_path())
    if root.exists() and not root.is_dir():
        raise BadInput(f"--out {root} is a file; pass a directory for Minari datasets")
    root.mkdir(parents=True, exist_ok=True)
    return root


@contextmanager
def _minari_root_set(root: Path) -> Iterator[None]:
    """Point Minari at ``root`` (it reads the variable on every call), then restore it."""
    old = os.environ.get(ROOT_ENV)
    os.environ[ROOT_ENV] = str(root)
    try:
        yield
    finally:
        if old is None:
            os.environ.pop(ROOT_ENV, None)
        else:
            os.environ[ROOT_ENV] = old


def _check_place(root: Path, dataset_id: str) -> None:
    """BadInput if the dataset's folder would lie inside another dataset's folder, below a
    file, or outside ``root`` (through a linked namespace folder)."""
    folder = root
    for part in Path(dataset_id).parts[:-1]:
        folder = folder / part
        if not os.path.lexists(folder):
            break
        if not folder.is_dir():
            raise BadInput(
                f"--dataset-id {dataset_id}: {folder} is a file, not a namespace folder; pass "
                "another --dataset-id"
            )
        if (folder / "data").is_dir():
            raise BadInput(
                f"--dataset-id {dataset_id} would be written inside the Minari dataset "
                f"{folder.relative_to(root)} ({folder}); pass an id outside it, like "
                f"{folder.relative_to(root).parent / Path(dataset_id).name}"
            )
    if not (root / dataset_id).resolve().is_relative_to(root.resolve()):
        raise BadInput(
            f"--dataset-id {dataset_id} leads out of {root} through a link; pass another "
            "--dataset-id"
        )


def _check_target(target: Path, dataset_id: str, root: Path, overwrite: bool) -> None:
    _check_place(root, dataset_id)
    if not target.exists():
        return
    if not (target / "data").is_dir():
        raise BadInput(
            f"{target} exists and is not a Minari dataset (a namespace?); pass another --dataset-id"
        )
    if not overwrite:
        raise BadInput(
            f"Minari dataset {dataset_id} already exists in {root}; pass --overwrite or "
            "another --dataset-id"
        )


def _add_namespaces(staged_root: Path, root: Path, dataset_id: str) -> None:
    """Copy the namespace files Minari wrote in the staging root that ``root`` lacks."""
    from minari.namespace import NAMESPACE_METADATA_FILENAME

    parent = Path(dataset_id).parent
    for level in [*reversed(parent.parents), parent][1:]:  # "a", "a/b", ... (not ".")
        made, wanted = staged_root / level / NAMESPACE_METADATA_FILENAME, root / level
        wanted.mkdir(exist_ok=True)
        if made.is_file() and not (wanted / NAMESPACE_METADATA_FILENAME).exists():
            shutil.copyfile(made, wanted / NAMESPACE_METADATA_FILENAME)


def _move_into_place(staged: Path, target: Path, trash: Path) -> None:
    """Rename ``staged`` to ``target``; an existing ``target`` is first renamed to ``trash``
    (and put back if the second rename fails)."""
    replaced = target.exists()
    if replaced:
        os.rename(target, trash)
    try:
        os.rename(staged, target)
    except BaseException:  # Ctrl-C included: the old dataset is never left in the trash
        if replaced:
            os.rename(trash, target)
        raise


# ----------------------------------------------------------------------------- export
def _buffers(
    data: Dataset,
    task: TaskSpec,
    env: DLOShapeEnv,
    skip_diverged: bool,
    progress: Callback,
    cancel: CancelToken,
) -> tuple[list[Any], list[int]]:
    """Minari episode buffers of the episodes exported, and their indices in ``data``; each
    episode of ``data`` reported as it is read (``cancel`` checked before each)."""
    from minari.data_collector import EpisodeBuffer

    buffers, kept = [], []
    total = data.n_episodes
    progress(Began("episode", 0, total))
    for e in range(total):
        cancel.raise_if_cancelled()
        episode = data.episode(e)
        if len(episode) == 0 or (skip_diverged and episode.diverged):
            progress(Event("episode", e + 1, total, {"steps": len(episode), "exported": False}))
            continue
        observations = episode_observations(episode, task)
        check_layout(env, observations, episode)
        truncations = np.zeros(len(episode), dtype=bool)
        truncations[-1] = True
        buffers.append(
            EpisodeBuffer(
                observations=observations,
                actions=episode_actions(episode, task),
                rewards=np.asarray(episode.rewards, dtype=np.float64),
                terminations=np.zeros(len(episode), dtype=bool),
                truncations=truncations,
                infos={},
            )
        )
        kept.append(e)
        progress(Event("episode", e + 1, total, {"steps": len(episode), "exported": True}))
    return buffers, kept


def export_minari(
    source: Path,
    dataset_id: str | None = None,
    root: Path | None = None,
    overwrite: bool = False,
    skip_diverged: bool = False,
    author: str | None = None,
    author_email: str | None = None,
    code_permalink: str | None = None,
    progress: Callback | None = None,
    cancel: CancelToken | None = None,
) -> dict[str, Any]:
    """Write the dataset at ``source`` (a run directory or dataset file) as the Minari dataset
    ``dataset_id`` (default :func:`default_dataset_id`) in ``root``; return a summary.

    An existing dataset of that id is refused unless ``overwrite``. ``progress`` gets a
    Began of the dataset's episodes (unit "episode"), then an Event as each is read
    (``values``: its ``steps`` and whether it is ``exported``); ``cancel`` stops it before
    each episode and before writing, with nothing written (an existing dataset of that id
    left as it was). See the module docstring for the mapping.
    """
    progress, cancel = progress or ignore, cancel or CancelToken()
    require("minari", "--format minari")
    import gymnasium as gym
    import minari

    source = Path(source)
    data = load_dataset(source)
    spec = dataset_env_spec(data, source)
    dataset_id = dataset_id or default_dataset_id(spec)
    check_dataset_id(dataset_id)
    root = minari_root(root)
    target = root / dataset_id
    _check_target(target, dataset_id, root, overwrite)
    env_spec = gym_env_spec(spec)
    env = gym.make(env_spec)
    staging = Path(tempfile.mkdtemp(prefix=".dlo-export-", dir=root))
    try:
        buffers, kept = _buffers(data, spec.task, env.unwrapped, skip_diverged, progress, cancel)
        cancel.raise_if_cancelled()  # the last episode read, before anything is written
        if not buffers:
            raise BadInput(
                f"dataset {source} has no episode to export (all diverged or empty); "
                "re-collect it" + ("" if not skip_diverged else " or drop --skip-diverged")
            )
        _check_free_space(root, buffers)
        metadata = {
            "source": str(source.resolve()),
            "spec": spec.model_dump(mode="json"),
            "episodes": kept,
            "diverged_episodes": [e for e in kept if data.diverged[e]],
            "observation_layout": observation_layout(env.unwrapped),
            "dlocli_version": __version__,
        }
        with _minari_root_set(staging), warnings.catch_warnings():
            warnings.simplefilter("ignore")  # Minari warns about every optional field left out
            made = minari.create_dataset_from_buffers(
                dataset_id,
                buffers,
                env=env,
                algorithm_name="random",
                author=author,
                author_email=author_email,
                code_permalink=code_permalink,
                description=_description(spec, source),
                data_format=DATA_FORMAT,
                requirements=[f"dlocli=={__version__}"],
            )
            made.storage.update_metadata({"dlocli": metadata})
        _add_namespaces(staging, root, dataset_id)
        _move_into_place(staging / dataset_id, target, staging / "replaced")
    finally:
        env.close()
        shutil.rmtree(staging, ignore_errors=True)
    return {
        "dataset_id": dataset_id,
        "root": str(root),
        "path": str(target),
        "episodes": len(kept),
        "steps": int(sum(data.episode_lengths[e] for e in kept)),
        "diverged_episodes": len(metadata["diverged_episodes"]),
        "skipped_episodes": data.n_episodes - len(kept),
        "env_id": env_spec.id,
        "observation_dim": int(env.observation_space.shape[0]),
        "action_dim": int(env.action_space.shape[0]),
        "source": str(source),
    }


def _check_free_space(root: Path, buffers: list[Any]) -> None:
    """OSError (ENOSPC) before any writing when ``root``'s file system cannot hold the
    export: Minari writes through HDF5, which crashes the process on a full disk."""
    fields = ("observations", "actions", "rewards", "terminations", "truncations")
    arrays = sum(np.asarray(getattr(b, f)).nbytes for b in buffers for f in fields)
    need = int(arrays * 1.25) + 2**20  # HDF5's own structures, Minari's metadata
    free = shutil.disk_usage(root).free
    if free < need:
        raise OSError(
            errno.ENOSPC,
            f"No space left on device (the export needs about {need / 1e6:.0f} MB, "
            f"{free / 1e6:.0f} MB are free)",
            str(root),
        )


def _description(spec: EnvSpec, source: Path) -> str:
    layout = "positions, quaternions, grippers, goal" + (
        ", velocities" if spec.task.observe_velocity else ""
    )
    return (
        f"dlocli {spec.backend.name} {spec.task.name}-task random-action data from {source}: "
        f"observations are DLOShapeEnv's ({layout}; metadata dlocli.observation_layout), "
        "actions in [-1, 1], reward paper eq. 12; episodes end by time (truncated), a diverged "
        "one at its last finite step. Recover the env after `import dlocli`."
    )
