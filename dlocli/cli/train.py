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
from dlocli.models.spec import TrainSpec


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
    from dlocli.models.fitting import BatchDone, FitEvent, RolloutValidated, Validated
    from dlocli.runs.train import resumed_spec, run_training

    run.refuse_with_resume(resume)
    spec = resumed_spec(resume, run.overrides) if resume is not None else run.spec()
    with Bars(run.json) as bars:

        def show(event: FitEvent) -> None:
            if isinstance(event, RolloutValidated):  # a marker dataset: steps through rollouts
                info = (f"k {event.k}, rollout loss {event.train_loss:.3g} cm, "
                        f"validation {event.val_loss:.3g} cm")  # fmt: skip
                bars.update("step", event.count, event.total, info=info)
                return
            if "epoch" not in bars.phases:  # training starts (after earlier epochs, resumed)
                bars.begin("epoch", spec.epochs, done=event.count - 1)
                bars.begin("batch", None, every=None)  # a log gets the epochs only
            if isinstance(event, Validated):  # an epoch finished
                bars.update("epoch", event.count, spec.epochs,
                            info=f"val loss {event.val_loss:.4g}")  # fmt: skip
            elif isinstance(event, BatchDone):  # each epoch counts its batches afresh
                bars.update("batch", event.batch, event.batches,
                            info=f"loss {event.loss:.4g}")  # fmt: skip

        summary = run_training(
            spec, run.overwrite, show, resume=resume is not None, accept_changes=accept_changes
        )
    emit_summary(summary, run.json, "dlo train")
