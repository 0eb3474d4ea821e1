"""`dlo eval` on a marker dataset: the DEFORM protocol on its eval split, with references."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import numpy as np
import torch

from dlocli.markers import protocol
from dlocli.markers.dataset import MarkerDataset
from dlocli.models.marker_training import predict_episodes
from dlocli.models.markers import MarkerModel

TIMING_STEPS = 200


def evaluate_markers(
    model: MarkerModel, dataset: MarkerDataset, split: str = "eval"
) -> tuple[dict[str, Any], dict[str, list[float]]]:
    """(summary, curves). The summary: the benchmark score (cm, mean and per trajectory), the free markers' error (mm) at
    0.5/1/2/5 s, the same for the freeze and straight-line references, and the time per
    predicted step on one CPU thread at batch 1. The curves: the free markers' mean error
    (mm) per frame, model and references."""
    episodes = dataset.episodes(split)
    predictions = {"model": predict_episodes(model, episodes, dataset.held)}
    for name, reference in protocol.REFERENCES.items():
        predictions[name] = [reference(e, dataset.held) for e in episodes]
    summary: dict[str, Any] = {"split": split, "episodes": len(episodes)}
    for name, preds in predictions.items():
        scores = [protocol.deform_score_cm(p, e) for p, e in zip(preds, episodes)]
        summary[f"{name}_score_cm"] = round(float(np.mean(scores)), 4)
        horizons = [protocol.horizon_errors_mm(p, e, dataset.held, dataset.rate_hz)
                    for p, e in zip(preds, episodes)]  # fmt: skip
        for key in horizons[0]:
            summary[f"{name}_error_mm_{key}"] = round(float(np.mean([h[key] for h in horizons])), 2)
    summary["model_scores_cm"] = [round(float(protocol.deform_score_cm(p, e)), 4)
                                  for p, e in zip(predictions["model"], episodes)]  # fmt: skip
    summary["ms_per_step_1_thread"] = round(time_per_step_ms(model, episodes[0]), 3)
    curves = {
        "free_error_mm": {name: np.mean([protocol.error_by_frame_mm(p, e, dataset.held)
                                         for p, e in zip(preds, episodes)], 0).round(3).tolist()
                          for name, preds in predictions.items()},
        "abs_error_cm": {name: np.mean([np.abs(p - e).mean((1, 2)) * 100
                                        for p, e in zip(preds, episodes)], 0).round(4).tolist()
                         for name, preds in predictions.items()},
    }  # fmt: skip
    return summary, curves


@torch.no_grad()
def time_per_step_ms(model: MarkerModel, episode: np.ndarray) -> float:
    """Median over 3 runs of a batch-1 open-loop rollout's time per step, one CPU thread."""
    cpu = model.to("cpu") if model.device.type != "cpu" else model
    rec = torch.as_tensor(episode[None, : TIMING_STEPS + 2], dtype=torch.float32)
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        times = []
        for _ in range(3):
            start = time.perf_counter()
            cpu.rollout(rec[:, 1], rec[:, 0], rec[:, 2:])
            times.append((time.perf_counter() - start) / (len(rec[0]) - 2))
    finally:
        torch.set_num_threads(threads)
    return float(np.median(times) * 1000.0)


def plot_error_by_horizon(
    summary: dict[str, Any], curves: dict[str, list[float]], rate_hz: float, path: Path,
    title: str = "",
) -> None:
    """Free markers' mean error (mm) against the horizon (s), model and references."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from dlocli.io import atomic_path

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
