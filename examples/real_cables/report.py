"""Collect the real-cable runs of run.sh into a table and a figure.

    python examples/real_cables/report.py [runs/real]

Reads RUNS/<cable>/<model>-s<seed>-eval/{summary,error_by_frame}.json (runs without the
curves enter the tables only) and writes, beside this script,
results.json, results.md and horizon.png: per cable, the DEFORM score of each model (mean ±
std over seeds) next to the published rows and the references, with the longest training
run's time; results.md keeps its notes below the tables; the figure shows the score of the
rollout cut at each horizon, so its right end is the benchmark score.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np

HERE = Path(__file__).parent
CABLES = ("DLO1", "DLO2", "DLO3", "DLO4")
#: DEFORM (Chen et al., CoRL 2024) Table 1, cm, and CPU time per step as printed
PUBLISHED = {
    "XPBD (physics)": ((4.00, 3.85, 3.80, 3.62), "13–15 ms"),
    "DRM (physics)": ((3.64, 4.16, 3.21, 4.02), "4.3–4.5 ms"),
    "Bi-LSTM (Yan et al. 2020)": ((1.98, 1.75, 1.10, 1.75), "0.3–0.4 ms"),
    "GNN (Wang et al. 2022)": ((3.41, 2.23, 2.15, 2.49), "16–17 ms"),
    "DER (physics)": ((1.96, 1.91, 1.86, 1.50), "17–18 ms"),
    "DEFORM": ((1.01, 0.97, 0.77, 0.85), "9–10 ms"),
}
#: results.md keeps what follows this line (written by hand) when the tables are rewritten
NOTES = "<!-- notes: kept by report.py -->"
REFERENCES = {
    "freeze": "freeze the free markers at frame 1",
    "straight_line": "straight line between the held ends",
}


def collect(runs: Path) -> dict:
    results: dict = {}
    for cable in CABLES:
        for summary_path in sorted((runs / cable).glob("*-s*-eval/summary.json")):
            model, seed = summary_path.parent.name.removesuffix("-eval").rsplit("-s", 1)
            summary = json.loads(summary_path.read_text())
            curves_path = summary_path.parent / "error_by_frame.json"  # a run may lack it
            curves = json.loads(curves_path.read_text()) if curves_path.is_file() else None
            entry = results.setdefault(cable, {}).setdefault(model, {"seeds": {}})
            trained = json.loads((runs / cable / f"{model}-s{seed}" / "summary.json").read_text())
            entry["seeds"][seed] = {
                "score_cm": summary["model_score_cm"],
                "train_seconds": trained["seconds"],
                "ms_per_step": summary["ms_per_step_1_thread"],
                "horizons_mm": {
                    k.split("_")[-1]: v
                    for k, v in summary.items()
                    if k.startswith("model_error_mm_")
                },  # fmt: skip
                "abs_error_cm": curves and curves["abs_error_cm"]["model"],
            }
            for ref in REFERENCES:
                reference = {
                    "score_cm": summary[f"{ref}_score_cm"],
                    "abs_error_cm": curves and curves["abs_error_cm"][ref],
                }
                if not results[cable].get(ref, {}).get("abs_error_cm"):
                    results[cable][ref] = reference
    for cable in results.values():
        for entry in cable.values():
            if "seeds" in entry:
                seeds = entry["seeds"].values()
                scores = [s["score_cm"] for s in seeds]
                entry["mean_cm"], entry["std_cm"] = float(np.mean(scores)), float(np.std(scores))
                entry["ms_per_step"] = float(np.median([s["ms_per_step"] for s in seeds]))
                entry["train_seconds"] = float(max(s["train_seconds"] for s in seeds))
    return results


def models_of(results: dict) -> list[str]:
    return sorted({m for c in results.values() for m, e in c.items() if "seeds" in e})


def table(results: dict) -> str:
    head = (
        "| method (cm, mean abs. error per coordinate, 5 s open loop) | "
        + " | ".join(CABLES)
        + " | time per step | training (longest run) |"
    )
    lines = [head, "|---|" + "---:|" * len(CABLES) + "---|---|"]
    for ref, words in REFERENCES.items():
        row = [f"{results[c][ref]['score_cm']:.2f}" if c in results else "–" for c in CABLES]
        lines.append(f"| {words} | " + " | ".join(row) + " | – | – |")
    for name, (scores, time) in PUBLISHED.items():
        lines.append(
            f"| {name}, published | " + " | ".join(f"{s:.2f}" for s in scores) + f" | {time} | – |"
        )
    for model in models_of(results):
        cells, times, training = [], [], []
        for c in CABLES:
            e = results.get(c, {}).get(model)
            cells.append(
                f"**{e['mean_cm']:.2f}** ± {e['std_cm']:.2f} ({len(e['seeds'])})" if e else "–"
            )
            if e:
                times.append(e["ms_per_step"])
                training.append(e["train_seconds"])
        t = f"{min(times):.2f}–{max(times):.2f} ms" if times else "–"
        trained = f"{max(training) / 60:.1f} min" if training else "–"
        lines.append(
            f"| dlocli `{model}` (mean ± std, seeds) | "
            + " | ".join(cells)
            + f" | {t} | {trained} |"
        )
    return "\n".join(lines)


def horizon_table(results: dict) -> str:
    keys = ("0.5s", "1s", "2s", "5s")
    lines = ["| cable | model | " + " | ".join(keys) + " |", "|---|---|" + "---:|" * len(keys)]
    for c in CABLES:
        for model in models_of(results):
            e = results.get(c, {}).get(model)
            if e:
                vals = [np.mean([s["horizons_mm"][k] for s in e["seeds"].values()]) for k in keys]
                lines.append(f"| {c} | `{model}` | " + " | ".join(f"{v:.1f}" for v in vals) + " |")
    return "\n".join(lines)


def figure(results: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(CABLES), figsize=(16, 4), sharey=True)
    colours = {
        "in-bilstm": "tab:blue",
        "mlp": "tab:orange",
        "mlp-long": "tab:cyan",
        "attention": "tab:purple",
        "freeze": "tab:gray",
        "straight_line": "tab:brown",
    }
    for ax, (i, cable) in zip(axes, enumerate(CABLES), strict=True):
        for name, entry in results.get(cable, {}).items():
            curves = (
                [s["abs_error_cm"] for s in entry["seeds"].values()]
                if "seeds" in entry
                else [entry["abs_error_cm"]]
            )
            if not all(curves):  # runs whose curves were not kept are left out of the figure
                continue
            per_frame = np.mean(curves, 0)[2:]
            running = np.cumsum(per_frame) / np.arange(1, len(per_frame) + 1)
            t = np.arange(1, len(running) + 1) / 100.0
            style = "-" if "seeds" in entry else ":"
            ax.plot(t, running, style, color=colours.get(name), label=name.replace("_", " "))
        for label, colour in (
            ("DEFORM", "black"),
            ("DER (physics)", "tab:red"),
            ("Bi-LSTM (Yan et al. 2020)", "tab:green"),
        ):
            ax.axhline(
                PUBLISHED[label][0][i],
                color=colour,
                lw=0.8,
                ls="--",
                label=f"{label.split(' (')[0]}, published",
            )
        ax.set_title(cable)
        ax.set_xlabel("horizon (s)")
        ax.grid(alpha=0.3)
    axes[0].set_ylabel("DEFORM score of the rollout up to the horizon (cm)")
    axes[-1].legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def main() -> None:
    runs = Path(sys.argv[1] if len(sys.argv) > 1 else "runs/real")
    results = collect(runs)
    curves = [s.get("abs_error_cm") for c in results.values() for e in c.values()
              for s in e.get("seeds", {}).values()]  # fmt: skip
    if all(curves):  # a run without its curves leaves the committed figure as it is
        figure(results, HERE / "horizon.png")
    slim = {c: {m: {k: v for k, v in e.items() if k != "abs_error_cm"} for m, e in models.items()}
            for c, models in results.items()}  # fmt: skip
    for models in slim.values():
        for e in models.values():
            for s in e.get("seeds", {}).values():
                s.pop("abs_error_cm", None)
    (HERE / "results.json").write_text(json.dumps(slim, indent=1) + "\n")
    text = (
        table(results)
        + "\n\nFree markers' mean Euclidean error (mm) at each horizon, mean over seeds:\n\n"
        + horizon_table(results)
        + "\n"
    )
    path = HERE / "results.md"
    notes = path.read_text().partition(NOTES)[2] if path.is_file() else "\n"
    path.write_text(text + "\n" + NOTES + notes)
    print(text)


if __name__ == "__main__":
    main()
