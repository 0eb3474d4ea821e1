"""`dlo train` on recorded cables: one model through the marker view, trained through
open-loop rollout windows on one cable or several at once (any marker counts, for a network
that serves any), or fine-tuned from ``init_from`` on a new one.

Each cable's train recordings are split by trajectory, ``val_fraction`` of them held out for
validation (its eval split is never seen); a batch of windows comes from one cable, drawn in
proportion to its recordings. The run directory holds spec.json, metrics.csv, summary.json
(with each cable's validation score against freezing it), checkpoints/final.pt and
plots/loss.png.
"""

from __future__ import annotations

import math
from itertools import accumulate
from pathlib import Path
from typing import Any

import numpy as np
import torch

from dlocli.cancel import CancelToken
from dlocli.data import Dataset, MarkerDataset
from dlocli.data.protocol import deform_score_cm, freeze
from dlocli.errors import BadInput
from dlocli.events import Callback
from dlocli.io import atomic_path, prepare_run_dir, write_json_atomic, write_text_atomic
from dlocli.models.base import check_control_rate
from dlocli.models.cable_codes import cable_key
from dlocli.models.checkpoints import CABLE_KEYS, CONTROL_DT, load_marker_model, save_checkpoint
from dlocli.models.fit import fit
from dlocli.models.fitting import FitRecord
from dlocli.models.marker_training import Cable, Cables, validation_score
from dlocli.models.markers import FORM, MarkerModel, build_marker_model
from dlocli.models.spec import ModelSpec, TrainSpec
from dlocli.models.splits import split_episodes


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
) -> dict[str, Any]:
    """Train (see the module docstring); the summary of the run."""
    paths = list(spec.data or [])
    check_same_rate(datasets, paths)
    torch.manual_seed(spec.seed)
    model = starting_model(spec, datasets, paths)
    if spec.init_from is not None:
        spec = fine_tuned_spec(spec, model.spec)
    train, val = split_cables(datasets, spec.val_fraction)
    out = prepare_run_dir(spec.out, overwrite)
    write_json_atomic(out / "spec.json", spec.model_dump(mode="json"))

    result = fit(model, Cables(train, [c for c in val if c.episodes]), spec,
                 progress=progress, cancel=cancel)  # fmt: skip
    history = result.history
    seconds = list(accumulate(r.seconds for r in history))  # since the fit started
    save_checkpoint(model, out / "checkpoints" / "final.pt",
                    {**recorded_rate(datasets[0]), CABLE_KEYS: model.cable_keys})  # fmt: skip
    lines = ["step,k,train_loss_cm,val_score_cm,seconds"]
    lines += [f"{r.count},{r.k},{r.train_loss:.6g},{r.val_loss:.6g},{s:.2f}"
              for r, s in zip(history, seconds, strict=True)]  # fmt: skip
    write_text_atomic(out / "metrics.csv", "\n".join(lines) + "\n")
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
        "seconds": round(seconds[-1], 1) if history else 0.0,
        "out": str(out),
    }
    _plot_history(history, out / "plots" / "loss.png")
    write_json_atomic(out / "summary.json", summary)
    return summary


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
    if model.network.any_count:
        return model
    for path, dataset in zip(paths, datasets, strict=True):
        if not np.array_equal(model.held.cpu().numpy(), dataset.held):
            raise BadInput(
                f"{source} is sized for {model.n_segments} markers ({int(model.held.sum())} "
                f"held) but --data {path} has {dataset.n_markers} ({int(dataset.held.sum())} "
                "held); train a model that serves any marker count (attention, in-bilstm) "
                "or give cables of one layout"
            )
    return model


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
