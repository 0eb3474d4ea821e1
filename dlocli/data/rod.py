"""Trajectory datasets: the documented HDF5 format every command reads and writes.

File ``dataset.h5`` (format ``dlocli-dataset`` version 1). E episodes, episode e has T_e
transitions and T_e + 1 states; S = sum(T_e + 1), M = sum(T_e); N segments:

=================  ==============  ==================================================
dataset            shape, dtype    meaning
=================  ==============  ==================================================
episode_lengths    (E,) int64      T_e, transitions per episode
positions          (S, N, 3) f32   segment centres, metres, world frame
quaternions        (S, N, 4) f32   segment orientations, unit (w, x, y, z)
grippers           (S, 2, 7) f32   gripper poses (x, y, z, qw, qx, qy, qz), left, right
actions            (M, 2, 6) f32   per-gripper commands in [-1, 1] (linear, angular);
                                   a static gripper's row is zero
rewards            (M,) f32        paper eq. 12 reward of each transition
goals              (E, N, 3) f32   the episode's goal shape
diverged           (E,) bool       the episode ended because the physics diverged
                                   (the diverged step itself is never stored)
markers            (S, M, 3) f32   optional (markers observation): the tracker's report
                                   of M markers, metres; a missing one at its last
                                   seen position
visible            (S, M) bool     optional, with markers: which markers were seen
=================  ==============  ==================================================

Attributes: ``format``, ``format_version``, ``n_segments``, ``spec`` (JSON of the resolved
run spec), ``rod`` (JSON material), ``versions`` (JSON), ``max_linear_velocity``,
``max_angular_velocity`` (what action 1 means, m/s and rad/s).

Read it with :func:`dlocli.data.load_dataset`; the state of a segment used by the models is
``concat(position, quaternion)`` (7 numbers), see :meth:`Dataset.transitions`.
"""

from __future__ import annotations

import io
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, ClassVar

import numpy as np

from dlocli.data.checks import check_fields
from dlocli.data.format import FORMAT_VERSION, ROD, write_header
from dlocli.errors import BadInput
from dlocli.io import write_bytes_atomic

STATE_ARRAYS = ("positions", "quaternions", "grippers")
EPISODE_ARRAYS = ("actions", "rewards")
#: what a markers observation adds per state (present in all episodes or in none)
OBSERVED_ARRAYS = ("markers", "visible")


@dataclass
class Episode:
    """One trajectory: T+1 states and T actions."""

    positions: np.ndarray  # (T+1, N, 3)
    quaternions: np.ndarray  # (T+1, N, 4)
    grippers: np.ndarray  # (T+1, 2, 7)
    actions: np.ndarray  # (T, 2, 6)
    rewards: np.ndarray  # (T,)
    goal: np.ndarray  # (N, 3)
    diverged: bool = False
    markers: np.ndarray | None = None  # (T+1, M, 3) the tracker's report
    visible: np.ndarray | None = None  # (T+1, M) which markers it saw

    def __len__(self) -> int:
        return len(self.actions)


