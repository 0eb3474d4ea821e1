"""`dlo eval`: a trained model's one-step and open-loop errors next to persistence's."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from dlocli.cli.common import emit_summary, handle_errors
from dlocli.cli.flags import RunFlags, spec_flags
from dlocli.models.spec import EvalSpec


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

    summary = run_evaluation(run.spec(), run.overwrite, record)
    emit_summary(summary, run.json, "dlo eval")
