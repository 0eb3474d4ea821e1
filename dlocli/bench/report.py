"""Results of ``dlo bench``: results.csv, the summary table and the figures, from result rows
(one row per agent x seed x evaluation point x evaluation setting; columns :data:`COLUMNS`).

Figures in the paper's style, mean +- std over seeds of each seed's mean cumulative reward
per evaluation episode (``zero``, doing nothing, drawn as the dashed reference):

- Fig. 4 ``fig4_learning_curves.png``: reward against transitions, every agent where it learned;
  ``fig4_training_trials.png``: the same for the agents' own training episodes (with their
  exploration noise: the paper's protocol);
- Fig. 5 ``fig5_bimanual.png``: final reward on the bimanual task, by the task learned on;
- Fig. 6 ``fig6_random_goals.png``: reward on random goals against transitions, after
  learning a fixed goal;
- Fig. 7 ``fig7_online_offline.png``: ``mpc`` (online) against ``mpc-offline``.

A figure is drawn only when the rows hold what it shows (e.g. Fig. 7 needs both mpc agents).
The summary leads with the score ``1 - final/initial`` (1 = on the goal, 0 = no better than
doing nothing) and the transitions at which each agent first closes half the initial error.
"""

from __future__ import annotations

import csv
import io
from collections import defaultdict
from pathlib import Path
from typing import Any

import numpy as np

from dlocli.bench.agents import is_reference
from dlocli.controllers.base import references
from dlocli.errors import BadInput
from dlocli.io import write_json_atomic, write_text_atomic
from dlocli.plots import (
    agent_colour,
    figure,
    integer_ticks,
    save_figure,
    shaded_curve,
)

Row = dict[str, Any]
GOALS = {"fixed": "fixed goal", "random": "random goals"}
SETTING = ("agent", "train_task", "train_goals", "eval_task", "eval_goals")
HALF = 0.5  # the score at which an agent has closed half the initial error


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
#: columns added later: results of older runs read them as missing (nan)
NEW_COLUMNS: dict[str, type] = {
    "initial_error_mm": float,
    "score": float,
    "score_std": float,
    "train_reward": float,
    "train_episodes": float,
}


def _typed(kind: type, text: str | None) -> Any:
    return float("nan") if text in (None, "") and kind is float else kind(text)


def write_results_csv(path: Path, rows: list[dict[str, Any]]) -> None:
    buffer = io.StringIO()
    writer = csv.DictWriter(
        buffer, fieldnames=[*COLUMNS, *NEW_COLUMNS], extrasaction="ignore", restval=""
    )
    writer.writeheader()
    writer.writerows(rows)
    write_text_atomic(path, buffer.getvalue())


def read_results_csv(path: Path) -> list[dict[str, Any]]:
    """results.csv with typed values; BadInput if it is not one."""
    if not Path(path).is_file():
        raise BadInput(f"{path} does not exist; pass the --out directory of a `dlo bench` run")
    not_results = f"{path} is not a dlo bench results.csv"
    kinds = {**COLUMNS, **NEW_COLUMNS}
    with open(path, newline="") as f:
        reader = csv.DictReader(f)
        try:
            if set(COLUMNS) - set(reader.fieldnames or []):
                raise BadInput(f"{not_results} (missing columns)")
            return [{k: _typed(kind, row.get(k)) for k, kind in kinds.items()} for row in reader]
        # undecodable bytes (a UnicodeDecodeError is a ValueError), NUL bytes, over-long
        # fields, values of the wrong type or missing: another file, damaged or not a CSV
        except (csv.Error, ValueError, TypeError) as exc:
            raise BadInput(
                f"{not_results} ({str(exc)[:120]}); pass the --out directory of a `dlo bench` run"
            ) from exc


def write_summary(
    out: Path, table: list[dict[str, Any]], figures: list[Path], extra: dict[str, Any]
) -> dict[str, Any]:
    """summary.json and summary.md (the table in Markdown)."""
    results = {
        t["agent"]: {
            name: t[f"{name}_mean"]
            for name in ("score", "initial_error_mm", "final_error_mm", "cumulative_reward")
        }
        for t in table
        if is_home(t)
    }
    summary = {
        **extra,
        "results": results,
        "table": table,
        "figures": [str(p) for p in figures],
        "out": str(out),
    }
    write_json_atomic(out / "summary.json", summary)
    write_text_atomic(out / "summary.md", markdown_table(table) + "\n" + markdown_half(table))
    return summary


# ----------------------------------------------------------------------------- table
def _mean_std(group: list[Row], key: str) -> tuple[float, float]:
    values = np.array([r.get(key, np.nan) for r in group], dtype=float)
    return float(values.mean()), float(values.std())


