"""`dlo collect --random`: random-action trajectories into an HDF5 dataset."""

from __future__ import annotations

from typing import Annotated, Any

import typer
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

from dlocli.cli.common import JsonFlag, OverwriteFlag, SpecFile, emit_summary, handle_errors
from dlocli.cli.flags import spec_flags
from dlocli.specs import CollectSpec


@handle_errors
@spec_flags(
    CollectSpec,
    ["out", "backend.name", "task.name", "task.shapes", "task.goal", "episodes",
     "task.episode_steps", "seed", "workers"],
)  # fmt: skip
def collect(
    overrides: dict[str, Any],
    random: Annotated[
        bool,
        typer.Option(
            "--random",
            help="Uniform random actions (the only policy here; use `dlo online` for MPC data).",
        ),
    ] = True,
    spec_file: SpecFile = None,
    overwrite: OverwriteFlag = False,
    json_out: JsonFlag = False,
) -> None:
    """Collect random-action episodes into OUT/dataset.h5 (format: `dlocli.data`)."""
    from dlocli.collect import collect_random
    from dlocli.registry import backends, tasks
    from dlocli.specs import resolve_spec

    spec = resolve_spec(CollectSpec, spec_file, overrides)
    backends.check(spec.backend.name)
    tasks.check(spec.task.name)
    columns = (
        TextColumn("collect"), BarColumn(), MofNCompleteColumn(), TextColumn("episodes"),
        TimeRemainingColumn(),
    )  # fmt: skip
    with Progress(*columns, transient=json_out, disable=json_out) as progress:
        bar = progress.add_task("collect", total=spec.episodes)
        summary = collect_random(spec, overwrite, lambda i, ep: progress.advance(bar))
    emit_summary(summary, json_out, "dlo collect")
