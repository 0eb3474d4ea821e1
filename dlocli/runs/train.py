"""`dlo train`: fit a dynamics model to a dataset and write a run directory: the data, the
model (fresh, or continued from ``init_from``), training (:func:`dlocli.models.fit.fit`:
epochs on a rod dataset, rollout windows on a marker dataset), checkpoints, metrics,
evaluation and plots; a run of one network resumes (``--resume``) after any finished epoch
of a rod dataset or any validation of a marker dataset, and ends as it would have
uninterrupted (checkpoints/last.pt holds what it continues from). An ensemble (``members``
> 1) trains its members apart in either view, member i as the network alone would from seed
``seed + i``, and is saved once all are done (checkpoints/final.pt), so it does not resume.

On recorded cables the model is seen through the marker view and trained through open-loop
rollout windows on one cable or several at once (any marker counts, for a network that serves
any), or fine-tuned from ``init_from`` on a new one. Each cable's train recordings are split
by trajectory, ``val_fraction`` of them held out for validation (its eval split is never
seen); a batch of windows comes from one cable, drawn in proportion to its recordings. The
run directory then holds spec.json, metrics.csv, summary.json (with each cable's validation
score against freezing it), checkpoints/{final,last}.pt and plots/loss.png.
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
from dlocli.models.cable_codes import cable_key
from dlocli.models.checkpoints import (
    CABLE_KEYS,
    CONTROL_DT,
    load_marker_model,
    load_model,
    read_checkpoint,
    save_checkpoint,
)
from dlocli.models.evaluation import evaluate_model
from dlocli.models.fit import ENSEMBLE_DOES_NOT_RESUME, fit
from dlocli.models.fitting import FitRecord, KeepBest
from dlocli.models.marker_model import FORM, MarkerModel, build_marker_model
from dlocli.models.marker_training import Cable, Cables, RolloutPoint, validation_score
from dlocli.models.spec import ModelSpec, TrainSpec
from dlocli.models.splits import split_episodes
from dlocli.plots import plot_losses, plot_rollout
from dlocli.resume import resumed_run_spec
from dlocli.rundir import check_fingerprints, owned, record_fingerprints
from dlocli.tensorboard import Scalars

LAST_CHECKPOINT = Path("checkpoints") / "last.pt"  # after every epoch/validation, for --resume


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
    if resume and spec.model.members > 1:
        raise BadInput(ENSEMBLE_DOES_NOT_RESUME)
    if isinstance(dataset, list):  # recorded cables
        with owned(spec.out):
            return run_marker_training(spec, dataset, overwrite, progress, cancel, resume,
                                       accept_changes)  # fmt: skip
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
        if not history and result.history:  # an ensemble's: its members' mean, at the end
            for record in result.history:
                history.append(record)
                scalars.add(record.count, "loss", train=record.train_loss, val=record.val_loss)
            best.val_loss = result.best_val_loss
            _write_metrics(out / "metrics.csv", history)
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
    payload = _resumable(path)
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


def _resumable(path: Path) -> dict[str, Any]:
    """The payload of the run's last checkpoint; BadInput if there is none."""
    if not path.is_file():
        raise BadInput(
            f"--resume: {path} does not exist (no epoch or validation finished, or the run "
            "predates resuming); start the run again with --overwrite"
        )
    return read_checkpoint(path)


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


# ---------------------------------------------------------------------- recorded cables
def check_init_rate(
    model: Any, spec: TrainSpec, dataset: Dataset | MarkerDataset, path: Path
) -> None:
    """BadInput if the --init-from model learned from data at another control period than
    ``dataset``'s (read from ``path``)."""
    if dataset.control_dt is not None:
        check_control_rate(model, dataset.control_dt, f"--init-from {spec.init_from}",
                           f"--data {path} is", "fine-tune it on data at {hz} Hz")  # fmt: skip


def fine_tuned_spec(spec: TrainSpec, held: ModelSpec) -> TrainSpec:
    """``spec`` with the model of its --init-from checkpoint (``held``), the model the run
    trains and its spec.json saves; BadInput if a model option given differs from the
    checkpoint's (a fine-tune cannot change the network)."""
    given = spec.model.model_fields_set if "model" in spec.model_fields_set else set()
    for name in sorted(given):
        want, have = getattr(spec.model, name), getattr(held, name, None)
        if want != have:
            flag = "--model" if name == "name" else "--" + name.replace("_", "-")
            raise BadInput(
                f"--init-from {spec.init_from} holds model {held.name} with {name} "
                f"{have!r}, not the {want!r} requested: drop {flag} (a fine-tune trains the "
                "checkpoint's model) or train a new model without --init-from"
            )
    return spec.model_copy(update={"model": held})


