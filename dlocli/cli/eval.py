"""`dlo eval`: a trained model's one-step and open-loop errors next to persistence's."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from dlocli.cli.common import emit_summary, handle_errors
from dlocli.cli.flags import RunFlags, spec_flags
from dlocli.cli.progress import Bars
from dlocli.events import Began, Event
from dlocli.models.spec import EvalSpec
from dlocli.processes import signal_token


@handle_errors
@spec_flags(EvalSpec)
def evaluate(
    run: RunFlags,
    record: Annotated[
        Path | None,
        typer.Option(
            "--record",
            help="On a marker dataset: write its eval trajectories beside the model's "
            "open-loop predictions to this .rrd file for the Rerun viewer (the 'view' extra).",
        ),
    ] = None,
) -> None:
    """Errors (mm) of --checkpoint on --data: one step, 5 and 50 steps open loop, vs persistence."""
    from dlocli.runs.evaluate import run_evaluation

    with Bars(run.json, _describe) as bars:
        summary = run_evaluation(run.spec(), run.overwrite, record, bars, signal_token())
    emit_summary(summary, run.json, "dlo eval")


def _describe(event: Event) -> str:
    """A measurement's name and its errors."""
    if isinstance(event, Began):
        return ""
    numbers = [f"{key} {value:.4g}" for key, value in event.values.items()
               if key.endswith(("_mm", "_cm")) and isinstance(value, float)]  # fmt: skip
    return f"{event.values['name']}: {', '.join(numbers)}" if numbers else event.values["name"]