@dataclass
class Dataset:
    """Episodes held in memory as concatenated arrays (see the module docstring)."""

    #: the ``form`` of its file (:mod:`dlocli.data.format`)
    form: ClassVar[str] = ROD

    episode_lengths: np.ndarray
    positions: np.ndarray
    quaternions: np.ndarray
    grippers: np.ndarray
    actions: np.ndarray
    rewards: np.ndarray
    goals: np.ndarray
    diverged: np.ndarray
    attrs: dict[str, Any] = field(default_factory=dict)
    markers: np.ndarray | None = None
    visible: np.ndarray | None = None

    # ------------------------------------------------------------------ building
    @classmethod
    def from_episodes(cls, episodes: list[Episode], attrs: dict[str, Any] | None = None) -> Dataset:
        if not episodes:
            raise BadInput("no episodes to store")

        def cat(name: str, dtype: type = np.float32) -> np.ndarray:
            return np.concatenate([np.asarray(getattr(e, name), dtype=dtype) for e in episodes])

        return cls(
            episode_lengths=np.array([len(e) for e in episodes], dtype=np.int64),
            positions=cat("positions"),
            quaternions=cat("quaternions"),
            grippers=cat("grippers"),
            actions=cat("actions"),
            rewards=cat("rewards"),
            goals=np.stack([np.asarray(e.goal, dtype=np.float32) for e in episodes]),
            diverged=np.array([e.diverged for e in episodes], dtype=bool),
            attrs=dict(attrs or {}),
            **_observed(episodes),
        )

    def concat(self, *others: Dataset) -> Dataset:
        """A new dataset with ``others``' episodes appended, in one copy (attrs of ``self``
        kept)."""
        for other in others:
            if other.n_segments != self.n_segments:
                raise BadInput(
                    f"cannot join datasets of {self.n_segments} and {other.n_segments} segments"
                )
        arrays = {
            name: np.concatenate([getattr(d, name) for d in (self, *others)])
            for name in ("episode_lengths", *STATE_ARRAYS, *EPISODE_ARRAYS, "goals", "diverged")
        }
        return Dataset(**arrays, attrs=dict(self.attrs), **_observed((self, *others)))

    # ------------------------------------------------------------------ views
    @property
    def n_segments(self) -> int:
        return int(self.positions.shape[1])

    @property
    def n_episodes(self) -> int:
        return int(len(self.episode_lengths))

    @property
    def n_transitions(self) -> int:
        return int(self.episode_lengths.sum())

    @property
    def control_dt(self) -> float | None:
        """The control period (s) the data were collected at, from the run spec it holds;
        None where it holds none."""
        spec = self.attrs.get("spec")
        task = spec.get("task") if isinstance(spec, dict) else None
        dt = task.get("control_dt") if isinstance(task, dict) else None
        return float(dt) if isinstance(dt, (int, float)) and dt > 0 else None

    def state_offsets(self) -> np.ndarray:
        """Index of each episode's first state in the state arrays, (E,)."""
        return np.concatenate([[0], np.cumsum(self.episode_lengths + 1)[:-1]]).astype(np.int64)

    def action_offsets(self) -> np.ndarray:
        """Index of each episode's first action in the action arrays, (E,)."""
        return np.concatenate([[0], np.cumsum(self.episode_lengths)[:-1]]).astype(np.int64)

    def states(self) -> np.ndarray:
        """(S, N, 7) segment states: position then quaternion."""
        return np.concatenate([self.positions, self.quaternions], axis=-1)

    def transition_index(
        self, episodes: np.ndarray | None = None, skip_first: bool = False
    ) -> tuple[np.ndarray, np.ndarray]:
        """(state index of s_t, action index of a_t) for every transition of ``episodes``;
        with ``skip_first``, those with t >= 1 only (the ones whose previous state is known)."""
        episodes = np.arange(self.n_episodes) if episodes is None else np.asarray(episodes)
        s_off, a_off = self.state_offsets(), self.action_offsets()
        t0 = int(skip_first)
        s_idx = [s_off[e] + np.arange(t0, self.episode_lengths[e]) for e in episodes]
        a_idx = [a_off[e] + np.arange(t0, self.episode_lengths[e]) for e in episodes]
        if not s_idx:
            return np.zeros(0, np.int64), np.zeros(0, np.int64)
        return np.concatenate(s_idx), np.concatenate(a_idx)

    def transitions(
        self, episodes: np.ndarray | None = None, skip_first: bool = False
    ) -> dict[str, np.ndarray]:
        """Arrays ``state`` (M,N,7), ``action`` (M,2,6), ``next_state`` (M,N,7), ``reward``,
        and ``previous_state`` (M,N,7), the state one step before s_t: s_{t-1}, or s_0 itself
        for t = 0 (an episode starts after the reset's random motion, so its s_{-1} is not
        recorded; ``skip_first`` leaves those transitions out)."""
        s_idx, a_idx = self.transition_index(episodes, skip_first)
        states = self.states()
        first = np.isin(s_idx, self.state_offsets())
        return {
            "previous_state": states[np.where(first, s_idx, s_idx - 1)],
            "state": states[s_idx],
            "action": self.actions[a_idx],
            "next_state": states[s_idx + 1],
            "reward": self.rewards[a_idx],
        }

    def episode(self, e: int) -> Episode:
        s0, a0 = self.state_offsets()[e], self.action_offsets()[e]
        t = int(self.episode_lengths[e])
        return Episode(
            positions=self.positions[s0 : s0 + t + 1],
            quaternions=self.quaternions[s0 : s0 + t + 1],
            grippers=self.grippers[s0 : s0 + t + 1],
            actions=self.actions[a0 : a0 + t],
            rewards=self.rewards[a0 : a0 + t],
            goal=self.goals[e],
            diverged=bool(self.diverged[e]),
            markers=None if self.markers is None else self.markers[s0 : s0 + t + 1],
            visible=None if self.visible is None else self.visible[s0 : s0 + t + 1],
        )

    def subset(self, episodes: np.ndarray) -> Dataset:
        return Dataset.from_episodes([self.episode(int(e)) for e in episodes], self.attrs)

    # ------------------------------------------------------------------ I/O
    def save(self, path: Path) -> Path:
        """Write atomically (temp file, then rename): a crash leaves the old file or none."""
        import h5py

        image = io.BytesIO()  # HDF5 writes into memory; the disk sees one Python write
        with h5py.File(image, "w") as f:
            write_header(f, self.form, self.n_segments, self.attrs)
            for name in ("episode_lengths", *STATE_ARRAYS, *EPISODE_ARRAYS, "goals", "diverged"):
                f.create_dataset(name, data=getattr(self, name))
            for name in OBSERVED_ARRAYS:
                if getattr(self, name) is not None:
                    f.create_dataset(name, data=getattr(self, name))
        path = Path(path)
        write_bytes_atomic(path, image.getbuffer())  # a view: no second copy
        return path


