"""What a real cell's faults cost closed-loop MPC: the same model, starts and goals, stepped in
this process and through a `dlo serve` cell in lockstep, in real time, with tracker delay,
lost commands and lost frames; against doing nothing and random actions from the same starts.

    pip install -c constraints.txt torch==2.13.0 -e ".[bridge]"
    dlo online --iters 3 --trials 5 --steps 200 --epochs 10 --lr 1e-3 --initial-episodes 2 \\
        --out runs/demo --overwrite                      # the README's main job: the model
    python examples/bridge/latency.py --checkpoint runs/demo/checkpoints/final.pt

Writes results/latency.{json,md} and results/latency.png beside this script.
"""

from __future__ import annotations

import argparse
import json
import re
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

HERE = Path(__file__).resolve().parent
#: (name, `dlo serve` flags or None for this process, extra `dlo control` flags)
SETTINGS = [
    ("in this process", None, []),
    ("cell, lockstep", [], []),
    ("cell, real time", ["--realtime"], []),
    ("real time, 10 ms delay", ["--realtime", "--delay-ms", "10"], []),
    ("real time, 20 ms delay", ["--realtime", "--delay-ms", "20"], []),
    ("real time, 40 ms delay", ["--realtime", "--delay-ms", "40"], []),
    ("5% commands lost", ["--drop-probability", "0.05"], []),
    ("20% commands lost", ["--drop-probability", "0.2"], []),
    ("20% frames lost, stop after 0.1 s", ["--frame-loss-probability", "0.2"],
     ["--stop-after-lost-s", "0.1"]),
]  # fmt: skip
REFERENCES = ["zero", "random"]


def dlo(*argv: str) -> dict:
    done = subprocess.run([sys.executable, "-m", "dlocli.cli", *argv, "--json"],
                          capture_output=True, text=True, check=True)  # fmt: skip
    return json.loads(done.stdout.strip().splitlines()[-1])


def control(goal: Path, seed: int, out: Path, *flags: str) -> dict:
    return dlo("control", "--goal", str(goal), "--seed", str(seed), "--out", str(out),
               "--overwrite", *flags)  # fmt: skip


def through_cell(serve_flags: list[str], run) -> dict:
    cell = subprocess.Popen(
        [sys.executable, "-m", "dlocli.cli", "serve", "--address", "tcp://127.0.0.1:*",
         *serve_flags], stderr=subprocess.PIPE, text=True,
    )  # fmt: skip
    try:
        address = re.search(r" at (tcp://\S+);", cell.stderr.readline()).group(1)
        return run("--cell", address)
    finally:
        cell.terminate()
        cell.wait()


def measure(checkpoint: Path, seeds: list[int], work: Path) -> dict:
    goals = {}
    for seed in seeds:
        goals[seed] = work / f"goal_{seed}.npy"
        dlo("goal", "--seed", str(seed), "--out", str(goals[seed]), "--overwrite")
    rows: dict[str, list[dict]] = {}
    for name in REFERENCES:
        rows[name] = [control(goals[s], s, work / "run", "--controller", name) for s in seeds]
    for name, serve_flags, flags in SETTINGS:
        rows[name] = []
        for seed in seeds:

            def run(*cell: str, seed=seed, flags=flags) -> dict:
                return control(goals[seed], seed, work / "run", "--checkpoint",
                               str(checkpoint), *flags, *cell)  # fmt: skip

            rows[name].append(run() if serve_flags is None else through_cell(serve_flags, run))
        print(f"{name:36s} {_mean(rows[name], 'final_error_mm'):7.1f} mm", flush=True)
    return rows


def _mean(runs: list[dict], key: str) -> float:
    return statistics.fmean(r.get(key, 0) for r in runs)


def _spread(runs: list[dict], key: str) -> float:
    return statistics.stdev(r[key] for r in runs) if len(runs) > 1 else 0.0


def table(rows: dict[str, list[dict]]) -> str:
    lines = ["| setting | final error (mm) | score | late steps (cell) | commands lost | "
             "tracking stops |", "|---|---:|---:|---:|---:|---:|"]  # fmt: skip
    initial = _mean(rows["zero"], "initial_error_mm")
    for name, runs in rows.items():
        lines.append(
            f"| {'doing nothing' if name == 'zero' else name} "
            f"| {_mean(runs, 'final_error_mm'):.1f} ± {_spread(runs, 'final_error_mm'):.1f} "
            f"| {_mean(runs, 'score'):.2f} | {_mean(runs, 'cell_late_steps'):.0f} "
            f"| {_mean(runs, 'cell_dropped_commands'):.0f} "
            f"| {_mean(runs, 'clipped_tracking_lost'):.0f} |"
        )
    return f"Initial error {initial:.1f} mm (mean of the starts).\n\n" + "\n".join(lines) + "\n"


def figure(rows: dict[str, list[dict]], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = list(rows)
    means = [_mean(rows[n], "final_error_mm") for n in names]
    fig, ax = plt.subplots(figsize=(8, 4.5))
    colours = ["0.6" if n in REFERENCES else "C0" for n in names]
    ax.barh(range(len(names)), means, color=colours, alpha=0.6, label="mean")
    for row, name in enumerate(names):  # each start: the spread of three is no error bar
        finals = [r["final_error_mm"] for r in rows[name]]
        ax.plot(finals, [row] * len(finals), "k.", label="each start" if row == 0 else None)
    ax.set_yticks(range(len(names)), ["doing nothing" if n == "zero" else n for n in names])
    ax.invert_yaxis()
    ax.axvline(_mean(rows["zero"], "initial_error_mm"), color="k", ls="--", lw=1,
               label="initial error")  # fmt: skip
    ax.set_xlabel("final shape error (mm)")
    ax.legend(loc="lower right")
    fig.tight_layout()
    fig.savefig(path, dpi=120)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--checkpoint", type=Path)
    parser.add_argument("--seeds", type=int, default=3)
    parser.add_argument("--replot", action="store_true", help="redraw from results/latency.json")
    args = parser.parse_args()
    results = HERE / "results"
    results.mkdir(exist_ok=True)
    if args.replot:
        figure(json.loads((results / "latency.json").read_text()), results / "latency.png")
        return
    with tempfile.TemporaryDirectory() as work:
        rows = measure(args.checkpoint, list(range(args.seeds)), Path(work))
    keep = ("initial_error_mm", "final_error_mm", "score", "late_steps", "cell_late_steps",
            "cell_dropped_commands", "clipped_tracking_lost", "latency_ms_median")  # fmt: skip
    slim = {name: [{k: r[k] for k in keep if k in r} for r in runs] for name, runs in rows.items()}
    (results / "latency.json").write_text(json.dumps(slim, indent=1) + "\n")
    (results / "latency.md").write_text(table(rows))
    figure(rows, results / "latency.png")
    print(table(rows))


if __name__ == "__main__":
    main()
