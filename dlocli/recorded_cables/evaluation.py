"""`dlo eval` on a marker dataset: the DEFORM protocol on its eval split, with references."""

from __future__ import annotations

import copy
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import torch

from dlocli.data import MarkerDataset, protocol
from dlocli.io import atomic_path
from dlocli.models.marker_model import MarkerModel
from dlocli.models.marker_training import predict_episodes
from dlocli.threads import torch_threads

TIMING_STEPS = 200


def evaluate_markers(
    model: MarkerModel, dataset: MarkerDataset, split: str = "eval"
) -> tuple[dict[str, Any], dict[str, dict[str, list[float]]]]:
    """(summary, curves) of ``model`` and the references on ``split``.

    The summary: the benchmark score (cm; mean, and per trajectory for the model), the free
    markers' mean error (mm) at 0.5/1/2/5 s, and the model's time per predicted step on one
    CPU thread at batch 1. The curves, per frame: the free markers' mean Euclidean error
    (mm) and the mean absolute error per coordinate over all markers (cm; its mean over
    frames 2.. is the benchmark score)."""
    summary: dict[str, Any] = {"split": split, "episodes": len(dataset.episodes(split))}
    curves: dict[str, dict[str, list[float]]] = {"free_error_mm": {}, "abs_error_cm": {}}
    for _, measured, curve in marker_evaluation_parts(model, dataset, split):
        summary.update(measured)
        for key, values in curve.items():
            curves[key].update(values)
    return summary, curves


def marker_evaluation_parts(
    model: MarkerModel, dataset: MarkerDataset, split: str = "eval"
) -> Iterator[tuple[str, dict[str, Any], dict[str, dict[str, list[float]]]]]:
    """:func:`evaluate_markers` one predictor at a time: (name, its summary entries, its
    curves) for the model, then each reference, then ("timing", the model's time per step,
    no curves); a caller may stop between them (``dlo eval``'s cancel) and keep what was
    measured. :data:`MARKER_PARTS` counts them."""
    episodes, held = dataset.episodes(split), dataset.held
    predictors = {"model": lambda: predict_episodes(model, episodes, held)}
    for name, reference in protocol.REFERENCES.items():
        predictors[name] = lambda reference=reference: [reference(e, held) for e in episodes]
    for name, predict in predictors.items():
        pairs = list(zip(predict(), episodes, strict=True))
        scores = [protocol.deform_score_cm(p, e) for p, e in pairs]
        summary: dict[str, Any] = {f"{name}_score_cm": round(float(np.mean(scores)), 4)}
        if name == "model":
            summary["model_scores_cm"] = [round(float(x), 4) for x in scores]
        horizons = [protocol.horizon_errors_mm(p, e, held, dataset.rate_hz) for p, e in pairs]
        for key in horizons[0]:
            summary[f"{name}_error_mm_{key}"] = round(float(np.mean([h[key] for h in horizons])), 2)
        free = [protocol.error_by_frame_mm(p, e, held) for p, e in pairs]
        per_coordinate = [np.abs(p - e).mean((1, 2)) * 100 for p, e in pairs]
        curves = {"free_error_mm": {name: np.mean(free, 0).round(3).tolist()},
                  "abs_error_cm": {name: np.mean(per_coordinate, 0).round(4).tolist()}}  # fmt: skip
        yield name, summary, curves
    timing = round(time_per_step_ms(model, episodes[0], held), 3)
    yield "timing", {"ms_per_step_1_thread": timing}, {}


#: how many parts :func:`marker_evaluation_parts` yields: the model, the references, timing
MARKER_PARTS = 2 + len(protocol.REFERENCES)


@torch.no_grad()
def time_per_step_ms(model: MarkerModel, episode: np.ndarray, held: np.ndarray) -> float:
    """Median over 3 runs of a batch-1 open-loop rollout's time per step, one CPU thread, of
    the cable whose markers ``held`` marks."""
    cpu = model if model.device.type == "cpu" else copy.deepcopy(model).to("cpu")
    rec = torch.as_tensor(episode[None, : TIMING_STEPS + 2], dtype=torch.float32)
    mask = torch.as_tensor(held, dtype=torch.bool)
    times = []
    with torch_threads(1):
        for _ in range(3):
            start = time.perf_counter()
            cpu.rollout(rec[:, 1], rec[:, 0], rec[:, 2:], mask)
            times.append((time.perf_counter() - start) / (len(rec[0]) - 2))
    return float(np.median(times) * 1000.0)


def plot_error_by_horizon(
    summary: dict[str, Any],
    curves: dict[str, dict[str, list[float]]],
    rate_hz: float,
    path: Path,
    title: str = "",
) -> None:
    """Free markers' mean error (mm) against the horizon (s), model and references."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 3.8))
    for name, curve in curves["free_error_mm"].items():
        t = (np.arange(len(curve)) - 1) / rate_hz
        ax.plot(t[1:], curve[1:], label=f"{name} ({summary[f'{name}_score_cm']:.2f} cm)",
                linestyle="-" if name == "model" else "--")  # fmt: skip
    ax.set_xlabel("horizon (s, open loop from frame 1)")
    ax.set_ylabel("free markers' mean error (mm)")
    ax.set_title(title or "open-loop prediction on the eval trajectories")
    ax.legend(title="DEFORM score in brackets")
    fig.tight_layout()
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(Path(path)) as tmp:
        fig.savefig(tmp, format="png", dpi=120)
    plt.close(fig)
