"""Marker datasets: recorded marker positions, some markers held (the input), the rest free.

Stored in the dataset file format (``dataset.h5``, ``format = dlocli-dataset``) version 2,
``form = "markers"`` (rod datasets are ``form = "rod"``; version 1 files are rod datasets).
E episodes, episode e has T_e transitions and T_e + 1 frames; S = sum(T_e + 1); V markers:

=================  ==============  ==================================================
dataset            shape, dtype    meaning
=================  ==============  ==================================================
episode_lengths    (E,) int64      T_e, transitions per episode
positions          (S, V, 3) f32   marker positions, metres, world frame, z up
held               (V,) bool       markers a gripper holds: their recorded motion is
                                   the input at every step
split              (E,) uint8      0 train, 1 eval (the source's own split)
names              (E,) str        the source file of each episode
=================  ==============  ==================================================

Attributes: ``rate_hz`` (frames per second), ``source`` (where it was imported from).
"""

from __future__ import annotations

import io
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, ClassVar

import numpy as np

from dlocli.data.checks import check_fields
from dlocli.data.format import FORMAT_VERSION, MARKERS, write_header
from dlocli.errors import BadInput
from dlocli.io import write_bytes_atomic

#: frames per second of a recording that does not say
DEFAULT_RATE_HZ = 100.0
MAX_RATE_HZ = 100_000
SPLIT_CODES = {"train": 0, "eval": 1}
ARRAYS = ("episode_lengths", "positions", "held", "split", "names")


@dataclass
class MarkerDataset:
    #: the ``form`` of its file (:mod:`dlocli.data.format`)
    form: ClassVar[str] = MARKERS

    episode_lengths: np.ndarray
    positions: np.ndarray
    held: np.ndarray
    split: np.ndarray
    names: np.ndarray
    attrs: dict[str, Any] = field(default_factory=dict)
    path: Path | None = None  # the file it was read from, named in errors

    @classmethod
    def from_trajectories(
        cls,
        trajectories: dict[str, list[tuple[str, np.ndarray]]],
        held: np.ndarray,
        attrs: dict[str, Any] | None = None,
    ) -> MarkerDataset:
        """From ``{split: [(name, (frames, V, 3)), ...]}`` (see :func:`deform.read_folder`)."""
        rows = [(s, n, a) for s, items in trajectories.items() for n, a in items]
        if not rows:
            raise BadInput("no trajectories to store")
        return cls(
            episode_lengths=np.array([len(a) - 1 for _, _, a in rows], dtype=np.int64),
            positions=np.concatenate([a for _, _, a in rows]).astype(np.float32),
            held=np.asarray(held, dtype=bool),
            split=np.array([SPLIT_CODES[s] for s, _, _ in rows], dtype=np.uint8),
            names=np.array([n for _, n, _ in rows], dtype=object),
            attrs=dict(attrs or {}),
        )

    @property
    def n_markers(self) -> int:
        return int(self.positions.shape[1])

    n_segments = n_markers  # the name the rod datasets' readers use

    @property
    def n_episodes(self) -> int:
        return len(self.episode_lengths)

    @property
    def n_transitions(self) -> int:
        return int(self.episode_lengths.sum())

    @property
    def rate_hz(self) -> float:
        return float(self.attrs.get("rate_hz", DEFAULT_RATE_HZ))

    @property
    def control_dt(self) -> float:
        """The period (s) between frames: a model trained on them predicts one such step."""
        return 1.0 / self.rate_hz

    def episodes(self, split: str | None = None) -> list[np.ndarray]:
        """Each episode's frames (T_e + 1, V, 3), of one split (None: all)."""
        ends = np.cumsum(self.episode_lengths + 1)
        starts = ends - (self.episode_lengths + 1)
        keep = np.ones(self.n_episodes, bool) if split is None else self.split == SPLIT_CODES[split]
        return [self.positions[a:b] for a, b, k in zip(starts, ends, keep, strict=True) if k]

    def require_split(self, split: str) -> None:
        """BadInput naming the file unless ``split`` holds an episode."""
        if not (self.split == SPLIT_CODES[split]).any():
            raise BadInput(
                f"marker dataset {self.path}: split holds no {split} episodes (code "
                f"{SPLIT_CODES[split]}); import a cable folder that holds {split}/ recordings"
            )

    def episode_names(self, split: str | None = None) -> list[str]:
        keep = np.ones(self.n_episodes, bool) if split is None else self.split == SPLIT_CODES[split]
        return [str(n) for n, k in zip(self.names, keep, strict=True) if k]

    def save(self, path: Path) -> Path:
        """Write atomically (temp file, then rename)."""
        import h5py

        image = io.BytesIO()
        with h5py.File(image, "w") as f:
            write_header(f, self.form, self.n_markers, self.attrs)
            for name in ARRAYS[:-1]:
                f.create_dataset(name, data=getattr(self, name))
            f.create_dataset("names", data=self.names.astype(object), dtype=h5py.string_dtype())
        write_bytes_atomic(Path(path), image.getbuffer())
        return Path(path)


