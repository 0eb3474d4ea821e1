"""Reports of a `dlo online` run at the paper's scale, as the READMEs here quote them.

    python examples/online_paper/report.py table RUN_DIR
    python examples/online_paper/report.py plot OUT.png LABEL=RUN_DIR [LABEL=RUN_DIR ...]

`table`: one Markdown row per iteration: final shape error of the iteration's MPC trials
(mean, median, worst), doing nothing, random actions and the held-end servo from the same
starts and goals (means, from the run's references.json; "–" where a run predates the servo),
and the trials' cumulative reward (mean ± std) beside doing nothing's. `plot`: each run's mean
and median final error per iteration against doing nothing (and the servo, where the run has
it), on one log axis, e.g. `"flex rod (MuJoCo 4.0.1)=examples/online_paper_flex"
"composite cable (MuJoCo 3.17)=examples/online_paper"`.
"""

from __future__ import annotations

import csv
import json
import statistics
import sys
from collections import defaultdict
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402


def by_iteration(rows: list[dict[str, str]], key: str) -> dict[int, list[float]]:
    grouped: dict[int, list[float]] = defaultdict(list)
    for row in rows:
        grouped[int(row["iteration"])].append(float(row[key]))
    return grouped


def reference_means(run: Path, kind: str, key: str) -> dict[int, float]:
    """Per iteration, the mean of reference ``kind``'s ``key`` ({} where the run has none)."""
    grouped: dict[int, list[float]] = defaultdict(list)
    references = json.loads((run / "references.json").read_text()).get(kind, {})
    for trial, values in references.items():
        grouped[int(trial.split("/")[0])].append(values[key])
    return {iteration: statistics.fmean(v) for iteration, v in grouped.items()}


def table(run: Path) -> str:
    rows = list(csv.DictReader((run / "metrics.csv").open()))
    final, reward = by_iteration(rows, "final_error_mm"), by_iteration(rows, "cumulative_reward")
    transitions = by_iteration(rows, "transitions")
    zero, random, servo = (
        reference_means(run, k, "final_error_mm") for k in ("zero", "random", "held-end")
    )
    zero_reward = reference_means(run, "zero", "cumulative_reward")
    lines = [
        "| iteration | transitions | final error (mm): mean | median | worst | doing nothing"
        " | random actions | held-end servo | reward | doing nothing's reward |",
        "|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for k in sorted(final):
        errors, rewards = final[k], reward[k]
        spread = statistics.pstdev(rewards)
        held = f"{servo[k]:.1f}" if k in servo else "–"
        lines.append(
            f"| {k} | {max(transitions[k]):,.0f} | {statistics.fmean(errors):.1f}"
            f" | {statistics.median(errors):.1f} | {max(errors):.1f} | {zero[k]:.1f}"
            f" | {random[k]:.1f} | {held} | {statistics.fmean(rewards):.1f} ± {spread:.1f}"
            f" | {zero_reward[k]:.1f} |"
        )
    return "\n".join(lines)


def plot(out: Path, runs: dict[str, Path]) -> None:
    figure, axes = plt.subplots(figsize=(7, 5))
    for index, (label, run) in enumerate(runs.items()):
        rows = list(csv.DictReader((run / "metrics.csv").open()))
        final = by_iteration(rows, "final_error_mm")
        zero = reference_means(run, "zero", "final_error_mm")
        iterations = sorted(final)
        color = f"C{index}"
        mean = [statistics.fmean(final[k]) for k in iterations]
        median = [statistics.median(final[k]) for k in iterations]
        axes.plot(iterations, mean, "o-", color=color, label=f"{label}: MPC, mean")
        axes.plot(iterations, median, "s:", color=color, label=f"{label}: MPC, median")
        axes.plot(iterations, [zero[k] for k in iterations], "--", color=color, alpha=0.6,
                  label=f"{label}: doing nothing, mean")  # fmt: skip
        servo = reference_means(run, "held-end", "final_error_mm")
        if servo:
            axes.plot(iterations, [servo[k] for k in iterations], "-.", color=color, alpha=0.6,
                      label=f"{label}: held-end servo, mean")  # fmt: skip
    axes.set_yscale("log")
    axes.set_xlabel("iteration (50 MPC trials each)")
    axes.set_ylabel("final shape error (mm)")
    axes.set_xticks(range(1, 21))
    axes.grid(True, which="both", alpha=0.3)
    axes.legend(fontsize=7, ncol=2, loc="upper center", bbox_to_anchor=(0.5, -0.18))
    figure.tight_layout()
    out.parent.mkdir(parents=True, exist_ok=True)
    figure.savefig(out, dpi=120, bbox_inches="tight")  # the legend sits below the axes


def main(argv: list[str]) -> None:
    if len(argv) == 2 and argv[0] == "table":
        print(table(Path(argv[1])))
    elif len(argv) >= 3 and argv[0] == "plot":
        plot(
            Path(argv[1]), {label: Path(run) for label, run in (a.split("=", 1) for a in argv[2:])}
        )
    else:
        raise SystemExit(__doc__.split("\n\n")[1])


if __name__ == "__main__":
    main(sys.argv[1:])
