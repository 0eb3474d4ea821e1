"""`dlo goal`: write a reachable goal shape (N,3) in metres to a .npy file."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from dlocli.cli.common import (
    JsonFlag,
    OverwriteFlag,
    SpecFile,
    build_spec,
    emit_summary,
    handle_errors,
)
from dlocli.cli.common import opt_help as h
from dlocli.errors import BadInput
from dlocli.specs import GoalSpec as S


@handle_errors
def goal(
    out: Annotated[Path | None, typer.Option(help=h(S, "out"))] = None,
    backend: Annotated[str | None, typer.Option(help=h(S, "backend.name"))] = None,
    task: Annotated[str | None, typer.Option(help=h(S, "task.name"))] = None,
    seed: Annotated[int | None, typer.Option(help=h(S, "seed"))] = None,
    spec_file: SpecFile = None,
    overwrite: OverwriteFlag = False,
    json_out: JsonFlag = False,
) -> None:
    """Move the grippers randomly from rest (seeded), let the rod settle, save its shape."""
    from dlocli.goals import make_goal, save_goal
    from dlocli.metrics import shape_error_mm
    from dlocli.registry import backends, tasks

    spec = build_spec(
        S, spec_file, {"out": out, "backend.name": backend, "task.name": task, "seed": seed}
    )
    backends.check(spec.backend.name)
    tasks.check(spec.task.name)
    if spec.out.suffix != ".npy":
        raise BadInput(f"--out {spec.out} must end in .npy (the goal format is a (N,3) .npy array)")
    if spec.out.exists() and not overwrite:
        raise BadInput(f"--out {spec.out} exists; pass --overwrite or another --out")
    shape = make_goal(spec)
    save_goal(shape, spec.out)
    rest = _rest_shape(spec)
    emit_summary(
        {
            "path": str(spec.out),
            "segments": int(shape.shape[0]),
            "seed": spec.seed,
            "distance_from_rest_mm": round(float(shape_error_mm(rest, shape)), 1),
        },
        json_out,
        "dlo goal",
    )


def _rest_shape(spec: S):
    from dlocli.env import make_backend

    backend = make_backend(spec.backend, spec.task.control_dt)
    backend.reset(spec.seed)
    shape = backend.segment_positions()
    backend.close()
    return shape