def read_marker_arrays(f: Any, path: Path, attrs: dict[str, Any]) -> MarkerDataset:
    """A marker dataset from an open HDF5 file (called by :func:`dlocli.data.load_dataset`)."""
    missing = [n for n in ARRAYS if n not in f]
    if missing:
        raise BadInput(f"marker dataset {path} lacks {', '.join(missing)}; re-import it")
    arrays = {n: f[n][()] for n in ARRAYS}
    arrays["names"] = np.array(
        [n.decode() if isinstance(n, bytes) else str(n) for n in arrays["names"]], dtype=object
    )
    data = MarkerDataset(**arrays, attrs=attrs, path=path)
    _check_held(data.held, path)
    _check(data, path)

    check_fields(arrays, attrs, path, FORMAT_VERSION)
    _check_split(data.split, path)
    _check_rate(attrs, path)
    data.require_split("train")
    return data


def _check(data: MarkerDataset, path: Path) -> None:
    """BadInput unless shapes agree and positions are finite."""
    lengths, pos = data.episode_lengths, data.positions
    if pos.dtype.kind not in "fiu":
        raise BadInput(
            f"marker dataset {path}: positions hold {pos.dtype}, not numbers; re-import it"
        )
    ok = (
        lengths.ndim == 1 and len(lengths) > 0 and bool((lengths >= 2).all())
        and pos.ndim == 3 and pos.shape[2] == 3 and pos.shape[0] == int((lengths + 1).sum())
        and data.held.shape == (pos.shape[1],) and data.held.any() and not data.held.all()
        and data.split.shape == lengths.shape and data.names.shape == lengths.shape
    )  # fmt: skip
    if not ok:
        raise BadInput(f"marker dataset {path} has inconsistent array shapes; re-import it")
    if not np.isfinite(pos).all():
        raise BadInput(f"marker dataset {path} contains NaN or inf positions; re-import it")


def _check_held(held: np.ndarray, path: Path) -> None:
    """A boolean mask with held markers in both halves (a gripper at each end: the
    straight-line reference and the models' inputs assume it)."""
    if held.dtype != bool:
        raise BadInput(
            f"marker dataset {path}: held holds {held.dtype}, not a boolean mask (one flag per "
            "marker); re-import it"
        )
    half = len(held) // 2
    if not (held[:half].any() and held[half:].any()):
        raise BadInput(
            f"marker dataset {path}: held marks markers {np.flatnonzero(held).tolist()[:8]}, "
            "not some at each end of the cable; re-import it"
        )


def _check_split(split: np.ndarray, path: Path) -> None:
    codes = sorted(SPLIT_CODES.values())
    if split.dtype.kind not in "iu" or not np.isin(split, codes).all():
        shown = split[~np.isin(split, codes)][:1] if split.dtype.kind in "fiu" else split.dtype
        raise BadInput(
            f"marker dataset {path}: split holds {str(shown)[:40]}, not only the codes "
            f"{codes} (0 train, 1 eval); re-import it"
        )


def _check_rate(attrs: dict[str, Any], path: Path) -> None:
    rate = attrs.get("rate_hz", DEFAULT_RATE_HZ)
    number = isinstance(rate, (int, float)) and not isinstance(rate, bool)
    if not (number and 0 < rate <= MAX_RATE_HZ):  # False for NaN too
        raise BadInput(
            f"marker dataset {path}: rate_hz is {str(rate)[:40]}, not frames per second in "
            f"(0, {MAX_RATE_HZ}]; re-import it with --rate-hz"
        )