def summary_table(rows: list[Row]) -> list[Row]:
    """Per agent and setting, at the final point: mean and std over seeds, and the
    transitions at which the seeds' mean score first reaches one half."""
    table = []
    for key, group in _group(final_rows(rows), SETTING).items():
        entry: Row = {
            **dict(zip(SETTING, key, strict=True)),
            "seeds": len(group),
            "transitions": int(np.mean([r["transitions"] for r in group])),
        }
        for name in ("score", "initial_error_mm", "final_error_mm", "cumulative_reward"):
            entry[f"{name}_mean"], entry[f"{name}_std"] = _mean_std(group, name)
        entry["wall_seconds_mean"] = _mean_std(group, "wall_seconds")[0]
        setting = [r for r in rows if tuple(r[k] for k in SETTING) == key]
        entry["half_closed_at"] = half_closed_at(setting)
        table.append(entry)
    return sorted(table, key=lambda t: (not is_home(t), t["eval_task"], t["eval_goals"], _rank(t)))


def _rank(row: Row) -> tuple[int, str]:
    """The references first, in their rank order, then the agents by name."""
    reference = references().get(row["agent"])
    return (reference.rank if reference else len(references()), row["agent"])


def half_closed_at(rows: list[Row]) -> int | None:
    """First transitions at which the mean score over seeds reaches one half (None: never)."""
    for _, group in sorted(_group(rows, ("eval",)).items()):
        if _mean_std(group, "score")[0] >= HALF:
            return int(np.mean([r["transitions"] for r in group]))
    return None


def _cell(t: Row, name: str, digits: int) -> str:
    mean, std = t[f"{name}_mean"], t[f"{name}_std"]
    return "–" if np.isnan(mean) else f"{mean:.{digits}f} ± {std:.{digits}f}"


