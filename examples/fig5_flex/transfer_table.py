"""The Fig. 5 transfer on the flex rod, seeds side by side: one table from the JSON files
``benchmarks/bimanual_transfer.py --online-only --json`` writes for each run and seed.

    python examples/fig5_flex/transfer_table.py EVAL_DIR examples/fig5_flex/transfer.json

EVAL_DIR holds ``{run}_s{seed}_{setting}.json``: ``run`` the single-gripper bench run with
the mirror option (its model transferred) or the bimanual one (its model learned on the
task), ``setting`` the planner's (``default``, or what ``--mpc`` changed). Each row: the mean
± std over seeds of the final error on the bimanual task, for each model and the references
(doing nothing, random actions and the held-end servo, evaluated beside each model on the
same episodes), and the ratio of the transferred model's error to the learned one's.
"""

from __future__ import annotations

import json
import re
import sys
from pathlib import Path

import numpy as np

NAME = re.compile(r"(?P<run>.+)_s(?P<seed>\d+)_(?P<setting>[^_]+)\.json")
#: the run whose model is transferred, and the run whose model learned on the task
TRANSFERRED, LEARNED = "bench_paper_mirror_flex", "bench_bimanual_flex"


def final_errors(eval_dir: Path) -> dict[tuple, dict[int, float]]:
    """(setting, goals, who) -> {seed: final error (mm)}; who is the run for its model's
    rows and the reference's name for the references (the same episodes in either run)."""
    found: dict[tuple, dict[int, float]] = {}
    for path in sorted(eval_dir.glob("*.json")):
        match = NAME.fullmatch(path.name)
        if match is None:
            continue
        run, seed, setting = match["run"], int(match["seed"]), match["setting"]
        for row in json.loads(path.read_text())["rows"]:
            who = run if row["model"].startswith("online") else row["model"]
            key = (setting, row["eval_goals"], who)
            found.setdefault(key, {})[seed] = row["final_error_mm"]
            found.setdefault((setting, row["eval_goals"], "initial"), {})[seed] = row[
                "initial_error_mm"
            ]
    return found


def table(found: dict[tuple, dict[int, float]]) -> list[dict]:
    """One row per (setting, goals) with both models' and the references' errors."""
    rows = []
    for setting, goals in sorted({(k[0], k[1]) for k in found}):
        cells = {who: found.get((setting, goals, who), {}) for who in
                 ("initial", "zero", "random", "held-end", TRANSFERRED, LEARNED)}  # fmt: skip
        seeds = sorted(set(cells[TRANSFERRED]) & set(cells[LEARNED]))
        row = {"setting": setting, "goals": goals, "seeds": seeds}
        for who, by_seed in cells.items():
            values = [by_seed[s] for s in seeds if s in by_seed]
            row[who] = {"per_seed": values, "mean": float(np.mean(values)) if values else None,
                        "std": float(np.std(values)) if values else None}  # fmt: skip
        if seeds:
            row["ratio"] = row[TRANSFERRED]["mean"] / row[LEARNED]["mean"]
        rows.append(row)
    return rows


def main(argv: list[str]) -> None:
    if len(argv) != 2:
        raise SystemExit(__doc__)
    rows = table(final_errors(Path(argv[0])))
    Path(argv[1]).write_text(json.dumps({"rows": rows}, indent=1) + "\n")
    for row in rows:
        print(row["setting"], row["goals"], row["seeds"],
              {k: v["mean"] and round(v["mean"], 2) for k, v in row.items() if isinstance(v, dict)},
              "ratio", round(row.get("ratio", float("nan")), 2))  # fmt: skip


if __name__ == "__main__":
    main(sys.argv[1:])
