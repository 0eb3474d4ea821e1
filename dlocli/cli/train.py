"""`dlo train`: fit a dynamics model to a dataset; checkpoints, metrics, plots, evaluation."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Any

import typer
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

from dlocli.cli.common import (
    JsonFlag,
    OverwriteFlag,
    SpecFile,
    VelocityInputFlag,
    build_spec,
    emit_summary,
    handle_errors,
)
from dlocli.cli.common import opt_help as h
from dlocli.train_spec import TrainSpec as S


@handle_errors
def train(
    data: Annotated[Path | None, typer.Option(help=h(S, "data"))] = None,
    model: Annotated[str | None, typer.Option(help=h(S, "model.name"))] = None,
    hidden: Annotated[int | None, typer.Option(help=h(S, "model.hidden"))] = None,
    velocity_input: VelocityInputFlag = None,
    epochs: Annotated[int | None, typer.Option(help=h(S, "epochs"))] = None,
    lr: Annotated[float | None, typer.Option(help=h(S, "lr"))] = None,
    batch_size: Annotated[int | None, typer.Option(help=h(S, "batch_size"))] = None,
    input_noise: Annotated[float | None, typer.Option(help=h(S, "input_noise"))] = None,
    val_fraction: Annotated[float | None, typer.Option(help=h(S, "val_fraction"))] = None,
    device: Annotated[str | None, typer.Option(help=h(S, "device"))] = None,
    seed: Annotated[int | None, typer.Option(help=h(S, "seed"))] = None,
    init_from: Annotated[Path | None, typer.Option(help=h(S, "init_from"))] = None,
    out: Annotated[Path | None, typer.Option(help=h(S, "out"))] = None,
    resume: Annotated[
        Path | None, typer.Option(help="Finish the stopped run in this directory, as if unstopped.")
    ] = None,
    spec_file: SpecFile = None,
    overwrite: OverwriteFlag = False,
    json_out: JsonFlag = False,
) -> None:
    """Train a dynamics model on --data; write OUT/checkpoints/final.pt and OUT/summary.json."""
    from dlocli.registry import models
    from dlocli.training import resumed_spec, run_training

    overrides: dict[str, Any] = {
        "data": data, "model.name": model, "model.hidden": hidden,
        "model.velocity_input": velocity_input, "epochs": epochs, "lr": lr,
        "batch_size": batch_size, "input_noise": input_noise, "val_fraction": val_fraction,
        "device": device, "seed": seed, "init_from": init_from, "out": out,
    }  # fmt: skip
    if resume is not None:
        spec = resumed_spec(resume, overrides)
    else:
        spec = build_spec(S, spec_file, overrides)
    models.check(spec.model.name)
    columns = (
        TextColumn("epoch {task.fields[epoch]}/{task.fields[epochs]}"), BarColumn(),
        MofNCompleteColumn(), TextColumn("loss {task.fields[loss]:.4g}"),
        TextColumn("val {task.fields[val]:.4g}"), TimeRemainingColumn(),
    )  # fmt: skip
    with Progress(*columns, transient=json_out, disable=json_out) as progress:
        bar = progress.add_task("train", total=None, epoch=0, epochs=spec.epochs,
                                loss=float("nan"), val=float("nan"))  # fmt: skip

        def show(event: dict[str, Any]) -> None:
            if "val_loss" in event:
                progress.update(bar, val=event["val_loss"])
                return
            progress.update(bar, epoch=event["epoch"], total=event["batches"],
                            completed=event["batch"], loss=event["loss"])  # fmt: skip

        summary = run_training(spec, overwrite, show, resume=resume is not None)
    emit_summary(summary, json_out, "dlo train")
