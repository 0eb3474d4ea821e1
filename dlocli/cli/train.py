"""`dlo train`: fit a dynamics model to a dataset; checkpoints, metrics, plots, evaluation."""

from __future__ import annotations

from typing import Any

from rich.progress import BarColumn, MofNCompleteColumn, TextColumn, TimeRemainingColumn

from dlocli.cli.common import (
    AcceptChangesFlag,
    ResumeFlag,
    emit_summary,
    handle_errors,
    progress_bars,
)
from dlocli.cli.flags import RunFlags, spec_flags
from dlocli.models.spec import TrainSpec as S


@handle_errors
@spec_flags(
    S,
    ["data", "model.name", "model.hidden", "model.velocity_input", "epochs", "lr", "batch_size",
     "input_noise", "val_fraction", "mirror", "device", "seed", "init_from", "out",
     "update_steps", "rollout_steps", "rollout_start", "eval_every"],
)  # fmt: skip
def train(
    run: RunFlags,
    resume: ResumeFlag = None,
    accept_changes: AcceptChangesFlag = False,
) -> None:
    """Train a dynamics model on --data; write OUT/checkpoints/final.pt and OUT/summary.json.

    A rod dataset (`dlo collect`) trains one step for --epochs. A marker dataset (`dlo
    import`, recorded cables) trains --update-steps gradient steps through open-loop
    rollouts of up to --rollout-steps steps, on its train split only."""
    from dlocli.models.training import resumed_spec, run_training
    from dlocli.registry import models

    run.refuse_with_resume(resume)
    spec = resumed_spec(resume, run.overrides) if resume is not None else run.spec()
    models.check(spec.model.name)
    columns = (
        TextColumn("epoch {task.fields[epoch]}/{task.fields[epochs]}"), BarColumn(),
        MofNCompleteColumn(), TextColumn("loss {task.fields[loss]:.4g}"),
        TextColumn("val {task.fields[val]:.4g}"), TimeRemainingColumn(),
    )  # fmt: skip
    with progress_bars(*columns, quiet=run.json) as progress:
        bar = progress.add_task("train", total=None, epoch=0, epochs=spec.epochs,
                                loss=float("nan"), val=float("nan"))  # fmt: skip

        def show(event: dict[str, Any]) -> None:
            progress.start()
            if "val_loss" in event:
                progress.update(bar, val=event["val_loss"])
                return
            progress.update(bar, epoch=event["epoch"], total=event["batches"],
                            completed=event["batch"], loss=event["loss"])  # fmt: skip

        summary = run_training(
            spec, run.overwrite, show, resume=resume is not None, accept_changes=accept_changes
        )
    emit_summary(summary, run.json, "dlo train")
