"""`dlo control`: closed-loop shape control to a goal shape through a learned model."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Any

import typer
import yaml
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn

from dlocli.cli.common import (
    JsonFlag,
    OverwriteFlag,
    SpecFile,
    build_spec,
    emit_summary,
    handle_errors,
)
from dlocli.cli.common import opt_help as h
from dlocli.control import ControlSpec as S
from dlocli.errors import BadInput

GOAL_HELP = (
    "Goal shape: a .npy float array (N,3) of segment centres in metres (make one with "
    "`dlo goal`). Sets task.goal_file."
)
OPTION_HELP = (
    "Controller option KEY=VALUE, a field of the controller's spec; repeatable. mpc: horizon, "
    "iterations, step_size, optimizer, restarts, warm_start, replan_every, tolerance; mppi: "
    "horizon, samples, iterations, noise, temperature, warm_start, replan_every."
)


@handle_errors
def control(
    goal: Annotated[Path | None, typer.Option(help=GOAL_HELP)] = None,
    model: Annotated[Path | None, typer.Option(help=h(S, "model"))] = None,
    out: Annotated[Path | None, typer.Option(help=h(S, "out"))] = None,
    backend: Annotated[str | None, typer.Option(help=h(S, "backend.name"))] = None,
    task: Annotated[str | None, typer.Option(help=h(S, "task.name"))] = None,
    controller: Annotated[str | None, typer.Option(help=h(S, "controller"))] = None,
    option: Annotated[list[str] | None, typer.Option("--option", "-o", help=OPTION_HELP)] = None,
    steps: Annotated[int | None, typer.Option(help=h(S, "steps"))] = None,
    seed: Annotated[int | None, typer.Option(help=h(S, "seed"))] = None,
    device: Annotated[str | None, typer.Option(help=h(S, "device"))] = None,
    threads: Annotated[int | None, typer.Option(help=h(S, "threads"))] = None,
    video: Annotated[Path | None, typer.Option(help=h(S, "video"))] = None,
    spec_file: SpecFile = None,
    overwrite: OverwriteFlag = False,
    json_out: JsonFlag = False,
) -> None:
    """Drive the rod from a seeded random start to the --goal shape; write OUT/summary.json."""
    from dlocli.control import run_control

    overrides: dict[str, Any] = {
        "task.goal_file": goal, "model": model, "out": out, "backend.name": backend,
        "task.name": task, "controller": controller, "steps": steps, "seed": seed,
        "device": device, "threads": threads, "video": video,
    }  # fmt: skip
    overrides.update(parse_options(option or []))
    spec = build_spec(S, spec_file, overrides)
    columns = (
        TextColumn("control"), BarColumn(), MofNCompleteColumn(),
        TextColumn("error {task.fields[error]:7.1f} mm  latency {task.fields[latency]:6.1f} ms"),
    )  # fmt: skip
    progress = Progress(*columns, transient=json_out, disable=json_out)
    bar = progress.add_task("control", total=spec.steps, error=float("nan"), latency=0.0)

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


def parse_options(pairs: list[str]) -> dict[str, Any]:
    """``["iterations=50", "warm_start=false"]`` -> dotted overrides of controller_options."""
    parsed: dict[str, Any] = {}
    for pair in pairs:
        key, sep, text = pair.partition("=")
        if not sep or not key.strip():
            raise BadInput(
                f"--option {pair!r} must look like KEY=VALUE, e.g. --option iterations=50"
            )
        try:
            value = yaml.safe_load(text)
        except yaml.YAMLError:
            value = text
        parsed[f"controller_options.{key.strip()}"] = value
    return parsed
