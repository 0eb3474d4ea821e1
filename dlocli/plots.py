"""Every figure dlocli draws (matplotlib, Agg, PNG written atomically): learning curves in
the paper's style with mean +- std shading, bars, training losses, model rollouts and the
shape error of a control run. The bench's own figures (:mod:`dlocli.bench.report`) are drawn
with these."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from dlocli.controllers.base import references
from dlocli.io import atomic_path

if TYPE_CHECKING:
    from dlocli.data import Dataset
    from dlocli.models.base import DynamicsModel


def pyplot() -> Any:
    """matplotlib.pyplot on the Agg backend (no display needed)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def figure(**kwargs: Any) -> tuple[Any, Any]:
    """A figure and axes, 6.4 x 4 inches at 120 dpi unless told otherwise."""
    return pyplot().subplots(**{"figsize": (6.4, 4.0), "dpi": 120, **kwargs})


def save_figure(fig: Any, path: Path) -> Path:
    """Save a PNG atomically and close the figure."""
    path = Path(path)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", bbox_inches="tight")
    pyplot().close(fig)
    return path


#: one colour per agent in every figure (matplotlib's cycle colours by name, so an agent keeps
#: its colour whichever agents a figure shows); the references bring their own
AGENT_COLOURS = {"mpc": "C0", "mpc-offline": "C1", "sac": "C2", "td3": "C3", "pilco": "C4",
                 "mppi": "C5"}  # fmt: skip


def agent_colour(name: str) -> str:
    """The agent's colour: a reference's own, else from :data:`AGENT_COLOURS`, else one from
    its name."""
    import zlib

    reference = references().get(name)
    if reference is not None:
        return reference.colour
    return AGENT_COLOURS.get(name) or f"C{6 + zlib.crc32(name.encode()) % 4}"


def integer_ticks(axis: Any) -> None:
    """Ticks at whole numbers only (epochs, steps, transitions)."""
    from matplotlib.ticker import MaxNLocator

    axis.set_major_locator(MaxNLocator(integer=True))


def shaded_curve(
    ax: Any,
    xs: list[float],
    mean: list[float],
    std: list[float],
    label: str,
    color: str | None = None,
    linestyle: str = "-",
) -> None:
    """A line with its mean +- std band (paper Figs. 4 and 7)."""
    mean_a, std_a = np.asarray(mean), np.asarray(std)
    (line,) = ax.plot(xs, mean_a, marker="o", label=label, color=color, linestyle=linestyle)
    ax.fill_between(xs, mean_a - std_a, mean_a + std_a, alpha=0.2, color=line.get_color())


def plot_learning_curve(
    curve: list[dict[str, Any]], offline: list[dict[str, Any]] | None, path: Path
) -> Path:
    """Cumulative reward (paper Fig. 4; Fig. 7 with ``offline``) and the final shape error of
    the trials against transitions, with what doing nothing and random actions got from the
    same starts (:mod:`dlocli.runs.references`), or else the trials' initial error."""
    fig, (ax, ax_mm) = figure(nrows=2, sharex=True, figsize=(6.4, 6.4))
    runs = [("online (MPC + model learning)", curve)]
    runs += [("offline (random data)", offline)] if offline else []
    for label, points in runs:
        xs = [c["transitions"] for c in points]
        means = [c["cumulative_reward_mean"] for c in points]
        shaded_curve(ax, xs, means, [c["cumulative_reward_std"] for c in points], label)
        ax_mm.plot(xs, [c["final_error_mm_mean"] for c in points], marker="o", label=label)
    xs = [c["transitions"] for c in curve]
    _reference_lines(ax, ax_mm, curve, xs)
    ax.set_ylabel("cumulative reward per trial")
    ax.set_title("Online model learning with MPC")
    ax_mm.set_ylabel("mean final shape error (mm)")
    ax_mm.set_yscale("log")
    ax_mm.set_xlabel("transitions")
    integer_ticks(ax_mm.xaxis)
    for axis in (ax, ax_mm):
        axis.grid(alpha=0.3)
        axis.legend(fontsize="small")
    return save_figure(fig, path)


def _reference_lines(ax: Any, ax_mm: Any, curve: list[dict[str, Any]], xs: list[int]) -> None:
    drawn = False
    for name, reference in references().items():
        style = reference.line
        if all(f"{name}_final_error_mm_mean" in c for c in curve):
            label = f"{reference.label}, same starts"
            look = {"color": agent_colour(name), "lw": 1, "label": label}
            errors = [c[f"{name}_final_error_mm_mean"] for c in curve]
            ax_mm.plot(xs, errors, style, **look)
            rewards = [c[f"{name}_cumulative_reward_mean"] for c in curve]
            ax.plot(xs, rewards, style, **look)
            drawn = True
    if not drawn and all("initial_error_mm_mean" in c for c in curve):  # runs before references
        initial = [c["initial_error_mm_mean"] for c in curve]
        ax_mm.plot(xs, initial, "k--", lw=1, label="initial error")


