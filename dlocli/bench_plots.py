"""Results of ``dlo bench``: results.csv, the summary table and the figures, from result rows
(one row per agent x seed x evaluation point x evaluation setting; columns :data:`COLUMNS`).

Figures in the paper's style, mean +- std over seeds of each seed's mean cumulative reward
per evaluation episode:

- Fig. 4 ``fig4_learning_curves.png``: reward against transitions, every agent where it learned;
- Fig. 5 ``fig5_bimanual.png``: final reward on the bimanual task, by the task learned on;
- Fig. 6 ``fig6_random_goals.png``: final reward on random goals next to the fixed goal;
- Fig. 7 ``fig7_online_offline.png``: ``mpc`` (online) against ``mpc-offline``.

A figure is drawn only when the rows hold what it shows (e.g. Fig. 7 needs both mpc agents).
"""

from __future__ import annotations

import csv
import io
from collections import defaultdict
from pathlib import Path
from typing import Any

import numpy as np

from dlocli.errors import BadInput
from dlocli.io import write_json_atomic, write_text_atomic
from dlocli.plots import save_figure, shaded_curve

Row = dict[str, Any]
GOALS = {"fixed": "fixed goal", "random": "random goals"}
SETTING = ("agent", "train_task", "train_goals", "eval_task", "eval_goals")


def is_home(row: Row) -> bool:
    """True for an evaluation where the agent learned (not a transfer)."""
    return row["eval_task"] == row["train_task"] and row["eval_goals"] == row["train_goals"]


def final_rows(rows: list[Row]) -> list[Row]:
    """Each agent x seed x setting's row at its last evaluation point."""
    last: dict[tuple, Row] = {}
    for row in rows:
        key = (*(row[k] for k in SETTING), row["seed"])
        if key not in last or row["eval"] > last[key]["eval"]:
            last[key] = row
    return list(last.values())


def _group(rows: list[Row], keys: tuple[str, ...]) -> dict[tuple, list[Row]]:
    groups: dict[tuple, list[Row]] = defaultdict(list)
    for row in rows:
        groups[tuple(row[k] for k in keys)].append(row)
    return groups


# ----------------------------------------------------------------------------- files
COLUMNS: dict[str, type] = {
    "agent": str,
    "seed": int,
    "eval": int,
    "transitions": int,
    "train_task": str,
    "train_goals": str,
    "eval_task": str,
    "eval_goals": str,
    "cumulative_reward": float,
    "cumulative_reward_std": float,
    "final_error_mm": float,
    "wall_seconds": float,
    "eval_seconds": float,
}


def write_results_csv(path: Path, rows: list[dict[str, Any]]) -> None:
    buffer = io.StringIO()
    writer = csv.DictWriter(buffer, fieldnames=list(COLUMNS), extrasaction="ignore")
    writer.writeheader()
    writer.writerows(rows)
    write_text_atomic(path, buffer.getvalue())


def read_results_csv(path: Path) -> list[dict[str, Any]]:
    """results.csv with typed values; BadInput if it is not one."""
    if not Path(path).is_file():
        raise BadInput(f"{path} does not exist; pass the --out directory of a `dlo bench` run")
    with open(path, newline="") as f:
        reader = csv.DictReader(f)
        if set(COLUMNS) - set(reader.fieldnames or []):
            raise BadInput(f"{path} is not a dlo bench results.csv (missing columns)")
        return [{k: COLUMNS[k](row[k]) for k in COLUMNS} for row in reader]


def write_summary(
    out: Path, table: list[dict[str, Any]], figures: list[Path], extra: dict[str, Any]
) -> dict[str, Any]:
    """summary.json and summary.md (the table in Markdown)."""
    summary = {**extra, "table": table, "figures": [str(p) for p in figures], "out": str(out)}
    write_json_atomic(out / "summary.json", summary)
    write_text_atomic(out / "summary.md", markdown_table(table))
    return summary


# ----------------------------------------------------------------------------- table
def summary_table(rows: list[Row]) -> list[Row]:
    """Per agent and setting, at the final point: mean and std over seeds."""
    table = []
    for key, group in _group(final_rows(rows), SETTING).items():
        rewards = np.array([r["cumulative_reward"] for r in group])
        errors = np.array([r["final_error_mm"] for r in group])
        table.append(
            {
                **dict(zip(SETTING, key, strict=True)),
                "seeds": len(group),
                "transitions": int(np.mean([r["transitions"] for r in group])),
                "cumulative_reward_mean": float(rewards.mean()),
                "cumulative_reward_std": float(rewards.std()),
                "final_error_mm_mean": float(errors.mean()),
                "final_error_mm_std": float(errors.std()),
                "wall_seconds_mean": float(np.mean([r["wall_seconds"] for r in group])),
            }
        )
    return sorted(table, key=lambda t: (not is_home(t), t["eval_task"], t["eval_goals"]))


