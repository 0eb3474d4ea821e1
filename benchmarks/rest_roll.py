"""Where an online run's trials ended, by the moving gripper's roll: does the roll decide how
near the goal the rod rests? (the measurement behind the planner's ``rest_roll``)

    python benchmarks/rest_roll.py RUN [--from-iteration K] [--to-iteration L] [--bin-deg 5]

For every trial of iterations K to L of a `dlo online` run with one fixed goal (the paper's
task): the moving gripper's final roll about its own x axis (the rod's axis where it holds
it), measured from the horizontal (its y axis against the horizontal line across that axis),
the final error, and the error of the rod's mean positions over the rest window
(:data:`~dlocli.controllers.rest_roll.REST_WINDOW_S`: about one period of the sideways
swing, so the swing averages out). Prints JSON: the trials binned by roll (count, mean final
error, mean rest error), and the roll a parabola fitted to the rest errors puts its least at.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

import numpy as np

from dlocli.backends.rotations import quat_to_matrix
from dlocli.controllers.rest_roll import REST_WINDOW_S
from dlocli.data import load_dataset
from dlocli.env.tasks import make_task
from dlocli.resume import load_saved_spec
from dlocli.runs.online.spec import OnlineSpec


def roll_deg(quaternion: np.ndarray) -> float:
    """The gripper's roll (degrees) about its x axis: its y axis against the horizontal line
    across the x axis."""
    frame = quat_to_matrix(np.asarray(quaternion, dtype=np.float64))
    x, y = frame[:, 0], frame[:, 1]
    level = np.cross([0.0, 0.0, 1.0], x)
    level /= np.linalg.norm(level)
    return float(np.degrees(np.arctan2(np.cross(level, y) @ x, level @ y)))


def endings(run: Path, first: int, last: int) -> list[dict[str, float]]:
    spec = load_saved_spec(OnlineSpec, run / "spec.json")
    window = int(round(REST_WINDOW_S / spec.task.control_dt))
    moving = int(np.flatnonzero(make_task(spec.task.name).moving)[-1])  # the right one
    rows = []
    for k in range(first, last + 1):
        for j in range(1, spec.trials + 1):
            data = load_dataset(run / "data" / f"iter_{k:02d}" / f"trial_{j:03d}.h5")
            goal, positions = data.goals[0], data.positions
            rows.append({
                "iteration": k, "roll_deg": roll_deg(data.grippers[-1, moving, 3:]),
                "final_mm": 1000.0 * float(np.linalg.norm(positions[-1] - goal, axis=-1).mean()),
                "rest_mm": 1000.0 * float(
                    np.linalg.norm(positions[-window:].mean(0) - goal, axis=-1).mean()),
            })  # fmt: skip
    return rows


def binned(rows: list[dict[str, float]], width: float) -> dict[str, Any]:
    rolls = np.array([r["roll_deg"] for r in rows])
    edges = np.arange(np.floor(rolls.min() / width), np.ceil(rolls.max() / width) + 1) * width
    bins = []
    for low, high in zip(edges[:-1], edges[1:], strict=True):
        inside = [r for r, roll in zip(rows, rolls, strict=True) if low <= roll < high]
        if inside:
            bins.append({
                "roll_deg": [float(low), float(high)], "trials": len(inside),
                "final_mm": round(float(np.mean([r["final_mm"] for r in inside])), 2),
                "rest_mm": round(float(np.mean([r["rest_mm"] for r in inside])), 2),
            })  # fmt: skip
    a, b, c = np.polyfit(rolls, [r["rest_mm"] for r in rows], 2)
    best = -b / (2 * a) if a > 0 else None
    return {
        "trials": len(rows), "bins": bins,
        "parabola_least_at_deg": None if best is None else round(float(best), 1),
        "parabola_least_mm": None if best is None else round(float(c - b * b / (4 * a)), 2),
        "final_mm": round(float(np.mean([r["final_mm"] for r in rows])), 2),
        "rest_mm": round(float(np.mean([r["rest_mm"] for r in rows])), 2),
    }  # fmt: skip


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("run", type=Path)
    parser.add_argument("--from-iteration", type=int, default=1)
    parser.add_argument("--to-iteration", type=int, default=None)
    parser.add_argument("--bin-deg", type=float, default=5.0)
    args = parser.parse_args(argv)
    spec = load_saved_spec(OnlineSpec, args.run / "spec.json")
    last = args.to_iteration or spec.iters
    report = {"run": str(args.run), "iterations": [args.from_iteration, last],
              **binned(endings(args.run, args.from_iteration, last), args.bin_deg)}  # fmt: skip
    json.dump(report, sys.stdout, indent=1)
    print()


if __name__ == "__main__":
    main()
