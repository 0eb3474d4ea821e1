"""Model training by epochs, the paper's schedule: :func:`train_model`, and ``dlo train``
(:func:`run_training`: data, model, training, checkpoints, metrics, evaluation and plots in
a run directory). The loop itself is :mod:`dlocli.models.fitting`'s, shared with the online
loop's fixed-cost update (:mod:`dlocli.models.update_steps`).
"""

from __future__ import annotations

import copy
import math
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch

from dlocli.data import Dataset, load_dataset
from dlocli.errors import BadInput
from dlocli.markers.dataset import MarkerDataset
from dlocli.models.base import (
    DynamicsModel,
    build_model,
    load_model,
    read_checkpoint,
    resolve_device,
    save_checkpoint,
)
from dlocli.models.fitting import (  # noqa: F401 (the training API, also from here)
    FitRecord,
    KeepBest,
    OnValidation,
    Progress,
    Round,
    TrainResult,
    Validated,
    fit_loop,
    mirror_applies,
    set_up,
    transition_tensors,
    validation_loss,
)
from dlocli.models.spec import FitSpec, TrainSpec
from dlocli.models.splits import split_episodes  # noqa: F401 (also imported from here)

LAST_CHECKPOINT = Path("checkpoints") / "last.pt"  # after every epoch, for --resume


@dataclass
class EpochPlan:
    """Epochs ``start + 1 .. fit.epochs``: each a pass over the training rows in shuffled
    mini-batches (a permutation drawn from ``gen``), then a validation on all of ``val``."""

    fit: FitSpec
    n_train: int
    val: dict[str, torch.Tensor]
    gen: torch.Generator
    device: torch.device
    start: int = 0
    unit: str = "epoch"
    kept: str = "the last finite epoch is saved"

    @property
    def total(self) -> int:
        return self.fit.epochs

    def rounds(self) -> Iterator[Round]:
        size = self.fit.batch_size
        for epoch in range(self.start + 1, self.fit.epochs + 1):
            order = torch.randperm(self.n_train, generator=self.gen).to(self.device)
            batches = [order[b : b + size] for b in range(0, self.n_train, size)]
            yield Round(epoch, batches, len(batches))


def train_model(
    model: DynamicsModel,
    dataset: Dataset,
    fit: FitSpec,
    *,
    optimizer_state: dict[str, Any] | None = None,
    progress: Progress | None = None,
    on_validation: OnValidation | None = None,
    start_epoch: int = 0,
    generator_state: torch.Tensor | None = None,
    best: KeepBest | None = None,
) -> TrainResult:
    """Train ``model`` in place for ``fit.epochs`` epochs on ``dataset``'s training split
    (with ``fit.mirror``, also on its transitions' mirrored twins; validation stays on the
    recorded data); the model ends with the last epoch's weights.

    The model moves to ``fit.device`` and comes back in eval mode. Its normalisation is
    fitted on the training data if it was never fitted (a continued model keeps its own).
    ``optimizer_state`` resumes Adam's moments (from a previous :class:`TrainResult` or
    checkpoint). ``progress`` gets a :class:`~dlocli.models.fitting.BatchDone` every few
    steps and a :class:`Validated` after each epoch; ``on_validation`` each epoch's
    :class:`FitRecord`, the optimizer and the random generator (for checkpoints), after
    ``best`` (the lowest validation loss so far) has seen it. ``start_epoch`` epochs are
    taken as done: given the generator state saved after them, the remaining epochs are
    those an uninterrupted run would train.
    """
    setup = set_up(model, dataset, fit, optimizer_state)
    gen = torch.Generator(device="cpu").manual_seed(fit.seed)
    if generator_state is not None:
        gen.set_state(generator_state)
    device = setup.train["state"].device
    plan = EpochPlan(fit, len(setup.train["state"]), setup.val, gen, device, start_epoch)
    start = time.perf_counter()
    history, rows = fit_loop(model, setup, fit, plan, gen, best or KeepBest(), progress,
                                on_validation)  # fmt: skip
    elapsed = time.perf_counter() - start
    return TrainResult(
        history=history,
        optimizer_state=copy.deepcopy(setup.optimizer.state_dict()),  # not the live one
        train_episodes=setup.train_episodes,
        val_episodes=setup.val_episodes,
        transitions_per_s=rows / elapsed if elapsed > 0 else 0.0,
    )


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
    with owned(spec.out):
        return _train_in(spec, dataset, overwrite, progress, resume, accept_changes)


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
        done = ResumePoint()
    ckpt_dir = out / "checkpoints"
    best = KeepBest(val_loss=done.best_val_loss)
    history = list(done.history)
    scalars = Scalars(out)

    def on_epoch(record: FitRecord, optimizer: torch.optim.Optimizer, gen: torch.Generator) -> None:
        history.append(record)
        scalars.add(record.count, "loss", train=record.train_loss, val=record.val_loss)
        _write_metrics(out / "metrics.csv", history)
        if best.count == record.count:  # the best so far
            save_checkpoint(model, ckpt_dir / "best.pt", {"epoch": record.count})
        point = {"epoch": record.count, "generator": gen.get_state(),
                 "history": [r.as_row() for r in history], "best_val_loss": best.val_loss,
                 "optimizer": optimizer.state_dict()}  # fmt: skip
        save_checkpoint(model, out / LAST_CHECKPOINT, point)

    try:
        result = train_model(model, dataset, spec, optimizer_state=opt_state, progress=progress,
                             on_validation=on_epoch, start_epoch=done.epoch,
                             generator_state=done.generator, best=best)  # fmt: skip
    finally:
        scalars.close()
    save_checkpoint(model, ckpt_dir / "final.pt",
                    {"epoch": spec.epochs, "optimizer": result.optimizer_state})  # fmt: skip
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
    from dlocli.resume import resumed_run_spec

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
    from dlocli.io import write_text_atomic

    lines = ["epoch,train_loss,val_loss,seconds"]
    lines += [f"{r.count},{r.train_loss:.6g},{r.val_loss:.6g},{r.seconds:.3f}"
              for r in history]  # fmt: skip
    write_text_atomic(path, "\n".join(lines) + "\n")


def _json_safe(summary: dict[str, Any]) -> dict[str, Any]:
    """NaN and infinities become None (JSON has no NaN)."""
    return {
        k: None if isinstance(v, float) and not math.isfinite(v) else v for k, v in summary.items()
    }
