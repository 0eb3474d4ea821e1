"""Model training: ``dlo train`` and the library function the online loop calls.

:func:`train_model` fits a :class:`~dlocli.models.base.DynamicsModel` to a dataset's
transitions with Adam on the mean squared error of the normalised state change, Gaussian
noise on the input state (paper Sec. IV-C), and a train/validation split by trajectory that
stays the same as the dataset grows (so continued training in the online loop never
validates on what it trained on). :func:`dlocli.models.update_steps.train_steps` is the
online loop's fixed-cost update (``FitSpec.schedule == "steps"``); it shares this module's
set-up, gradient step and validation. :func:`run_training` is the whole
command: data, model, training, checkpoints, metrics, evaluation and plots in a run directory.
"""

from __future__ import annotations

import copy
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from dlocli.data import Dataset, load_dataset
from dlocli.errors import BadInput, DloError
from dlocli.markers.dataset import MarkerDataset
from dlocli.models.base import (
    DynamicsModel,
    build_model,
    load_model,
    read_checkpoint,
    resolve_device,
    save_checkpoint,
)
from dlocli.models.mirror import with_mirrored
from dlocli.models.spec import FitSpec, TrainSpec
from dlocli.models.splits import split_episodes  # noqa: F401 (also imported from here)
from dlocli.processes import raise_if_stopped

EVAL_BATCH = 1024
LAST_CHECKPOINT = Path("checkpoints") / "last.pt"  # after every epoch, for --resume
Progress = Callable[[dict[str, Any]], None]
OnEpoch = Callable[[dict[str, float], torch.optim.Optimizer, torch.Generator], None]


@dataclass
class TrainResult:
    """What :func:`train_model` and :func:`train_steps` return: the history (a record per
    epoch, or per validation of the steps schedule) and the optimiser's state; for the steps
    schedule also the gradient steps taken, the step whose weights were kept (0: the weights
    it started from) and the share of sampled training rows from the recent episodes."""

    history: list[dict[str, float]] = field(default_factory=list)
    optimizer_state: dict[str, Any] = field(default_factory=dict)
    train_episodes: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    val_episodes: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    transitions_per_s: float = 0.0
    steps: int = 0
    best_step: int | None = None
    best_val_loss: float = math.nan
    recent_share: float = math.nan

    @property
    def val_loss(self) -> float:
        """The validation loss of the weights the model ends with."""
        if self.best_step is not None:
            return self.best_val_loss
        return self.history[-1]["val_loss"] if self.history else math.nan


# ---------------------------------------------------------------------- split and tensors
def transition_tensors(
    dataset: Dataset, episodes: np.ndarray, device: torch.device, mirror: bool = False
) -> dict[str, torch.Tensor]:
    """``previous_state``, ``state`` (M,N,7), ``action`` (M,2,6), ``next_state`` (M,N,7)
    float32 on ``device``, for the transitions whose previous state is recorded (t >= 1);
    with ``mirror``, followed by their mirrored twins (2M rows, :mod:`dlocli.models.mirror`)."""
    arrays = dataset.transitions(episodes, skip_first=True)
    if mirror:
        arrays = with_mirrored(arrays)
    return {
        k: torch.as_tensor(arrays[k], dtype=torch.float32, device=device)
        for k in ("previous_state", "state", "action", "next_state")
    }


@dataclass
class _Setup:
    """What both schedules train with: the split, its tensors and the optimizer."""

    train_episodes: np.ndarray
    val_episodes: np.ndarray
    train: dict[str, torch.Tensor]
    val: dict[str, torch.Tensor]
    optimizer: torch.optim.Optimizer
    mirror: bool  # whether the training rows include the mirrored twins


def _set_up(
    model: DynamicsModel,
    dataset: Dataset,
    fit: FitSpec,
    optimizer_state: dict[str, Any] | None,
) -> _Setup:
    """Move ``model`` to ``fit.device``, split ``dataset``, fit the normalisation of a model
    that never had one, and make Adam (resuming ``optimizer_state``, at ``fit.lr``)."""
    if dataset.n_segments != model.n_segments:
        raise BadInput(
            f"dataset has {dataset.n_segments} segments but the model {model.n_segments}; "
            "train a new model or use a matching dataset"
        )
    device = resolve_device(fit.device)
    model.to(device)
    train_eps, val_eps = split_episodes(dataset.n_episodes, fit.val_fraction)
    mirror = fit.mirror and mirror_applies(dataset)
    train = transition_tensors(dataset, train_eps, device, mirror=mirror)
    val = transition_tensors(dataset, val_eps, device)  # the recorded data only
    if len(train["state"]) == 0:
        raise BadInput("the training split has no transitions; collect more episodes")
    if not bool(model.fitted):
        arrays = dataset.transitions(train_eps)
        model.fit_normalization(with_mirrored(arrays) if mirror else arrays)
    model.requires_grad_(True)  # a loaded model comes frozen for planning
    optimizer = torch.optim.Adam(model.parameters(), lr=fit.lr)
    if optimizer_state:
        optimizer.load_state_dict(copy.deepcopy(optimizer_state))  # the caller's stays as is
        for group in optimizer.param_groups:
            group["lr"] = fit.lr
    return _Setup(train_eps, val_eps, train, val, optimizer, mirror)


