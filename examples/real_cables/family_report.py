"""Gather family_leave_one_out.sh's runs into examples/real_cables/family_leave_one_out.json:
per left-out cable, trained without and with the simulated family, the eval score (cm) of
the mean code, the code picked from one recording (no gradient) and the code fitted to it
alone, beside freezing the cable; with the family, how many simulated cables it held.

    python examples/real_cables/family_report.py OUT SPEC SEED [SOURCES [STEPS]]

With STEPS (the runs' update steps, where the script overrode the spec's) the file is
family_leave_one_out_STEPS.json; with SOURCES "all" (the family driven by every training
cable's motion) its name ends in _all; a recipe other than arc-mlp-coded-small names it
(family_leave_one_out_RECIPE...), a seed other than 0 ends it (..._seedS). A fold run with
the family only (no OUT/CABLE-without) is reported with it alone.

    python examples/real_cables/family_report.py seeds TARGET REPORT [REPORT ...]

writes TARGET (a name in examples/real_cables/): per cable, each seed's report's scores
side by side and their mean over the seeds. The summary keeps every seed's scores, so the
docs cite it alone and the seeds' own reports (..._seedS.json) need not be kept.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent
SMALL = "arc-mlp-coded-small"  # the script's default recipe: its files carry no recipe name


def read(path: Path) -> dict:
    return json.loads(path.read_text())


def run_row(run: Path) -> dict:
    mean = read(run / "mean-eval.json")
    picked, code = read(run / "pick.json"), read(run / "code.json")
    row = {
        "mean_code_cm": mean["model_score_cm"],
        "picked_cm": read(run / "pick-eval.json")["model_score_cm"],
        "picked": picked["picked"],
        "pick_seconds": picked["pick_seconds"],
        "code_fitted_cm": read(run / "code-eval.json")["model_score_cm"],
        "code_fit_seconds": code["fit_seconds"],
        "train_seconds": read(run / "train.json").get("seconds"),
    }
    if (run / "family" / "summary.json").is_file():
        family = read(run / "family" / "summary.json")
        row["simulated_cables"] = family["datasets"]
        row["simulated_cables_drawn"] = family["cables"]
        sources = family.get("sources") or [{"source": family["source"]}]  # older summaries
        row["family_sources"] = [s["source"] for s in sources]
    return row


def main(out: Path, spec: str, seed: int, sources: str = "first", steps: int | None = None) -> None:
    cables = sorted({p.name.rsplit("-", 1)[0] for p in out.glob("DLO*-with*")})
    rows = {}
    for cable in cables:
        runs = {f: out / f"{cable}-{f}" for f in ("without", "with")}
        runs = {f: r for f, r in runs.items() if (r / "code-eval.json").is_file()}
        if "with" not in runs:
            continue
        freeze = read(runs["with"] / "mean-eval.json")["freeze_score_cm"]
        rows[cable] = {"freeze_cm": freeze, **{f: run_row(r) for f, r in runs.items()}}
    recipe = Path(spec).stem
    name = "family_leave_one_out" + ("" if recipe == SMALL else f"_{recipe}")
    name += (f"_{steps}" if steps else "") + ("_all" if sources == "all" else "")
    name += f"_seed{seed}" if seed else ""
    target = HERE / f"{name}.json"
    report = {"spec": spec, "seed": seed, "update_steps": steps, "sources": sources, "cables": rows}
    target.write_text(json.dumps(report, indent=1) + "\n")
    for cable, row in rows.items():
        print(cable, row)


#: the scores the seeds' summary averages, per training (without / with the family)
SCORES = ("mean_code_cm", "picked_cm", "code_fitted_cm")


def over_seeds(target: str, reports: list[Path]) -> None:
    """Each cable's scores of every seed's report and their mean (module docstring)."""
    found = [read(r) for r in reports]
    summary: dict[str, dict] = {}
    for cable in found[0]["cables"]:
        for family in ("without", "with"):
            rows = [f["cables"][cable][family] for f in found if cable in f["cables"]]
            summary.setdefault(cable, {})[family] = {
                key: {"seeds": [r[key] for r in rows],
                      "mean": round(sum(r[key] for r in rows) / len(rows), 4)}
                for key in SCORES
            }  # fmt: skip
    seeds = [f["seed"] for f in found]
    out = {"spec": found[0]["spec"], "sources": found[0].get("sources"), "seeds": seeds,
           "reports": [r.name for r in reports], "cables": summary}  # fmt: skip
    (HERE / target).write_text(json.dumps(out, indent=1) + "\n")
    for cable, row in summary.items():
        print(cable, {f: {k: v["mean"] for k, v in row[f].items()} for f in row})


if __name__ == "__main__" and sys.argv[1] == "seeds":
    over_seeds(sys.argv[2], [Path(p) for p in sys.argv[3:]])
elif __name__ == "__main__":
    main(Path(sys.argv[1]), sys.argv[2], int(sys.argv[3]),
         sys.argv[4] if len(sys.argv) > 4 else "first",
         int(sys.argv[5]) if len(sys.argv) > 5 else None)  # fmt: skip
