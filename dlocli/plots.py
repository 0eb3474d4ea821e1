"""Figures in the paper's style (matplotlib, Agg): learning curves with mean +- std shading."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from dlocli.io import atomic_path


def _figure() -> tuple[Any, Any]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt.subplots(figsize=(6.4, 4.0), dpi=120)


def save_figure(fig: Any, path: Path) -> Path:
    """Save a PNG atomically and close the figure."""
    import matplotlib.pyplot as plt

    path = Path(path)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", bbox_inches="tight")
    plt.close(fig)
    return path


def shaded_curve(ax: Any, xs: list[float], mean: list[float], std: list[float], label: str) -> None:
    """A line with its mean +- std band (paper Figs. 4 and 7)."""
    import numpy as np

    mean_a, std_a = np.asarray(mean), np.asarray(std)
    (line,) = ax.plot(xs, mean_a, marker="o", label=label)
    ax.fill_between(xs, mean_a - std_a, mean_a + std_a, alpha=0.2, color=line.get_color())


def plot_learning_curve(
    curve: list[dict[str, Any]], offline: list[dict[str, Any]] | None, path: Path
) -> Path:
    """Cumulative reward per trial against transitions (paper Fig. 4; Fig. 7 with ``offline``)."""
    fig, ax = _figure()
    xs = [c["transitions"] for c in curve]
    shaded_curve(
        ax,
        xs,
        [c["cumulative_reward_mean"] for c in curve],
        [c["cumulative_reward_std"] for c in curve],
        "online (MPC + model learning)",
    )
    if offline:
        shaded_curve(
            ax,
            [c["transitions"] for c in offline],
            [c["cumulative_reward_mean"] for c in offline],
            [c["cumulative_reward_std"] for c in offline],
            "offline (random data)",
        )
    ax.set_xlabel("transitions")
    ax.set_ylabel("cumulative reward per trial")
    ax.set_title("Online model learning with MPC")
    ax.grid(alpha=0.3)
    ax.legend()
    return save_figure(fig, path)
