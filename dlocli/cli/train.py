"""`dlo train`: fit a dynamics model to a dataset; checkpoints, metrics, plots, evaluation."""

from __future__ import annotations

from dlocli.cli.common import (
    AcceptChangesFlag,
    ResumeFlag,
    emit_summary,
    handle_errors,
)
from dlocli.cli.flags import RunFlags, spec_flags
from dlocli.cli.progress import Bars
from dlocli.events import Event
from dlocli.models.spec import TrainSpec
from dlocli.processes import signal_token


@handle_errors
@spec_flags(TrainSpec)
def train(
    run: RunFlags,
    resume: ResumeFlag = None,
    accept_changes: AcceptChangesFlag = False,
) -> None:
    """Train a dynamics model on --data; write OUT/checkpoints/final.pt and OUT/summary.json.

    A rod dataset (`dlo collect`) trains one step for --epochs. A marker dataset (`dlo
    import`, recorded cables) trains --update-steps gradient steps through open-loop
    rollouts of up to --rollout-steps steps, on its train split only."""
    from dlocli.runs.train import resumed_spec, run_training

    run.refuse_with_resume(resume)
    spec = resumed_spec(resume, run.overrides) if resume is not None else run.spec()
    with Bars(run.json, _describe, every={"batch": None}) as bars:  # a log gets epochs only
        summary = run_training(
            spec,
            run.overwrite,
            bars,
            resume=resume is not None,
            accept_changes=accept_changes,
            cancel=signal_token(),  # Ctrl-C and SIGTERM stop the fit between gradient steps
        )
    emit_summary(summary, run.json, "dlo train")


def _describe(event: Event) -> str:
    """An epoch's validation loss, a batch's loss; a marker dataset's steps through rollouts."""
    from dlocli.models.fitting import BatchDone, RolloutValidated, Validated

    values = event.values
    if isinstance(event, RolloutValidated):
        return (f"k {values['k']}, rollout loss {values['train_loss']:.3g} cm, "
                f"validation {values['val_loss']:.3g} cm")  # fmt: skip
    if isinstance(event, Validated):
        return f"val loss {values['val_loss']:.4g}"
    if isinstance(event, BatchDone):
        return f"loss {values['loss']:.4g}"
    if event.unit == "member" and "val_loss" in values:  # an ensemble's member trained
        return f"its validation {values['val_loss']:.3g} cm"
    return ""
