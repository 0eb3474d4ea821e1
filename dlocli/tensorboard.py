"""Live curves: scalars written as TensorBoard event files under a run directory
(``OUT/tensorboard/``) when TensorBoard is installed (``pip install dlocli[tensorboard]``);
without it, nothing is written. The CSV files stay the source of truth. Watch a run with
``tensorboard --logdir runs``."""

from __future__ import annotations

import importlib.util
from pathlib import Path
from typing import Any

TENSORBOARD_DIR = "tensorboard"


def available() -> bool:
    return importlib.util.find_spec("tensorboard") is not None


class Scalars:
    """An event-file writer for one run directory (a no-op without TensorBoard). The file is
    made with the first scalar: a run refused before it has nothing to show, and leaves none."""

    def __init__(self, run_dir: Path | None) -> None:
        self.writer: Any = None
        self.log_dir = None
        if run_dir is not None and available():
            self.log_dir = Path(run_dir) / TENSORBOARD_DIR

    def add(self, step: int, prefix: str = "", **values: float | None) -> None:
        """Write each finite value as ``prefix/name`` at ``step``; flush (others read live)."""
        if self.log_dir is None:
            return
        if self.writer is None:
            from torch.utils.tensorboard import SummaryWriter

            self.writer = SummaryWriter(log_dir=str(self.log_dir))
        for name, value in values.items():
            if value is not None:
                self.writer.add_scalar(f"{prefix}/{name}" if prefix else name, value, step)
        self.writer.flush()

    def close(self) -> None:
        if self.writer is not None:
            self.writer.close()
            self.writer = None
        self.log_dir = None
