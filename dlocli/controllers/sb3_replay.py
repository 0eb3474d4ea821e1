"""An SB3 replay buffer saved in chunks (checkpoints of the SAC and TD3 agents): each
checkpoint writes only the rows added since the last one, as ``.npz`` arrays (nothing
pickled), and a resumed agent refills a fresh buffer from them."""

from __future__ import annotations

import io
from pathlib import Path
from typing import Any

import numpy as np

from dlocli.io import write_bytes_atomic

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
