"""`dlo eval`: a trained model's one-step and open-loop errors next to persistence's."""

from __future__ import annotations

from typing import Any

from dlocli.cli.common import JsonFlag, OverwriteFlag, SpecFile, emit_summary, handle_errors
from dlocli.cli.flags import spec_flags
from dlocli.train_spec import EvalSpec


@handle_errors
@spec_flags(EvalSpec, ["checkpoint", "data", "device", "max_starts", "plot", "out"])
def evaluate(
    overrides: dict[str, Any],
    spec_file: SpecFile = None,
    overwrite: OverwriteFlag = False,
    json_out: JsonFlag = False,
) -> None:
    """Errors (mm) of --checkpoint on --data: one step, 5 and 50 steps open loop, vs persistence."""
    from dlocli.evaluation import run_evaluation
    from dlocli.specs import resolve_spec

    summary = run_evaluation(resolve_spec(EvalSpec, spec_file, overrides), overwrite)
    emit_summary(summary, json_out, "dlo eval")
