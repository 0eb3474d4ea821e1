"""`dlo eval`: a trained model's one-step and open-loop errors next to persistence's."""

from __future__ import annotations

from dlocli.cli.common import emit_summary, handle_errors
from dlocli.cli.flags import RunFlags, spec_flags
from dlocli.models.spec import EvalSpec


@handle_errors
@spec_flags(EvalSpec)
def evaluate(
    run: RunFlags,
) -> None:
    """Errors (mm) of --checkpoint on --data: one step, 5 and 50 steps open loop, vs persistence."""
    from dlocli.runs.evaluate import run_evaluation

    summary = run_evaluation(run.spec(), run.overwrite)
    emit_summary(summary, run.json, "dlo eval")