def recorded_rate(dataset: Dataset | MarkerDataset) -> dict[str, float]:
    """What a checkpoint records of the data's control period (nothing where it is unknown)."""
    return {} if dataset.control_dt is None else {CONTROL_DT: dataset.control_dt}


def run_marker_training(
    spec: TrainSpec,
    datasets: list[MarkerDataset],
    overwrite: bool,
    progress: Callback | None,
    cancel: CancelToken | None = None,
    resume: bool = False,
    accept_changes: bool = False,
) -> dict[str, Any]:
    """Train (see the module docstring); the summary of the run. After each validation
    checkpoints/last.pt holds the model and its :class:`RolloutPoint`; ``resume`` continues
    the run in ``spec.out`` from there."""
    paths = list(spec.data or [])
    check_same_rate(datasets, paths)
    point = None
    if resume:
        out = Path(spec.out)
        check_fingerprints(out, spec, accept_changes)
        point = RolloutPoint.from_payload(_resumable(last := out / LAST_CHECKPOINT))
        if point is None:
            raise BadInput(f"--resume: {last} is not a resumable checkpoint; start again with "
                           "--overwrite")  # fmt: skip
        model = load_model(last, "cpu", expect=spec.model, form=FORM)
        check_layout(model, datasets, paths, f"--resume {out}")
    else:
        torch.manual_seed(spec.seed)
        model = starting_model(spec, datasets, paths)
        if spec.init_from is not None:
            spec = fine_tuned_spec(spec, model.spec)
        out = prepare_run_dir(spec.out, overwrite)
        (out / LAST_CHECKPOINT).unlink(missing_ok=True)  # an overwritten run's: not ours to resume
        write_json_atomic(out / "spec.json", spec.model_dump(mode="json"))
        record_fingerprints(out, spec)
    train, val = split_cables(datasets, spec.val_fraction)
    rate = recorded_rate(datasets[0])

    def on_validation(record: FitRecord, now: RolloutPoint) -> None:
        _write_marker_metrics(out / "metrics.csv", now.history)
        extra = {**rate, CABLE_KEYS: model.cable_keys, **now.as_payload()}
        save_checkpoint(model, out / LAST_CHECKPOINT, extra)

    result = fit(model, Cables(train, [c for c in val if c.episodes]), spec,
                 progress=progress, cancel=cancel, on_validation=on_validation,
                 resume_from=point)  # fmt: skip
    history = result.history
    save_checkpoint(model, out / "checkpoints" / "final.pt",
                    {**rate, CABLE_KEYS: model.cable_keys})  # fmt: skip
    seconds = _write_marker_metrics(out / "metrics.csv", history)
    best = min((r.val_loss for r in history), default=math.nan)
    cables = [cable_summary(model, str(p), d, t, v)
              for p, d, t, v in zip(paths, datasets, train, val, strict=True)]  # fmt: skip
    val_freeze = [c["val_freeze_cm"] for c in cables if c["val_episodes"]]
    summary = {
        "model": spec.model.name,
        "form": FORM,
        "parameters": sum(p.numel() for p in model.parameters()),
        "device": str(model.device),
        "update_steps": spec.update_steps,
        "rollout_steps": spec.rollout_steps,
        "train_episodes": sum(c["train_episodes"] for c in cables),
        "val_episodes": sum(c["val_episodes"] for c in cables),
        "val_score_cm": None if math.isnan(best) else round(best, 4),
        "val_freeze_cm": _weighted(val_freeze, cables),
        "cables": cables,
        "seconds": round(seconds, 1),
        "out": str(out),
    }
    _plot_history(history, out / "plots" / "loss.png")
    write_json_atomic(out / "summary.json", summary)
    return summary


