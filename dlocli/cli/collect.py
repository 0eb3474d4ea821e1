"""`dlo collect --random`: random-action trajectories into an HDF5 dataset."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

from dlocli.cli.common import (
    JsonFlag,
    OverwriteFlag,
    SpecFile,
    build_spec,
    emit_summary,
    handle_errors,
)
from dlocli.cli.common import opt_help as h
from dlocli.specs import CollectSpec as S


@handle_errors
def collect(
    random: Annotated[
        bool,
        typer.Option(
            "--random",
            help="Uniform random actions (the only policy here; use `dlo online` for MPC data).",
        ),
    ] = True,
    out: Annotated[Path | None, typer.Option(help=h(S, "out"))] = None,
    backend: Annotated[str | None, typer.Option(help=h(S, "backend.name"))] = None,
    task: Annotated[str | None, typer.Option(help=h(S, "task.name"))] = None,
    episodes: Annotated[int | None, typer.Option(help=h(S, "episodes"))] = None,
    steps: Annotated[int | None, typer.Option(help=h(S, "steps"))] = None,
    seed: Annotated[int | None, typer.Option(help=h(S, "seed"))] = None,
    workers: Annotated[int | None, typer.Option(help=h(S, "workers"))] = None,
    spec_file: SpecFile = None,
    overwrite: OverwriteFlag = False,
    json_out: JsonFlag = False,
) -> None:
    """Collect random-action episodes into OUT/dataset.h5 (format: `dlocli.data`)."""
    from dlocli.collect import collect_random
    from dlocli.registry import backends, tasks

    spec = build_spec(
        S,
        spec_file,
        {
            "out": out,
            "backend.name": backend,
            "task.name": task,
            "episodes": episodes,
            "steps": steps,
            "seed": seed,
            "workers": workers,
        },
    )
    backends.check(spec.backend.name)
    tasks.check(spec.task.name)
    columns = (
        TextColumn("collect"),
        BarColumn(),
        MofNCompleteColumn(),
        TextColumn("episodes"),
        TimeRemainingColumn(),
    )
    with Progress(*columns, transient=json_out, disable=json_out) as progress:
        bar = progress.add_task("collect", total=spec.episodes)
        summary = collect_random(spec, overwrite, lambda i, ep: progress.advance(bar))
    emit_summary(summary, json_out, "dlo collect")
