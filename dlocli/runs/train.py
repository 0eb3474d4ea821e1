"""`dlo train`: fit a dynamics model to a dataset and write a run directory: the data, the
model (fresh, or continued from ``init_from``), training (:func:`dlocli.models.fit.fit`:
epochs on a rod dataset, rollout windows on a marker dataset), checkpoints, metrics,
evaluation and plots; a rod run resumes after any finished epoch.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch

from dlocli.cancel import CancelToken
from dlocli.data import Dataset, MarkerDataset, load_dataset
from dlocli.errors import BadInput
from dlocli.events import Callback
from dlocli.io import prepare_run_dir, write_json_atomic, write_text_atomic
from dlocli.models.base import DynamicsModel, build_model, resolve_device
from dlocli.models.checkpoints import (
    load_model,
    read_checkpoint,
    save_checkpoint,
)
from dlocli.models.evaluation import evaluate_model
from dlocli.models.fit import fit
from dlocli.models.fitting import FitRecord, KeepBest
from dlocli.models.spec import TrainSpec
from dlocli.plots import plot_losses, plot_rollout
from dlocli.resume import resumed_run_spec
from dlocli.rundir import check_fingerprints, owned, record_fingerprints
from dlocli.runs.train_markers import (
    check_init_rate,
    fine_tuned_spec,
    recorded_rate,
    run_marker_training,
)
from dlocli.tensorboard import Scalars

LAST_CHECKPOINT = Path("checkpoints") / "last.pt"  # after every epoch, for --resume


def prepare_model(spec: TrainSpec, dataset: Dataset) -> tuple[DynamicsModel, dict[str, Any] | None]:
    """A fresh model (seeded) or the one in ``spec.init_from`` and its optimizer state.

    With ``init_from``, model fields given explicitly must match the checkpoint's
    (:func:`fine_tuned_spec`); none given means "the checkpoint's model".
    """
    device = resolve_device(spec.device)
    if spec.init_from is not None:
        model = load_model(spec.init_from, device)
        fine_tuned_spec(spec, model.spec)
        check_init_rate(model, spec, dataset, spec.data[0])
        opt_state = read_checkpoint(spec.init_from).get("optimizer")
        if model.n_segments != dataset.n_segments:
            raise BadInput(
                f"--init-from model has {model.n_segments} segments, the dataset "
                f"{dataset.n_segments}; use a matching dataset"
            )
        return model, opt_state if isinstance(opt_state, dict) else None
    torch.manual_seed(spec.seed)
    return build_model(spec.model, dataset.n_segments).to(device), None


def load_training_data(spec: TrainSpec) -> Dataset | list[MarkerDataset]:
    """The rod dataset of ``--data``, or its marker datasets (one or several cables)."""
    if not spec.data:
        raise BadInput("no dataset given; pass --data DATASET (make one: `dlo collect --random`)")
    datasets = [load_dataset(path) for path in spec.data]
    for path, dataset in zip(spec.data, datasets, strict=True):
        if len(datasets) > 1 and not isinstance(dataset, MarkerDataset):
            raise BadInput(
                f"--data {path} is simulated rod data; several --data train one model on "
                "recorded cables (marker datasets from `dlo import`): pass one rod dataset"
            )
        if dataset.n_episodes < 2 and spec.val_fraction > 0:
            raise BadInput(
                f"dataset {path} has {dataset.n_episodes} episode; validation is split by "
                "trajectory, so collect at least 2 (or pass --val-fraction 0)"
            )
    return datasets if isinstance(datasets[0], MarkerDataset) else datasets[0]


def run_training(
    spec: TrainSpec,
    overwrite: bool = False,
    progress: Callback | None = None,
    resume: bool = False,
    accept_changes: bool = False,
    cancel: CancelToken | None = None,
) -> dict[str, Any]:
    """`dlo train`: train, then write OUT/{spec.json, metrics.csv, summary.json,
    checkpoints/{final,best,last}.pt, plots/{loss,rollout}.png}; return the summary.
    ``progress`` gets the fit's events; ``cancel`` stops it before its next gradient step.

    ``resume``: continue the run in ``spec.out`` (its saved spec) from ``checkpoints/last.pt``;
    a changed spec.json or dataset is refused unless ``accept_changes``.
    """
    dataset = load_training_data(spec)
    if spec.fine_tune == "code" and (spec.init_from is None or not isinstance(dataset, list)):
        raise BadInput(
            "--fine-tune code learns a recorded cable's code from a model with cable codes: "
            "pass --init-from that model and a marker dataset, or drop --fine-tune"
        )
    if isinstance(dataset, list):  # recorded cables
        if resume:
            raise BadInput("--resume is not supported for marker datasets yet; train again")
        with owned(spec.out):
            return run_marker_training(spec, dataset, overwrite, progress, cancel)
    if spec.rollout_steps > 1:
        raise BadInput(
            "--rollout-steps > 1 trains marker datasets (`dlo import`); rod datasets train "
            "one step: drop it"
        )
    with owned(spec.out):
        return _train_in(spec, dataset, overwrite, progress, resume, accept_changes, cancel)


@dataclass
class ResumePoint:
    """Where a `dlo train` run stands after its last finished epoch."""

    epoch: int = 0
    generator: torch.Tensor | None = None
    history: list[FitRecord] = field(default_factory=list)
    best_val_loss: float = math.inf


def _train_in(
    spec: TrainSpec,
    dataset: Dataset,
    overwrite: bool,
    progress: Callback | None,
    resume: bool,
    accept_changes: bool,
    cancel: CancelToken | None,
) -> dict[str, Any]:
    if resume:
        out = Path(spec.out)
        check_fingerprints(out, spec, accept_changes)
        model, opt_state, done = _resume_point(out / LAST_CHECKPOINT, spec, dataset)
    else:
        model, opt_state = prepare_model(spec, dataset)
        spec = spec.model_copy(update={"model": model.spec})  # with --init-from: the checkpoint's
        out = prepare_run_dir(spec.out, overwrite)
        (out / LAST_CHECKPOINT).unlink(missing_ok=True)  # an overwritten run's: not ours to resume
        write_json_atomic(out / "spec.json", spec.model_dump(mode="json"))
        record_fingerprints(out, spec)
        done = ResumePoint()
    ckpt_dir = out / "checkpoints"
    rate = recorded_rate(dataset)
    best = KeepBest(val_loss=done.best_val_loss)
    history = list(done.history)
    scalars = Scalars(out)

    def on_epoch(record: FitRecord, optimizer: torch.optim.Optimizer, gen: torch.Generator) -> None:
        history.append(record)
        scalars.add(record.count, "loss", train=record.train_loss, val=record.val_loss)
        _write_metrics(out / "metrics.csv", history)
        if best.count == record.count:  # the best so far
            save_checkpoint(model, ckpt_dir / "best.pt", {"epoch": record.count, **rate})
        point = {"epoch": record.count, "generator": gen.get_state(),
                 "history": [r.as_row() for r in history], "best_val_loss": best.val_loss,
                 "optimizer": optimizer.state_dict(), **rate}  # fmt: skip
        save_checkpoint(model, out / LAST_CHECKPOINT, point)

    try:
        result = fit(model, dataset, spec, optimizer_state=opt_state, progress=progress,
                     on_validation=on_epoch, start_epoch=done.epoch,
                     generator_state=done.generator, best=best,
                     cancel=cancel)  # fmt: skip
    finally:
        scalars.close()
    final = {"epoch": spec.epochs, "optimizer": result.optimizer_state, **rate}
    save_checkpoint(model, ckpt_dir / "final.pt", final)
    eval_eps = result.val_episodes if len(result.val_episodes) else result.train_episodes
    last = history[-1] if history else None
    summary: dict[str, Any] = {
        "model": spec.model.name,
        "parameters": sum(p.numel() for p in model.parameters()),
        "device": str(model.device),
        "epochs": spec.epochs,
        "train_episodes": len(result.train_episodes),
        "val_episodes": len(result.val_episodes),
        "train_loss": last and last.train_loss,
        "val_loss": last and last.val_loss,
        "best_val_loss": None if math.isinf(best.val_loss) else best.val_loss,
        "seconds": round(sum(r.seconds for r in history), 2),
        "transitions_per_s": round(result.transitions_per_s, 1),
        **evaluate_model(model, dataset, eval_eps),
        "out": str(out),
    }
    if history:
        plot_losses([r.as_row() for r in history], out / "plots" / "loss.png")
    plot_rollout(model, dataset, int(eval_eps[0]), out / "plots" / "rollout.png")
    write_json_atomic(out / "summary.json", _json_safe(summary))
    return _json_safe(summary)


def resumed_spec(run_dir: Path, overrides: dict[str, Any]) -> TrainSpec:
    """`dlo train --resume RUN`: the spec of the run in ``run_dir`` (pass it to
    :func:`run_training` with ``resume=True``); flags that contradict it are refused."""
    return resumed_run_spec(TrainSpec, run_dir, overrides, "a training", "dlo train")


def _resume_point(
    path: Path, spec: TrainSpec, dataset: Dataset
) -> tuple[DynamicsModel, dict[str, Any], ResumePoint]:
    """The model, Adam's state and what was done at the end of the last finished epoch."""
    if not path.is_file():
        raise BadInput(
            f"--resume: {path} does not exist (no epoch finished, or the run predates "
            "resuming); start the run again with --overwrite"
        )
    payload = read_checkpoint(path)
    model = load_model(path, spec.device, expect=spec.model)
    if model.n_segments != dataset.n_segments:
        raise BadInput(f"--resume: {path} has {model.n_segments} segments, the dataset "
                       f"{dataset.n_segments}; the run's --data has changed")  # fmt: skip
    epoch, history = payload.get("epoch"), payload.get("history")
    if not isinstance(epoch, int) or not isinstance(history, list):
        raise BadInput(f"--resume: {path} is not a resumable checkpoint; start again with "
                       "--overwrite")  # fmt: skip
    records = [FitRecord.from_row(row) for row in history]
    best = payload.get("best_val_loss")
    done = ResumePoint(epoch, payload.get("generator"), records,
                       best if isinstance(best, float) else math.inf)  # fmt: skip
    return model, payload.get("optimizer") or {}, done


def _write_metrics(path: Path, history: list[FitRecord]) -> None:
    lines = ["epoch,train_loss,val_loss,seconds"]
    lines += [f"{r.count},{r.train_loss:.6g},{r.val_loss:.6g},{r.seconds:.3f}"
              for r in history]  # fmt: skip
    write_text_atomic(path, "\n".join(lines) + "\n")


def _json_safe(summary: dict[str, Any]) -> dict[str, Any]:
    """NaN and infinities become None (JSON has no NaN)."""
    return {
        k: None if isinstance(v, float) and not math.isfinite(v) else v for k, v in summary.items()
    }