def mirror_applies(dataset: Dataset) -> bool:
    """Whether ``dataset``'s transitions have valid mirrored twins: both rod ends held (a free
    right end's twin would be a rod with a free left end, which no backend simulates)."""
    spec = dataset.attrs.get("spec")
    backend = spec.get("backend") if isinstance(spec, dict) else None
    return not (isinstance(backend, dict) and backend.get("held_ends") == "left")


def _check_finite(loss: float, where: str, fit: FitSpec, kept: str) -> None:
    if not math.isfinite(loss):  # the model is lost; never save it as a result
        raise DloError(
            f"training diverged: the loss became {loss} in {where} at lr {fit.lr:g}; start "
            f"again with a lower --lr ({kept})"
        )


# ---------------------------------------------------------------------- the loop
def train_model(
    model: DynamicsModel,
    dataset: Dataset,
    fit: FitSpec,
    *,
    optimizer_state: dict[str, Any] | None = None,
    progress: Progress | None = None,
    on_epoch: OnEpoch | None = None,
    start_epoch: int = 0,
    generator_state: torch.Tensor | None = None,
) -> TrainResult:
    """Train ``model`` in place for ``fit.epochs`` epochs on ``dataset``'s training split
    (with ``fit.mirror``, also on its transitions' mirrored twins; validation stays on the
    recorded data).

    The model moves to ``fit.device`` and comes back in eval mode. Its normalisation is
    fitted on the training data if it was never fitted (a continued model keeps its own).
    ``optimizer_state`` resumes Adam's moments (from a previous :class:`TrainResult` or
    checkpoint). ``progress`` gets ``{"epoch", "batch", "batches", "loss"}`` every few steps
    and ``{"epoch", "val_loss"}`` after each epoch; ``on_epoch`` gets each epoch's record
    ``{"epoch", "train_loss", "val_loss", "seconds"}``, the optimizer and the random generator
    (for checkpoints). ``start_epoch`` epochs are taken as done: given the generator state
    saved after them, the remaining epochs are those an uninterrupted run would train.
    ``fit.schedule`` is not read here: the online loop picks :func:`train_steps` for "steps".
    """
    setup = _set_up(model, dataset, fit, optimizer_state)
    train, val, optimizer = setup.train, setup.val, setup.optimizer
    n_train = len(train["state"])
    gen = torch.Generator(device="cpu").manual_seed(fit.seed)
    if generator_state is not None:
        gen.set_state(generator_state)
    result = TrainResult(train_episodes=setup.train_episodes, val_episodes=setup.val_episodes)
    start = time.perf_counter()
    for epoch in range(start_epoch + 1, fit.epochs + 1):
        t0 = time.perf_counter()
        model.train()
        train_loss = _train_epoch(model, optimizer, train, fit, gen, epoch, progress)
        _check_finite(train_loss, f"epoch {epoch}", fit, "the last finite epoch is saved")
        record = {
            "epoch": epoch,
            "train_loss": train_loss,
            "val_loss": validation_loss(model, val),
            "seconds": time.perf_counter() - t0,
        }
        result.history.append(record)
        if progress is not None:
            progress({"epoch": epoch, "epochs": fit.epochs, "val_loss": record["val_loss"]})
        if on_epoch is not None:
            on_epoch(record, optimizer, gen)
    model.eval()
    elapsed = time.perf_counter() - start
    result.optimizer_state = copy.deepcopy(optimizer.state_dict())  # not aliased to the live one
    epochs_run = max(fit.epochs - start_epoch, 0)
    result.transitions_per_s = epochs_run * n_train / elapsed if elapsed > 0 else 0.0
    return result


def _train_epoch(
    model: DynamicsModel,
    optimizer: torch.optim.Optimizer,
    data: dict[str, torch.Tensor],
    fit: FitSpec,
    gen: torch.Generator,
    epoch: int,
    progress: Progress | None,
) -> float:
    """One pass over ``data`` in shuffled mini-batches; the mean training loss."""
    n = len(data["state"])
    order = torch.randperm(n, generator=gen).to(data["state"].device)
    batches = math.ceil(n / fit.batch_size)
    total = torch.zeros((), device=data["state"].device)
    for b in range(batches):
        idx = order[b * fit.batch_size : (b + 1) * fit.batch_size]
        loss = _gradient_step(model, optimizer, data, idx, fit, gen)
        total += loss * len(idx)
        if progress is not None and (b % 10 == 0 or b == batches - 1):
            progress({"epoch": epoch, "batch": b + 1, "batches": batches, "loss": loss.item()})
    return float(total) / n