def read_rod_arrays(f: Any, path: Path, attrs: dict[str, Any]) -> Dataset:
    """A rod dataset from an open HDF5 file (called by :func:`dlocli.data.load_dataset`);
    BadInput on the first thing that breaks the format."""
    names = ("episode_lengths", *STATE_ARRAYS, *EPISODE_ARRAYS, "goals", "diverged")
    missing = [n for n in names if n not in f]
    if missing:
        raise BadInput(f"dataset {path} lacks {', '.join(missing)}; re-collect it")
    arrays = {n: f[n][()] for n in names}
    arrays |= {n: f[n][()] for n in OBSERVED_ARRAYS if n in f}
    data = Dataset(**arrays, attrs=attrs)
    _check_consistent(data, path)
    check_fields(arrays, attrs, path, FORMAT_VERSION)
    return data


def _observed(datasets: Any, cat: Any = None) -> dict[str, np.ndarray | None]:
    """The markers observation's arrays of ``datasets`` (episodes or datasets) joined, or
    None where any lacks them (BadInput if their marker counts differ)."""
    if any(d.markers is None for d in datasets):
        return {}
    if len({d.markers.shape[1] for d in datasets}) > 1:
        raise BadInput("cannot join episodes observed through different marker counts")
    return {
        "markers": np.concatenate([np.asarray(d.markers, np.float32) for d in datasets]),
        "visible": np.concatenate([np.asarray(d.visible, bool) for d in datasets]),
    }


def _check_consistent(data: Dataset, path: Path) -> None:
    """BadInput unless every array holds finite numbers and the shapes agree."""
    for name in ("episode_lengths", *STATE_ARRAYS, *EPISODE_ARRAYS, "goals"):
        array = getattr(data, name)
        if array.dtype.kind not in "fiu":
            raise BadInput(
                f"dataset {path}: {name} holds {array.dtype}, not numbers; re-collect it"
            )
        if not np.isfinite(array).all():
            raise BadInput(f"dataset {path}: {name} contains NaN or inf; re-collect it")
    n_states = int((data.episode_lengths + 1).sum())
    ok = (
        data.positions.shape[0] == n_states
        and data.quaternions.shape[0] == n_states
        and data.grippers.shape[0] == n_states
        and data.actions.shape[0] == data.n_transitions
        and data.positions.shape[2:] == (3,)
        and data.quaternions.shape[2:] == (4,)
        and data.actions.shape[1:] == (2, 6)
        and data.goals.shape == (data.n_episodes, data.n_segments, 3)
    )
    if not ok:
        raise BadInput(f"dataset {path} has inconsistent array shapes; re-collect it")
