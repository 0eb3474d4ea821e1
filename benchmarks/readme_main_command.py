"""Does the README's main command give the numbers of docs/getting-started.md on this machine?

    python benchmarks/readme_main_command.py [--out DIR]

Runs the command of "Two commands on a fresh machine" (read from the README) and checks the
mean final shape error of each iteration's MPC trials, the last score and doing nothing
against the ranges measured for the rod it ran (the installed MuJoCo's: RANGES below, as
docs/getting-started.md states them); float rounding differs by CPU. Prints each number, its
range, and PASS or FAIL; exits 1 if any is outside.
"""

from __future__ import annotations

import argparse
import json
import shlex
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from readme_commands import commands, split_main  # this folder: a script's first path entry


def readme_command() -> list[str]:
    """The README's main command after `dlo`, without its --out (this script picks one)."""
    words = shlex.split(split_main(commands()[0])[1])[1:]
    at = words.index("--out")
    return words[:at] + words[at + 2 :]


#: (low, high) around the runs measured with the rods' planner defaults, AMD EPYC, seeds 0-4
#: (benchmarks/main_job_seeds.py): on the flex rod (MuJoCo 4.0.1, of 2026-12-08: the pull
#: towards the held-end servo, the roll from the rest states) 1.7-5.8 / 2.1-5.0 / 0.5-5.4 mm,
#: scores 0.952-0.996; on the composite cable (MuJoCo 3.17, of 2026-12-07: the pull, the roll
#: left to the model) 2.4-9.6 / 1.8-3.6 / 1.1-6.6 mm, scores 0.926-0.991. The ranges widen
#: those by half again for another CPU's rounding; doing nothing is seed 0's, which no model
#: changes. Keyed by the backend the run used.
RANGES = {
    "mujoco-flex": {
        "iteration 1 final error (mm)": (1.0, 10.0),
        "iteration 2 final error (mm)": (1.0, 9.0),
        "iteration 3 final error (mm)": (0.2, 8.5),
        "iteration 3 score": (0.90, 1.0),
        "doing nothing, iteration 3 (mm)": (127.5, 128.5),
    },
    "mujoco": {
        "iteration 1 final error (mm)": (1.0, 14.0),
        "iteration 2 final error (mm)": (1.0, 6.0),
        "iteration 3 final error (mm)": (1.0, 9.5),
        "iteration 3 score": (0.90, 0.99),
        "doing nothing, iteration 3 (mm)": (125.5, 126.7),
    },
}

#: the README's table of the main job over seeds 0-4 (benchmarks/main_job_seeds.py) with each
#: rod's planner defaults: another CPU's run of seed 0 draws another model, so its score is
#: checked against the seeds' range
RESULTS = Path(__file__).resolve().parent / "results"
SEEDS = {"mujoco-flex": RESULTS / "main_job_seeds_rest_roll.json",
         "mujoco": RESULTS / "main_job_seeds.json"}  # fmt: skip


def seeds_range(backend: str) -> tuple[float, float]:
    """(worst, best) score of the README's command on ``backend``'s rod over seeds 0-4, and
    over any other float rounding measured (groups ``default-...``, e.g. one thread)."""
    groups = json.loads(SEEDS[backend].read_text())["groups"]
    scores = [score for name, group in groups.items()
              if name == f"{backend}/default" or name.startswith(f"{backend}/default-")
              for score in group["scores"]]  # fmt: skip
    return min(scores), max(scores)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, default=None, help="run directory (default: temp)")
    args = parser.parse_args()
    out = args.out or Path(tempfile.mkdtemp()) / "demo"
    start = time.perf_counter()
    subprocess.run([sys.executable, "-m", "dlocli", *readme_command(), "--out", str(out), "--json"],
                   check=True, stdout=subprocess.DEVNULL)  # fmt: skip
    seconds = time.perf_counter() - start
    curve = json.loads((out / "summary.json").read_text())["curve"]
    found = {
        f"iteration {c['iteration']} final error (mm)": c["final_error_mm_mean"] for c in curve
    }
    found["iteration 3 score"] = curve[-1]["score_mean"]
    found["doing nothing, iteration 3 (mm)"] = curve[-1]["zero_final_error_mm_mean"]
    backend = json.loads((out / "spec.json").read_text())["backend"]["name"]
    print(f"backend {backend}")
    ok = True
    ranges = {**RANGES[backend], "iteration 3 score, all measured": seeds_range(backend)}
    found["iteration 3 score, all measured"] = found["iteration 3 score"]
    for name, (low, high) in ranges.items():
        value = found.get(name, float("nan"))
        inside = low - 0.05 <= round(value, 3) <= high + 0.05
        ok &= inside
        print(f"{name:34s} {value:8.3f}  range {low}–{high}  {'PASS' if inside else 'FAIL'}")
    print(f"wall time {seconds:.0f} s (seeds 0-4: 246-288 s, two runs at a time on 2 cores)")
    sys.exit(0 if ok else 1)


if __name__ == "__main__":
    main()
