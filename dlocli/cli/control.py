"""`dlo control`: closed-loop shape control to a goal shape through a learned model."""

from __future__ import annotations

from typing import Annotated, Any

import typer
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn

from dlocli.cli.common import JsonFlag, OverwriteFlag, SpecFile, emit_summary, handle_errors
from dlocli.cli.flags import parse_options, spec_flags
from dlocli.control import ControlSpec

OPTION_HELP = (
    "Controller option KEY=VALUE, a field of the controller's spec; repeatable. mpc: horizon, "
    "iterations, step_size, optimizer, restarts, warm_start, replan_every, tolerance; mppi: "
    "horizon, samples, iterations, noise, temperature, warm_start, replan_every."
)


@handle_errors
@spec_flags(
    ControlSpec,
    ["task.goal_file", "checkpoint", "controller", "out", "backend.name", "task.name",
     "task.shapes", "task.episode_steps", "seed", "device", "threads", "video", "video_every"],
)  # fmt: skip
def control(
    overrides: dict[str, Any],
    option: Annotated[list[str] | None, typer.Option("--option", "-o", help=OPTION_HELP)] = None,
    spec_file: SpecFile = None,
    overwrite: OverwriteFlag = False,
    json_out: JsonFlag = False,
) -> None:
    """Drive the rod from a seeded random start to the --goal shape; write OUT/summary.json."""
    from dlocli.control import run_control
    from dlocli.specs import resolve_spec

    overrides |= parse_options(option or [], "controller_options")
    spec = resolve_spec(ControlSpec, spec_file, overrides)
    columns = (
        TextColumn("control"), BarColumn(), MofNCompleteColumn(),
        TextColumn("error {task.fields[error]:7.1f} mm  latency {task.fields[latency]:6.1f} ms"),
    )  # fmt: skip
    progress = Progress(*columns, transient=json_out, disable=json_out)
    bar = progress.add_task(
        "control", total=spec.task.episode_steps, error=float("nan"), latency=0.0
    )

    def show(record: dict[str, float]) -> None:
        progress.start()  # on the first step: bad input never shows a bar
        progress.update(
            bar, completed=record["step"], error=record["shape_error_mm"],
            latency=record["latency_ms"],
        )  # fmt: skip

    try:
        summary = run_control(spec, show, overwrite=overwrite)
    finally:
        progress.stop()
    summary.pop("versions", None)
    emit_summary(summary, json_out, "dlo control")