def markdown_table(table: list[Row]) -> str:
    """The summary table in Markdown."""
    lines = [
        "| agent | learned on | evaluated on | seeds | transitions | cumulative reward "
        "| final error (mm) | learning wall (s) |",
        "|---|---|---|---:|---:|---:|---:|---:|",
    ]
    for t in table:
        lines.append(
            f"| {t['agent']} | {t['train_task']}, {GOALS[t['train_goals']]} "
            f"| {t['eval_task']}, {GOALS[t['eval_goals']]} | {t['seeds']} | {t['transitions']} "
            f"| {t['cumulative_reward_mean']:.2f} ± {t['cumulative_reward_std']:.2f} "
            f"| {t['final_error_mm_mean']:.1f} ± {t['final_error_mm_std']:.1f} "
            f"| {t['wall_seconds_mean']:.0f} |"
        )
    return "\n".join(lines) + "\n"


# ----------------------------------------------------------------------------- figures
def _figure() -> tuple[Any, Any]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt.subplots(figsize=(6.4, 4.0), dpi=120)


def curve(rows: list[Row]) -> tuple[list[float], list[float], list[float]]:
    """(transitions, mean, std) over seeds per evaluation point of one agent's rows."""
    xs, means, stds = [], [], []
    for _, group in sorted(_group(rows, ("eval",)).items()):
        rewards = np.array([r["cumulative_reward"] for r in group])
        xs.append(float(np.mean([r["transitions"] for r in group])))
        means.append(float(rewards.mean()))
        stds.append(float(rewards.std()))
    return xs, means, stds


def plot_curves(rows: list[Row], path: Path, title: str) -> Path:
    """Reward against transitions, one shaded curve per agent (and learning setting)."""
    fig, ax = _figure()
    groups = _group([r for r in rows if is_home(r)], ("agent", "train_task", "train_goals"))
    several = len({key[1:] for key in groups}) > 1
    for (agent, task, goals), group in groups.items():
        label = f"{agent} ({task}, {GOALS[goals]})" if several else agent
        shaded_curve(ax, *curve(group), label=label)
    ax.set_xlabel("transitions")
    ax.set_ylabel("cumulative reward per episode")
    ax.set_title(title)
    ax.grid(alpha=0.3)
    ax.legend()
    return save_figure(fig, path)


def plot_bars(bars: dict[str, dict[str, list[float]]], path: Path, title: str) -> Path:
    """Grouped bars: ``bars[agent][series]`` = per-seed rewards; mean with std error bars."""
    fig, ax = _figure()
    series = sorted({s for by_series in bars.values() for s in by_series})
    width = 0.8 / len(series)
    for i, name in enumerate(series):
        xs = [a for a, agent in enumerate(bars) if name in bars[agent]]
        values = [bars[agent][name] for agent in bars if name in bars[agent]]
        ax.bar(
            np.array(xs) + (i - (len(series) - 1) / 2) * width,
            [np.mean(v) for v in values],
            width,
            yerr=[np.std(v) for v in values],
            capsize=3,
            label=name,
        )
    ax.set_xticks(range(len(bars)), list(bars))
    ax.set_ylabel("final cumulative reward per episode")
    ax.set_title(title)
    ax.grid(alpha=0.3, axis="y")
    ax.legend()
    return save_figure(fig, path)


def _bars(rows: list[Row], series_of: Any) -> dict[str, dict[str, list[float]]]:
    bars: dict[str, dict[str, list[float]]] = defaultdict(lambda: defaultdict(list))
    for row in rows:
        bars[row["agent"]][series_of(row)].append(row["cumulative_reward"])
    return {agent: dict(by_series) for agent, by_series in bars.items()}


def draw_figures(rows: list[Row], plots: Path) -> list[Path]:
    """Every figure the rows allow, into ``plots``; returns their paths."""
    if not rows:
        return []
    figures = [
        plot_curves(
            rows,
            Path(plots) / "fig4_learning_curves.png",
            "Sample efficiency (cumulative reward vs transitions)",
        )
    ]
    final = final_rows(rows)
    bimanual = [r for r in final if r["eval_task"] == "bimanual"]
    if bimanual:
        mixed = len({r["eval_goals"] for r in bimanual}) > 1

        def learned_on(r: Row) -> str:
            goals = f", evaluated on {GOALS[r['eval_goals']]}" if mixed else ""
            return f"learned on {r['train_task']}{goals}"

        figures.append(
            plot_bars(
                _bars(bimanual, learned_on), Path(plots) / "fig5_bimanual.png", "Bimanual task"
            )
        )
    same_task = [r for r in final if r["eval_task"] == r["train_task"]]
    if any(r["eval_goals"] == "random" for r in same_task):

        def series(r: Row) -> str:
            return f"learned on {GOALS[r['train_goals']]}, evaluated on {GOALS[r['eval_goals']]}"

        figures.append(
            plot_bars(
                _bars(same_task, series), Path(plots) / "fig6_random_goals.png", "Random goals"
            )
        )
    mpc = [r for r in rows if r["agent"] in ("mpc", "mpc-offline")]
    if {r["agent"] for r in mpc} == {"mpc", "mpc-offline"}:
        figures.append(
            plot_curves(
                mpc, Path(plots) / "fig7_online_offline.png", "Online vs offline model learning"
            )
        )
    return figures