def _write_marker_metrics(path: Path, history: list[FitRecord]) -> float:
    """metrics.csv of a rollout fit (its seconds counted since the fit started); the seconds."""
    seconds = list(accumulate(r.seconds for r in history))
    lines = ["step,k,train_loss_cm,val_score_cm,seconds"]
    lines += [f"{r.count},{r.k},{r.train_loss:.6g},{r.val_loss:.6g},{s:.2f}"
              for r, s in zip(history, seconds, strict=True)]  # fmt: skip
    write_text_atomic(path, "\n".join(lines) + "\n")
    return seconds[-1] if seconds else 0.0


def check_same_rate(datasets: list[MarkerDataset], paths: list[Path]) -> None:
    """BadInput if the cables were recorded (or resampled) at different rates: one model step
    is one control period."""
    rates = {d.control_dt for d in datasets if d.control_dt is not None}
    if len(rates) > 1:
        shown = ", ".join(f"{p} {1 / d.control_dt:.6g} Hz" for p, d in zip(paths, datasets,
                          strict=True) if d.control_dt)  # fmt: skip
        raise BadInput(
            f"the --data cables have different rates ({shown}); import them at one rate "
            "(`dlo import --control-hz`)"
        )


def starting_model(
    spec: TrainSpec, datasets: list[MarkerDataset], paths: list[Path]
) -> MarkerModel:
    """A fresh model (its size from the first cable) or the ``init_from`` one to fine-tune;
    BadInput where a network of one marker count meets a cable of another layout."""
    if spec.init_from is not None:  # fine-tuning: the checkpoint's model and normalization
        model = load_marker_model(spec.init_from)
        for path, dataset in zip(paths, datasets, strict=True):
            check_init_rate(model, spec, dataset, path)
        source = f"--init-from {spec.init_from}"
        if spec.fine_tune == "code" and not model.spec.cable_code:
            raise BadInput(
                f"{source} learned no cable codes, so --fine-tune code has nothing to learn: "
                "drop it (or train a model with --cable-code)"
            )
    else:
        model = build_marker_model(spec.model, datasets[0].n_markers, datasets[0].held)
        source = f"model {spec.model.name}"
    check_layout(model, datasets, paths, source)
    return model


def check_layout(
    model: MarkerModel, datasets: list[MarkerDataset], paths: list[Path], source: str
) -> None:
    """BadInput where ``model`` (``source``) of one marker count meets a cable of another."""
    if model.network.any_count:
        return
    for path, dataset in zip(paths, datasets, strict=True):
        if not np.array_equal(model.held.cpu().numpy(), dataset.held):
            raise BadInput(
                f"{source} is sized for {model.n_segments} markers ({int(model.held.sum())} "
                f"held) but --data {path} has {dataset.n_markers} ({int(dataset.held.sum())} "
                "held); train a model that serves any marker count (attention, in-bilstm) "
                "or give cables of one layout"
            )


def split_cables(
    datasets: list[MarkerDataset], val_fraction: float
) -> tuple[list[Cable], list[Cable]]:
    """Each cable's train recordings split by trajectory: (train cables, validation cables),
    in the order of ``datasets`` (a validation cable may hold no recordings)."""
    train, val = [], []
    for dataset in datasets:
        episodes = dataset.episodes("train")
        train_idx, val_idx = split_episodes(len(episodes), val_fraction)
        key = cable_key(dataset.held, episodes)  # its code's, whatever the split
        train.append(Cable([episodes[i] for i in train_idx], dataset.held, key))
        val.append(Cable([episodes[i] for i in val_idx], dataset.held, key))
    return train, val


def cable_summary(
    model: MarkerModel, path: str, dataset: MarkerDataset, train: Cable, val: Cable
) -> dict[str, Any]:
    """One cable's recordings and its validation score (the trained model's, and freezing the
    cable's)."""
    scored = bool(val.episodes)
    frozen = [deform_score_cm(freeze(e, val.held), e) for e in val.episodes]
    return {
        "data": path,
        "markers": dataset.n_markers,
        "train_episodes": len(train.episodes),
        "val_episodes": len(val.episodes),
        "val_score_cm": round(validation_score(model, [val]), 4) if scored else None,
        "val_freeze_cm": round(float(np.mean(frozen)), 4) if scored else None,
    }


def _weighted(values: list[float], cables: list[dict[str, Any]]) -> float | None:
    """The mean over every validation recording of the cables' per-cable means."""
    counts = [c["val_episodes"] for c in cables if c["val_episodes"]]
    if not values:
        return None
    return round(float(np.average(values, weights=counts)), 4)


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