def plot_losses(history: list[dict[str, float]], path: Path) -> Path:
    """PNG: training and validation loss per epoch (log scale)."""
    fig, ax = figure(figsize=(6, 4))
    epochs = [r["epoch"] for r in history]
    ax.plot(epochs, [r["train_loss"] for r in history], "o-", label="train (with input noise)")
    ax.plot(epochs, [r["val_loss"] for r in history], "o-", label="validation")
    ax.set_yscale("log")
    ax.set_xlabel("epoch")
    integer_ticks(ax.xaxis)
    ax.set_ylabel("MSE of normalised state change")
    ax.legend()
    ax.grid(alpha=0.3)
    return save_figure(fig, path)


def plot_errors(
    path: Path, records: list[dict[str, float]], initial_error: float, label: str
) -> Path:
    """Shape error (mm) and controller latency (ms) over the control steps."""
    plt = pyplot()
    steps = [0] + [r["step"] for r in records]
    errors = [initial_error] + [r["shape_error_mm"] for r in records]
    fig, (ax_err, ax_lat) = plt.subplots(2, 1, figsize=(6, 5), sharex=True, height_ratios=(2, 1))
    ax_err.plot(steps, errors, label=label, color=agent_colour(label))
    # the run's reference: doing nothing keeps the start's error
    ax_err.axhline(initial_error, color="black", ls="--", lw=1,
                   label=f"do nothing (start error {initial_error:.1f} mm)")  # fmt: skip
    ax_err.set_ylabel("shape error (mm)")
    ax_err.set_ylim(bottom=0)
    ax_err.grid(alpha=0.3)
    ax_err.legend()
    ax_lat.plot(steps[1:], [r["latency_ms"] for r in records], lw=0.8)
    ax_lat.set_ylabel("latency (ms)")
    ax_lat.set_xlabel("control step")
    integer_ticks(ax_lat.xaxis)
    return save_figure(fig, path)


def plot_rollout_figure(
    truth: np.ndarray, pred: np.ndarray, errors: dict[str, np.ndarray], title: str, path: Path
) -> Path:
    """True (H, N, >=3) vs predicted rod at a few instants (3D), and each error per step."""
    plt = pyplot()
    h = len(pred)
    fig = plt.figure(figsize=(11, 4.5))
    ax = fig.add_subplot(1, 2, 1, projection="3d")
    shown = sorted({0, h // 3, (2 * h) // 3, h - 1})
    colors = plt.cm.viridis(np.linspace(0, 0.9, len(shown)))
    for color, k in zip(colors, shown, strict=True):
        t, p = truth[k, :, :3], pred[k, :, :3]
        ax.plot(t[:, 0], t[:, 1], t[:, 2], "-", color=color, label=f"true t+{k + 1}")
        ax.plot(p[:, 0], p[:, 1], p[:, 2], "--", color=color, label=f"model t+{k + 1}")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_zlabel("z (m)")
    ax.legend(fontsize="small", loc="upper left", bbox_to_anchor=(-0.25, 1.0))
    ax.set_title(f"{title}: open-loop rollout")
    err = fig.add_subplot(1, 2, 2)
    steps = np.arange(1, h + 1)
    for label, values in errors.items():
        err.plot(steps, values, label=label)
    err.set_xlabel("prediction step")
    integer_ticks(err.xaxis)
    err.set_ylabel("mean segment position error (mm)")
    err.legend()
    err.grid(alpha=0.3)
    return save_figure(fig, path)


def plot_rollout(
    model: DynamicsModel, dataset: Dataset, episode: int, path: Path, horizon: int = 50
) -> Path:
    """PNG: true vs predicted rod over an open-loop rollout from the episode's second state,
    at a few instants (3D), and the error per step next to persistence's."""
    from dlocli.models.evaluation import position_error_mm, predict, windows

    start = 1 if dataset.episode_lengths[episode] > 1 else 0  # t = 1: s_{t-1} is recorded
    h = int(min(horizon, dataset.episode_lengths[episode] - start))
    state, actions, truth, previous = windows(dataset, [(episode, start)], h)
    pred = predict(model, state, actions, previous)[0]
    errors = {
        model.spec.name: position_error_mm(pred, truth[0]),
        "persistence": position_error_mm(state[:, None], truth)[0],
    }
    return plot_rollout_figure(truth[0], pred, errors, f"episode {episode}", path)
