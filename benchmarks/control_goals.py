"""Closed-loop control on the goals of `dlo goal --seed 0..9`: the acceptance numbers.

    python benchmarks/control_goals.py [--model CKPT] [--seeds 0-9] [--steps 200]
        [--controller mpc] [-o iterations=50 -o warm_start=false] [--task single]
        [--workers 1] --out runs/goals-default

For goal seed k this is exactly ``dlo goal --seed k --out gk.npy`` followed by
``dlo control --goal gk.npy --model CKPT --seed k ...`` (the library calls behind both
commands). Prints one row per goal and the medians of the final error and latency; writes
``OUT/results.json`` and each run's directory under OUT.
"""

from __future__ import annotations

import argparse
import json
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np

from dlocli.cli.flags import parse_options
from dlocli.env.shape_env import make_goal, save_goal
from dlocli.runs.control import ControlSpec, run_control
from dlocli.specs import GoalSpec, TaskSpec, resolve_spec


def one_goal(seed: int, args: argparse.Namespace) -> dict[str, Any]:
    """Make goal ``seed`` as `dlo goal` does, control towards it as `dlo control` does."""
    out = Path(args.out)
    goal_path = out / f"goal{seed}.npy"
    save_goal(make_goal(GoalSpec(seed=seed, task=TaskSpec(name=args.task))), goal_path)
    overrides = {
        "task.name": args.task, "task.goal_file": goal_path, "seed": seed,
        "steps": args.steps, "controller": args.controller, "out": out / f"run{seed}",
        **parse_options(args.option, "controller_options"),
        **({"model": args.model} if args.model else {}),
    }  # fmt: skip
    summary = run_control(resolve_spec(ControlSpec, None, overrides), overwrite=True)
    keys = ("initial_error_mm", "final_error_mm", "best_error_mm", "latency_ms_median",
            "latency_ms_p95", "cpu_ms_median", "steps", "diverged")  # fmt: skip
    return {"goal": seed, **{k: summary[k] for k in keys}}


def parse_seeds(text: str) -> list[int]:
    """ "0-9" -> [0, ..., 9]; "1,4,6" -> [1, 4, 6]."""
    if "-" in text:
        low, high = text.split("-")
        return list(range(int(low), int(high) + 1))
    return [int(part) for part in text.split(",")]


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawTextHelpFormatter
    )
    parser.add_argument("--model", type=Path, help="checkpoint (for the model-based controllers)")
    parser.add_argument("--seeds", default="0-9", help="goal seeds: a range 0-9 or a list 1,4,6")
    parser.add_argument("--steps", type=int, default=200)
    parser.add_argument("--task", default="single")
    parser.add_argument("--controller", default="mpc")
    parser.add_argument("-o", "--option", action="append", default=[], help="KEY=VALUE")
    parser.add_argument("--workers", type=int, default=1, help="goals run in parallel")
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args()
    seeds = parse_seeds(args.seeds)
    with ProcessPoolExecutor(args.workers) as pool:
        rows = list(pool.map(one_goal, seeds, [args] * len(seeds)))
    improved = sum(r["final_error_mm"] < r["initial_error_mm"] for r in rows)
    result = {
        "controller": args.controller, "options": args.option, "task": args.task,
        "steps": args.steps, "model": str(args.model), "rows": rows,
        "improved": improved,
        "median_initial_error_mm": float(np.median([r["initial_error_mm"] for r in rows])),
        "median_final_error_mm": float(np.median([r["final_error_mm"] for r in rows])),
        "median_latency_ms": float(np.median([r["latency_ms_median"] for r in rows])),
        "median_cpu_ms": float(np.median([r["cpu_ms_median"] for r in rows])),
    }  # fmt: skip
    (args.out / "results.json").write_text(json.dumps(result, indent=1) + "\n")
    print(f"{'goal':>4} {'initial mm':>10} {'final mm':>9} {'best mm':>8} {'ms':>7} {'cpu ms':>7}")
    for r in rows:
        print(f"{r['goal']:4d} {r['initial_error_mm']:10.1f} {r['final_error_mm']:9.1f} "
              f"{r['best_error_mm']:8.1f} {r['latency_ms_median']:7.1f} "
              f"{r['cpu_ms_median']:7.1f}")  # fmt: skip
    final, latency = result["median_final_error_mm"], result["median_latency_ms"]
    print(f"improved {improved}/{len(rows)}; median final {final:.1f} mm; "
          f"median latency {latency:.1f} ms (cpu {result['median_cpu_ms']:.1f})")  # fmt: skip


if __name__ == "__main__":
    main()
