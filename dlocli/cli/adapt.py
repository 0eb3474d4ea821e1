"""`dlo adapt`: a model with cable codes given a new cable's code from a few recordings."""

from __future__ import annotations

from rich.console import Console
from rich.table import Table

from dlocli.cli.common import emit_summary, handle_errors
from dlocli.cli.flags import RunFlags, spec_flags
from dlocli.cli.progress import Bars
from dlocli.events import Event
from dlocli.models.spec import AdaptSpec
from dlocli.processes import signal_token


@handle_errors
@spec_flags(AdaptSpec)
def adapt(run: RunFlags) -> None:
    """Pick a new cable's code (and learn it, with --fine-tune) from its first --recordings.

    Every code of --checkpoint (each training cable's and their mean) predicts the first
    --recordings train recordings of --data open loop; the best becomes the cable's code.
    --fine-tune code (or all) then trains the code (or the whole model) on them within
    --update-steps and --seconds. Writes OUT/checkpoints/final.pt, which `dlo eval`, `dlo
    control --cable` and the twins take like any other, and OUT/scores.csv."""
    from dlocli.runs.adapt import run_adaptation

    with Bars(run.json, _describe) as bars:
        summary = run_adaptation(run.spec(), run.overwrite, bars, cancel=signal_token())
    if run.json:
        emit_summary(summary, True, "dlo adapt")
        return
    _print_scores(summary)
    emit_summary({k: v for k, v in summary.items() if k != "scores"}, False, "dlo adapt")


def _describe(event: Event) -> str:
    """A candidate's score; a fine-tune's validation on the recordings read."""
    values = event.values
    if "name" in values:
        return f"{values['name']}: {values['score_cm']:.3g} cm"
    if "val_loss" in values and "k" in values:
        return f"k {values['k']}, on the recordings read {values['val_loss']:.3g} cm"
    return ""


def _print_scores(summary: dict) -> None:
    """The scores table: each candidate on the recordings read, the pick, the reference."""
    count = summary["recordings"]
    table = Table(title=f"scores on the {count} recording{'s' if count > 1 else ''} read (cm)")
    for column in ("code", "score (cm)", ""):
        table.add_column(column)
    for row in summary["scores"]:
        score = "–" if row["score_cm"] is None else f"{row['score_cm']:.3f}"
        table.add_row(row["name"], score, "" if row["role"] == "candidate" else row["role"])
    Console().print(table)