def _gradient_step(
    model: DynamicsModel,
    optimizer: torch.optim.Optimizer,
    data: dict[str, torch.Tensor],
    idx: torch.Tensor,
    fit: FitSpec,
    gen: torch.Generator,
) -> torch.Tensor:
    """One Adam step on the rows ``idx`` of ``data``, with input noise from ``gen``; the
    batch's loss (detached)."""
    raise_if_stopped()
    state = data["state"][idx]
    noise = None
    if fit.input_noise > 0:  # in units of the one-step change, expressed in state units
        scale = fit.input_noise * model.delta_std / model.state_std
        noise = torch.randn(state.shape, generator=gen).to(state.device) * scale
    loss = model.loss(
        state, data["action"][idx], data["next_state"][idx], noise, data["previous_state"][idx]
    )
    optimizer.zero_grad(set_to_none=True)
    loss.backward()
    optimizer.step()
    return loss.detach()


@torch.no_grad()
def validation_loss(model: DynamicsModel, data: dict[str, torch.Tensor]) -> float:
    """Mean normalised-delta MSE on ``data`` without input noise (NaN if it is empty)."""
    n = len(data["state"])
    if n == 0:
        return math.nan
    was_training = model.training
    model.eval()
    total = 0.0
    for i in range(0, n, EVAL_BATCH):
        sl = slice(i, i + EVAL_BATCH)
        batch = data["state"][sl]
        loss = model.loss(
            batch, data["action"][sl], data["next_state"][sl], previous=data["previous_state"][sl]
        )
        total += float(loss) * len(batch)
    model.train(was_training)
    return total / n


# ---------------------------------------------------------------------- model set-up
def prepare_model(spec: TrainSpec, dataset: Dataset) -> tuple[DynamicsModel, dict[str, Any] | None]:
    """A fresh model (seeded) or the one in ``spec.init_from`` and its optimizer state.

    With ``init_from``, model fields given explicitly must match the checkpoint's; none given
    means "the checkpoint's model".
    """
    device = resolve_device(spec.device)
    if spec.init_from is not None:
        expect = spec.model if "model" in spec.model_fields_set else None
        model = load_model(spec.init_from, device, expect=expect)
        opt_state = read_checkpoint(spec.init_from).get("optimizer")
        if model.n_segments != dataset.n_segments:
            raise BadInput(
                f"--init-from model has {model.n_segments} segments, the dataset "
                f"{dataset.n_segments}; use a matching dataset"
            )
        return model, opt_state if isinstance(opt_state, dict) else None
    torch.manual_seed(spec.seed)
    return build_model(spec.model, dataset.n_segments).to(device), None


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


# ---------------------------------------------------------------------- the command
def run_training(
    spec: TrainSpec,
    overwrite: bool = False,
    progress: Progress | None = None,
    resume: bool = False,
    accept_changes: bool = False,
) -> dict[str, Any]:
    """`dlo train`: train, then write OUT/{spec.json, metrics.csv, summary.json,
    checkpoints/{final,best,last}.pt, plots/{loss,rollout}.png}; return the summary.

    ``resume``: continue the run in ``spec.out`` (its saved spec) from ``checkpoints/last.pt``;
    a changed spec.json or dataset is refused unless ``accept_changes``.
    """
    from dlocli.rundir import owned

    dataset = load_training_data(spec)
    if isinstance(dataset, MarkerDataset):
        from dlocli.models.marker_training import run_marker_training

        if resume:
            raise BadInput("--resume is not supported for marker datasets yet; train again")
        with owned(spec.out):
            return run_marker_training(spec, dataset, overwrite, progress)
    if spec.rollout_steps > 1:
        raise BadInput(
            "--rollout-steps > 1 trains marker datasets (`dlo import`); rod datasets train "
            "one step: drop it"
        )
    if spec.schedule != "epochs":
        raise BadInput(
            'dlo train trains by epochs; the "steps" schedule is the online loop\'s model '
            "update (dlo online --schedule steps): drop it from the spec"
        )
    with owned(spec.out):
        return _train_in(spec, dataset, overwrite, progress, resume, accept_changes)


