"""`dlo train`: fit a dynamics model to a dataset and write a run directory: the data, the
model (fresh, or continued from ``init_from``), training (:func:`dlocli.models.fit.fit`:
epochs on a rod dataset, rollout windows on a marker dataset), checkpoints, metrics,
evaluation and plots; a rod run resumes after any finished epoch.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from itertools import accumulate
from pathlib import Path
from typing import Any

import numpy as np
import torch

from dlocli.cancel import CancelToken
from dlocli.data import Dataset, MarkerDataset, load_dataset
from dlocli.data.protocol import deform_score_cm, freeze
from dlocli.errors import BadInput
from dlocli.events import Callback
from dlocli.io import atomic_path, prepare_run_dir, write_json_atomic, write_text_atomic
from dlocli.models.base import DynamicsModel, build_model, check_control_rate, resolve_device
from dlocli.models.checkpoints import (
    CONTROL_DT,
    load_marker_model,
    load_model,
    read_checkpoint,
    save_checkpoint,
)
from dlocli.models.evaluation import evaluate_model, plot_rollout
from dlocli.models.fit import fit
from dlocli.models.fitting import FitRecord, KeepBest
from dlocli.models.markers import FORM, build_marker_model
from dlocli.models.spec import TrainSpec
from dlocli.plots import plot_losses
from dlocli.resume import resumed_run_spec
from dlocli.rundir import check_fingerprints, owned, record_fingerprints
from dlocli.tensorboard import Scalars

LAST_CHECKPOINT = Path("checkpoints") / "last.pt"  # after every epoch, for --resume


def prepare_model(spec: TrainSpec, dataset: Dataset) -> tuple[DynamicsModel, dict[str, Any] | None]:
    """A fresh model (seeded) or the one in ``spec.init_from`` and its optimizer state.

    With ``init_from``, model fields given explicitly must match the checkpoint's; none given
    means "the checkpoint's model".
    """
    device = resolve_device(spec.device)
    if spec.init_from is not None:
        expect = spec.model if "model" in spec.model_fields_set else None
        model = load_model(spec.init_from, device, expect=expect)
        check_init_rate(model, spec, dataset)
        opt_state = read_checkpoint(spec.init_from).get("optimizer")
        if model.n_segments != dataset.n_segments:
            raise BadInput(
                f"--init-from model has {model.n_segments} segments, the dataset "
                f"{dataset.n_segments}; use a matching dataset"
            )
        return model, opt_state if isinstance(opt_state, dict) else None
    torch.manual_seed(spec.seed)
    return build_model(spec.model, dataset.n_segments).to(device), None


def check_init_rate(model: Any, spec: TrainSpec, dataset: Dataset | MarkerDataset) -> None:
    """BadInput if the --init-from model learned from data at another control period."""
    if dataset.control_dt is not None:
        check_control_rate(model, dataset.control_dt, f"--init-from {spec.init_from}",
                           f"--data {spec.data} is", "fine-tune it on data at {hz} Hz")  # fmt: skip


def recorded_rate(dataset: Dataset | MarkerDataset) -> dict[str, float]:
    """What a checkpoint records of the data's control period (nothing where it is unknown)."""
    return {} if dataset.control_dt is None else {CONTROL_DT: dataset.control_dt}


def load_training_data(spec: TrainSpec) -> Dataset:
    if spec.data is None:
        raise BadInput("no dataset given; pass --data DATASET (make one: `dlo collect --random`)")
    dataset = load_dataset(spec.data)
    if dataset.n_episodes < 2 and spec.val_fraction > 0:
        raise BadInput(
            f"dataset {spec.data} has {dataset.n_episodes} episode; validation is split by "
            "trajectory, so collect at least 2 (or pass --val-fraction 0)"
        )
    return dataset


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
    if isinstance(dataset, MarkerDataset):
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


# ---------------------------------------------------------------------- marker datasets
def run_marker_training(
    spec: TrainSpec,
    dataset: MarkerDataset,
    overwrite: bool,
    progress: Callback | None,
    cancel: CancelToken | None = None,
) -> dict[str, Any]:
    """`dlo train` on a marker dataset: train on its train split (``val_fraction`` of those
    trajectories held out for validation; the eval split is never seen), then write
    OUT/{spec.json, metrics.csv, summary.json, checkpoints/final.pt, plots/loss.png}."""
    torch.manual_seed(spec.seed)
    if spec.init_from is not None:  # fine-tuning: the checkpoint's model and normalization
        model = load_marker_model(spec.init_from)
        check_init_rate(model, spec, dataset)
        if not np.array_equal(model.held.cpu().numpy(), dataset.held):
            raise BadInput(
                f"--init-from {spec.init_from} was trained on another marker layout than "
                "--data (held markers differ); pass a checkpoint of the same cable"
            )
    else:
        model = build_marker_model(spec.model, dataset.n_markers, dataset.held)
    out = prepare_run_dir(spec.out, overwrite)
    write_json_atomic(out / "spec.json", spec.model_dump(mode="json"))

    result = fit(model, dataset, spec, progress=progress, cancel=cancel)
    history = result.history
    seconds = list(accumulate(r.seconds for r in history))  # since the fit started
    save_checkpoint(model, out / "checkpoints" / "final.pt", recorded_rate(dataset))
    lines = ["step,k,train_loss_cm,val_score_cm,seconds"]
    lines += [f"{r.count},{r.k},{r.train_loss:.6g},{r.val_loss:.6g},{s:.2f}"
              for r, s in zip(history, seconds, strict=True)]  # fmt: skip
    write_text_atomic(out / "metrics.csv", "\n".join(lines) + "\n")
    best = min((r.val_loss for r in history), default=math.nan)
    val = [dataset.episodes("train")[i] for i in result.val_episodes]
    summary = {
        "model": spec.model.name,
        "form": FORM,
        "parameters": sum(p.numel() for p in model.parameters()),
        "device": str(model.device),
        "update_steps": spec.update_steps,
        "rollout_steps": spec.rollout_steps,
        "train_episodes": len(result.train_episodes),
        "val_episodes": len(val),
        "val_score_cm": None if math.isnan(best) else round(best, 4),
        "val_freeze_cm": round(
            float(np.mean([deform_score_cm(freeze(e, dataset.held), e) for e in val])), 4
        )
        if val
        else None,  # fmt: skip
        "seconds": round(seconds[-1], 1) if history else 0.0,
        "out": str(out),
    }
    _plot_history(history, out / "plots" / "loss.png")
    write_json_atomic(out / "summary.json", summary)
    return summary


def _plot_history(history: list[FitRecord], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 3.5))
    steps = [r.count for r in history]
    ax.plot(steps, [r.train_loss for r in history], label="train: k-step rollout L1 (cm)")
    ax.plot(steps, [r.val_loss for r in history], label="validation: whole rollout (cm)")
    ax.set_xlabel("gradient step")
    ax.set_ylabel("cm")
    ax.set_yscale("log")
    ax.legend()
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", dpi=120)
    plt.close(fig)
