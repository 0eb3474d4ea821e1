"""The checks every run makes before it starts or resumes, in one place."""

from __future__ import annotations

import importlib.util
from pathlib import Path
from typing import Any

from dlocli.errors import BadInput
from dlocli.io import check_writable
from dlocli.registry import backends, models, tasks

#: what `--video` may write
VIDEO_SUFFIXES = (".gif", ".mp4")


def check_registered(spec: Any) -> None:
    """UnknownName, listing the valid names, if ``spec`` names a backend, task or model that
    is not registered (a spec without a model is checked for the others)."""
    backends.check(spec.backend.name)
    tasks.check(spec.task.name)
    model = getattr(spec, "model", None)
    if model is not None:
        models.check(model.name)


def check_video_path(path: Path | None, overwrite: bool) -> None:
    """BadInput unless ``path`` is None, a .gif, or a .mp4 with an mp4 writer installed, and
    new unless ``overwrite``."""
    if path is None:
        return
    if path.suffix not in VIDEO_SUFFIXES:
        raise BadInput(f"--video {path} must end in .gif or .mp4")
    if path.suffix == ".mp4" and importlib.util.find_spec("imageio_ffmpeg") is None:
        raise BadInput(
            f"--video {path}: writing .mp4 needs `pip install imageio-ffmpeg`; or use a .gif"
        )
    check_writable(path, "--video", overwrite)


def check_apart_from_run_dir(path: Path | None, flag: str, out: Path) -> None:
    """BadInput if the file ``path`` is the run directory ``out`` or holds it: the run would
    make that directory first and fail only after its last step, when the file is written."""
    if path is None:
        return
    file, run_dir = Path(path).resolve(), Path(out).resolve()
    if file == run_dir or file in run_dir.parents:
        raise BadInput(
            f"{flag} {path} is where --out {out} makes the run directory; "
            f"pass another {flag} path, e.g. {Path(out) / Path(path).name}"
        )
