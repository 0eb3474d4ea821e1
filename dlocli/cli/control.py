"""`dlo control`: closed-loop shape control to a goal shape through a learned model."""

from __future__ import annotations

from typing import Annotated

import typer
from rich.progress import BarColumn, MofNCompleteColumn, TextColumn

from dlocli.cli.common import emit_summary, handle_errors, progress_bars
from dlocli.cli.flags import RunFlags, parse_options, spec_flags
from dlocli.runs.control import ControlSpec

OPTION_HELP = (
    "Controller option KEY=VALUE, a field of the controller's spec; repeatable. mpc: horizon, "
    "iterations, step_size, optimizer, restarts, warm_start, replan_every, tolerance; mppi: "
    "horizon, samples, iterations, noise, temperature, warm_start, replan_every."
)


@handle_errors
@spec_flags(
    ControlSpec,
    ["task.goal_file", "checkpoint", "policy", "controller", "out", "backend.name", "task.name",
     "task.shapes", "task.episode_steps", "seed", "device", "threads", "video", "video_every"],
)  # fmt: skip
def control(
    run: RunFlags,
    option: Annotated[list[str] | None, typer.Option("--option", "-o", help=OPTION_HELP)] = None,
) -> None:
    """Drive the rod from a seeded random start to the --goal shape; write OUT/summary.json."""
    from dlocli.runs.control import run_control

    run.overrides |= parse_options(option or [], "controller_options")
    spec = run.spec()
    columns = (
        TextColumn("control"), BarColumn(), MofNCompleteColumn(),
        TextColumn("error {task.fields[error]:7.1f} mm  latency {task.fields[latency]:6.1f} ms"),
    )  # fmt: skip
    with progress_bars(*columns, quiet=run.json) as progress:
        bar = progress.add_task(
            "control", total=spec.task.episode_steps, error=float("nan"), latency=0.0
        )

        def show(record: dict[str, float]) -> None:
            progress.start()  # on the first step: bad input never shows a bar
            progress.update(
                bar, completed=record["step"], error=record["shape_error_mm"],
                latency=record["latency_ms"],
            )  # fmt: skip

        summary = run_control(spec, show, overwrite=run.overwrite)
    summary.pop("versions", None)
    emit_summary(summary, run.json, "dlo control")