def _train_in(
    spec: TrainSpec,
    dataset: Dataset,
    overwrite: bool,
    progress: Progress | None,
    resume: bool,
    accept_changes: bool,
) -> dict[str, Any]:
    from dlocli.io import prepare_run_dir, write_json_atomic
    from dlocli.models.evaluation import evaluate_model, plot_rollout
    from dlocli.plots import plot_losses
    from dlocli.rundir import check_fingerprints, record_fingerprints
    from dlocli.tensorboard import Scalars

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
        done = {"epoch": 0, "generator": None, "history": [], "best_val_loss": math.inf}
    ckpt_dir = out / "checkpoints"
    best = {"val_loss": done["best_val_loss"]}
    history: list[dict[str, float]] = list(done["history"])
    scalars = Scalars(out)

    def on_epoch(
        record: dict[str, float], optimizer: torch.optim.Optimizer, gen: torch.Generator
    ) -> None:
        history.append(record)
        scalars.add(record["epoch"], "loss", train=record["train_loss"], val=record["val_loss"])
        _write_metrics(out / "metrics.csv", history)
        if not record["val_loss"] >= best["val_loss"]:  # also true for the first NaN
            best["val_loss"] = record["val_loss"]
            save_checkpoint(model, ckpt_dir / "best.pt", {"epoch": record["epoch"]})
        point = {"epoch": record["epoch"], "generator": gen.get_state(), "history": history,
                 "best_val_loss": best["val_loss"],
                 "optimizer": optimizer.state_dict()}  # fmt: skip
        save_checkpoint(model, out / LAST_CHECKPOINT, point)

    try:
        result = train_model(model, dataset, spec, optimizer_state=opt_state, progress=progress,
                             on_epoch=on_epoch, start_epoch=done["epoch"],
                             generator_state=done["generator"])  # fmt: skip
    finally:
        scalars.close()
    save_checkpoint(model, ckpt_dir / "final.pt",
                    {"epoch": spec.epochs, "optimizer": result.optimizer_state})  # fmt: skip
    eval_eps = result.val_episodes if len(result.val_episodes) else result.train_episodes
    summary: dict[str, Any] = {
        "model": spec.model.name,
        "parameters": sum(p.numel() for p in model.parameters()),
        "device": str(model.device),
        "epochs": spec.epochs,
        "train_episodes": len(result.train_episodes),
        "val_episodes": len(result.val_episodes),
        "train_loss": history[-1]["train_loss"] if history else None,
        "val_loss": history[-1]["val_loss"] if history else None,
        "best_val_loss": None if math.isinf(best["val_loss"]) else best["val_loss"],
        "seconds": round(sum(r["seconds"] for r in history), 2),
        "transitions_per_s": round(result.transitions_per_s, 1),
        **evaluate_model(model, dataset, eval_eps),
        "out": str(out),
    }
    if history:
        plot_losses(history, out / "plots" / "loss.png")
    plot_rollout(model, dataset, int(eval_eps[0]), out / "plots" / "rollout.png")
    write_json_atomic(out / "summary.json", _json_safe(summary))
    return _json_safe(summary)


def resumed_spec(run_dir: Path, overrides: dict[str, Any]) -> TrainSpec:
    """`dlo train --resume RUN`: the spec of the run in ``run_dir`` (pass it to
    :func:`run_training` with ``resume=True``); flags that contradict it are refused."""
    from dlocli.resume import resumed_run_spec

    return resumed_run_spec(TrainSpec, run_dir, overrides, "a training", "dlo train")


def _resume_point(
    path: Path, spec: TrainSpec, dataset: Dataset
) -> tuple[DynamicsModel, dict[str, Any], dict[str, Any]]:
    """The model, Adam's state and what was done (epoch, generator, history, best) at the
    end of the last finished epoch."""
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
    done = {k: payload.get(k) for k in ("epoch", "generator", "history", "best_val_loss")}
    if not isinstance(done["epoch"], int) or not isinstance(done["history"], list):
        raise BadInput(f"--resume: {path} is not a resumable checkpoint; start again with "
                       "--overwrite")  # fmt: skip
    return model, payload.get("optimizer") or {}, done


def _write_metrics(path: Path, history: list[dict[str, float]]) -> None:
    from dlocli.io import write_text_atomic

    lines = ["epoch,train_loss,val_loss,seconds"]
    lines += [f"{r['epoch']},{r['train_loss']:.6g},{r['val_loss']:.6g},{r['seconds']:.3f}"
              for r in history]  # fmt: skip
    write_text_atomic(path, "\n".join(lines) + "\n")


def _json_safe(summary: dict[str, Any]) -> dict[str, Any]:
    """NaN and infinities become None (JSON has no NaN)."""
    return {
        k: None if isinstance(v, float) and not math.isfinite(v) else v for k, v in summary.items()
    }
