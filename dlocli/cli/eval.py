"""`dlo eval`: a trained model's one-step and open-loop errors next to persistence's."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from dlocli.cli.common import JsonFlag, emit_summary, handle_errors

MODEL_HELP = "Trained model: a checkpoint .pt or a `dlo train` run directory (its final.pt)."
DATA_HELP = "Dataset file or collect run directory; every episode is evaluated."
DEVICE_HELP = "Torch device: auto, cpu, cuda or cuda:K."
PLOT_HELP = "Also write a PNG of the predicted vs true rod over a rollout of the first episode."
STARTS_HELP = "Most start states per rollout horizon (evenly spread over the data)."


@handle_errors
def evaluate(
    model: Annotated[Path, typer.Option(help=MODEL_HELP)],
    data: Annotated[Path, typer.Option(help=DATA_HELP)],
    device: Annotated[str, typer.Option(help=DEVICE_HELP)] = "auto",
    max_starts: Annotated[int, typer.Option(min=1, help=STARTS_HELP)] = 512,
    plot: Annotated[Path | None, typer.Option(help=PLOT_HELP)] = None,
    json_out: JsonFlag = False,
) -> None:
    """Errors (mm) of --model on --data: one step, 5 and 50 steps open loop, vs persistence."""
    from dlocli.data import load_dataset
    from dlocli.errors import BadInput
    from dlocli.evaluation import evaluate_model, plot_rollout
    from dlocli.models.base import load_model

    net = load_model(model, device)
    dataset = load_dataset(data)
    if dataset.n_segments != net.n_segments:
        raise BadInput(
            f"model {model} is for {net.n_segments} segments but {data} has "
            f"{dataset.n_segments}; evaluate on matching data"
        )
    if plot is not None and plot.suffix != ".png":
        raise BadInput(f"--plot {plot} must end in .png")
    summary = {"model": str(model), "data": str(data)}
    summary.update(evaluate_model(net, dataset, max_starts=max_starts))
    if plot is not None:
        plot_rollout(net, dataset, 0, plot)
        summary["plot"] = str(plot)
    emit_summary(summary, json_out, "dlo eval")