def markdown_table(table: list[Row]) -> str:
    """The summary table in Markdown, led by the score (1 - final/initial error)."""
    lines = [
        "| agent | learned on | evaluated on | seeds | transitions | score "
        "| initial error (mm) | final error (mm) | cumulative reward | learning wall (s) |",
        "|---|---|---|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for t in table:
        lines.append(
            f"| {t['agent']} | {t['train_task']}, {GOALS[t['train_goals']]} "
            f"| {t['eval_task']}, {GOALS[t['eval_goals']]} | {t['seeds']} | {t['transitions']} "
            f"| {_cell(t, 'score', 2)} | {_cell(t, 'initial_error_mm', 1)} "
            f"| {_cell(t, 'final_error_mm', 1)} | {_cell(t, 'cumulative_reward', 2)} "
            f"| {t['wall_seconds_mean']:.0f} |"
        )
    return "\n".join(lines) + "\n"


def markdown_half(table: list[Row]) -> str:
    """Per agent where it learned: the transitions at which it first closes half the initial
    error (mean score over seeds >= 0.5), and the ratio to ``mpc``'s."""
    home = [t for t in table if is_home(t)]
    mpc = next((t["half_closed_at"] for t in home if t["agent"] == "mpc"), None)
    lines = [
        "Transitions until half the initial error is closed (mean score over seeds >= 0.5):",
        "",
        "| agent | transitions | ratio to mpc |",
        "|---|---:|---:|",
    ]
    for t in home:
        at = t["half_closed_at"]
        ratio = f"{at / mpc:.1f}" if at is not None and mpc else "–"
        text = f"{at}" if at is not None else f"not within budget ({t['transitions']})"
        lines.append(f"| {t['agent']} | {text} | {ratio} |")
    return "\n".join(lines) + "\n"


# ----------------------------------------------------------------------------- figures
def curve(
    rows: list[Row], key: str = "cumulative_reward"
) -> tuple[list[float], list[float], list[float]]:
    """(transitions, mean, std) over seeds per evaluation point of one agent's rows."""
    xs, means, stds = [], [], []
    for _, group in sorted(_group(rows, ("eval",)).items()):
        mean, std = _mean_std(group, key)
        if np.isnan(mean):
            continue
        xs.append(float(np.mean([r["transitions"] for r in group])))
        means.append(mean)
        stds.append(std)
    return xs, means, stds


def plot_curves(
    rows: list[Row], path: Path, title: str, key: str = "cumulative_reward", ylabel: str = ""
) -> Path:
    """``key`` against transitions, one shaded curve per agent (and learning setting); the
    ``zero`` reference dashed."""
    fig, ax = figure()
    groups = _group(rows, ("agent", "train_task", "train_goals"))
    settings = sorted({key[1:] for key in groups})  # a line style per learning setting
    for (agent, task, goals), group in sorted(groups.items(), key=lambda item: _rank(item[1][0])):
        label = f"{agent} ({task}, {GOALS[goals]})" if len(settings) > 1 else agent
        xs, means, stds = curve(group, key)
        if not xs:
            continue
        reference = references().get(agent)
        if reference:  # a thin line without band, under the agents' curves
            ax.plot(xs, means, reference.line, color=reference.colour, lw=1.5,
                    label=f"{label} ({reference.label})", zorder=1)  # fmt: skip
        else:
            style = ["-", "--", "-.", ":"][settings.index((task, goals)) % 4]
            shaded_curve(ax, xs, means, stds, label, agent_colour(agent), style)
    ax.set_xlabel("transitions")
    integer_ticks(ax.xaxis)
    ax.set_ylabel(ylabel or "cumulative reward per episode")
    ax.set_title(title)
    ax.grid(alpha=0.3)
    ax.legend(fontsize="small")
    return save_figure(fig, path)


def plot_bars(bars: dict[str, dict[str, list[float]]], path: Path, title: str) -> Path:
    """Grouped bars: ``bars[agent][series]`` = per-seed rewards; mean with std error bars.
    Each agent's group holds only its own series, centred on its tick."""
    fig, ax = figure(figsize=(max(6.4, 1.9 * len(bars)), 4.0))
    series = sorted({s for by_series in bars.values() for s in by_series})
    colours = {name: f"C{i}" for i, name in enumerate(series)}
    width = 0.8 / max(len(by_series) for by_series in bars.values())
    for a, by_series in enumerate(bars.values()):
        for i, name in enumerate(sorted(by_series)):
            values = by_series[name]
            ax.bar(
                a + (i - (len(by_series) - 1) / 2) * width,
                np.mean(values),
                width,
                yerr=np.std(values),
                capsize=3,
                color=colours[name],
            )
    for name in series:  # one legend entry per series
        ax.bar(0, 0, 0, color=colours[name], label=name)
    ax.set_xticks(range(len(bars)), [a.replace(" [", "\n[") for a in bars], fontsize="small")
    ax.set_ylabel("final cumulative reward per episode")
    ax.set_title(title)
    ax.grid(alpha=0.3, axis="y")
    ax.legend()
    return save_figure(fig, path)


def _references_once(rows: list[Row]) -> list[Row]:
    """``rows`` with each reference's (zero, random) evaluation of a seed once: a run
    learning on either task evaluates them alike on the bimanual one."""
    seen, kept = set(), []
    for row in rows:
        key = (row["agent"], row["seed"], row["eval_goals"])
        if not is_reference(row["agent"]) or key not in seen:
            seen.add(key)
            kept.append(row)
    return kept


def _bars(rows: list[Row], series_of: Any) -> dict[str, dict[str, list[float]]]:
    """``bars[agent][series]``, the agents in the tables' order (references first)."""
    bars: dict[str, dict[str, list[float]]] = defaultdict(lambda: defaultdict(list))
    for row in sorted(rows, key=_rank):
        bars[row["agent"]][series_of(row)].append(row["cumulative_reward"])
    return {agent: dict(by_series) for agent, by_series in bars.items()}


def draw_figures(rows: list[Row], plots: Path) -> list[Path]:
    """Every figure the rows allow, into ``plots``; returns their paths."""
    if not rows:
        return []
    home = [r for r in rows if is_home(r)]
    figures = [
        plot_curves(
            home,
            Path(plots) / "fig4_learning_curves.png",
            "Sample efficiency (noise-free evaluation episodes)",
        )
    ]
    if any(not np.isnan(r.get("train_reward", np.nan) or np.nan) for r in home):
        figures.append(
            plot_curves(
                home,
                Path(plots) / "fig4_training_trials.png",
                "Sample efficiency (the agents' own training episodes)",
                key="train_reward",
                ylabel="cumulative reward per training episode",
            )
        )
    final = final_rows(rows)
    # the goal mode each agent learned (random goals after a fixed one are Fig. 6's)
    bimanual = [
        r for r in final if r["eval_task"] == "bimanual" and r["eval_goals"] == r["train_goals"]
    ]
    if bimanual:
        mixed = len({r["eval_goals"] for r in bimanual}) > 1

        def learned_on(r: Row) -> str:
            goals = f", evaluated on {GOALS[r['eval_goals']]}" if mixed else ""
            learned = (
                "does not learn" if is_reference(r["agent"]) else f"learned on {r['train_task']}"
            )
            return learned + goals

        figures.append(
            plot_bars(
                _bars(_references_once(bimanual), learned_on),
                Path(plots) / "fig5_bimanual.png",
                "Bimanual task",
            )
        )
    transfer = [
        r
        for r in rows
        if r["eval_task"] == r["train_task"] and r["train_goals"] == "fixed"
        if r["eval_goals"] == "random"
    ]
    if transfer:
        figures.append(
            plot_curves(
                transfer,
                Path(plots) / "fig6_random_goals.png",
                "Random goals, after learning a fixed goal",
            )
        )
    mpc = [r for r in home if r["agent"] in ("mpc", "mpc-offline")]
    if {r["agent"] for r in mpc} == {"mpc", "mpc-offline"}:
        figures.append(
            plot_curves(
                mpc, Path(plots) / "fig7_online_offline.png", "Online vs offline model learning"
            )
        )
    return figures
