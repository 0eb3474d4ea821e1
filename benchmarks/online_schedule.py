"""The online loop's model-update schedules side by side: the paper's "epochs" against
"steps" (issue 17, point 1).

    python benchmarks/online_schedule.py [--seeds 0,1,2] [--out runs/online_schedule]
        [--iters 6] [--trials 10] [--steps 200] [--hidden 64] [--epochs 50]
        [--update-steps 2000] [--schedules epochs,steps] [--threads 1] [--overwrite] [--quick]

For every schedule and seed, one `dlo online` run (``dlocli.runs.online.start_online``) in
OUT/SCHEDULE/sSEED, everything else equal: the same seeds give both schedules the same
initial data, the same first model and the same trial starts and goals. "epochs" trains E
epochs over all data D_k at every iteration, so its cost grows with k; "steps" trains at
most ``--update-steps`` steps per update (FitSpec's defaults for the rest: half of each batch
from the newest trials, early stopping on the validation split).

Printed per schedule, mean ± std over the seeds: the final error of the last iteration's
trials (mm), its score (1 - final/initial), the do-nothing reference (the trials' initial
error), and the seconds spent training, planning (MPC) and simulating; then the training
seconds per iteration (does the update's cost grow with the data?) and the ratio of the
schedules' training times, measured in this same run. Results also go to OUT/results.json.

Finished runs are reused and interrupted ones resumed (the same arguments give the same
specs); ``--overwrite`` starts afresh. ``--quick`` is a smoke test at tiny sizes.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch

from dlocli.models.checkpoints import read_checkpoint
from dlocli.runs.online import OnlineSpec, resume_online, start_online

QUICK = {
    "iters": 2,
    "trials": 2,
    "steps": 15,
    "initial_episodes": 2,
    "hidden": 16,
    "epochs": 2,
    "update_steps": 20,
    "eval_every": 5,
    "horizon": 2,
    "shapes": "near-rest",
}


def run_spec(args: argparse.Namespace, schedule: str, seed: int) -> OnlineSpec:
    fit: dict[str, Any] = {"schedule": schedule, "epochs": args.epochs, "device": "cpu"}
    fit["update_steps"] = args.update_steps
    if args.eval_every is not None:
        fit["eval_every"] = args.eval_every
    task: dict[str, Any] = {"episode_steps": args.steps}
    if args.shapes is not None:
        task["shapes"] = args.shapes
    spec: dict[str, Any] = {
        "iters": args.iters,
        "trials": args.trials,
        "initial_episodes": args.initial_episodes,
        "model": {"hidden": args.hidden},
        "fit": fit,
        "task": task,
        "seed": seed,
        "out": str(args.out / schedule / f"s{seed}"),
    }
    if args.horizon is not None:
        spec["mpc"] = {"horizon": args.horizon}
    return OnlineSpec.model_validate(spec)


def run_one(spec: OnlineSpec, overwrite: bool) -> dict[str, Any]:
    """The run's summary: a new run, or the one in ``spec.out`` resumed (or just re-read)."""
    saved = spec.out / "spec.json"
    if overwrite or not saved.is_file():
        return start_online(spec, overwrite=True)
    if OnlineSpec.model_validate_json(saved.read_text()) != spec:
        raise SystemExit(f"{spec.out} holds a run with other arguments; pass --overwrite")
    return resume_online(spec.out, {})


def iteration_train_seconds(spec: OnlineSpec) -> list[float]:
    paths = [spec.out / "checkpoints" / f"iter_{k:02d}.pt" for k in range(1, spec.iters + 1)]
    return [float(read_checkpoint(p)["train_seconds"]) for p in paths]


def spread(values: list[float], digits: int = 1) -> str:
    a = np.asarray(values, dtype=float)
    return f"{a.mean():.{digits}f} ± {a.std():.{digits}f}"


def report(results: dict[str, list[dict[str, Any]]]) -> None:
    keys = ["final_error_mm", "score", "initial_error_mm", "train_seconds", "mpc_seconds",
            "simulation_seconds"]  # fmt: skip
    print(f"{'schedule':<9}" + "".join(f"{k:>20}" for k in keys))
    for schedule, runs in results.items():
        cells = [spread([r[k] for r in runs], 3 if k == "score" else 1) for k in keys]
        print(f"{schedule:<9}" + "".join(f"{c:>20}" for c in cells))
    print("\ntraining seconds per iteration (mean over seeds):")
    for schedule, runs in results.items():
        per_iter = np.mean([r["train_seconds_per_iteration"] for r in runs], axis=0)
        print(f"  {schedule:<8} " + " ".join(f"{s:7.1f}" for s in per_iter))
    if {"epochs", "steps"} <= results.keys():
        train = {s: sum(r["train_seconds"] for r in results[s]) for s in ("epochs", "steps")}
        ratio = train["epochs"] / train["steps"] if train["steps"] > 0 else float("nan")
        print(f"\ntraining time epochs / steps: {train['epochs']:.1f} s / {train['steps']:.1f} s "
              f"= {ratio:.2f}x")  # fmt: skip


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seeds", default="0,1,2")
    parser.add_argument("--out", type=Path, default=Path("runs/online_schedule"))
    parser.add_argument("--schedules", default="epochs,steps")
    parser.add_argument("--iters", type=int, default=6)
    parser.add_argument("--trials", type=int, default=10)
    parser.add_argument("--steps", type=int, default=200, help="control steps per episode")
    parser.add_argument("--initial-episodes", type=int, default=10)
    parser.add_argument("--hidden", type=int, default=64)
    parser.add_argument("--epochs", type=int, default=50, help='E of "epochs" (paper: 50)')
    parser.add_argument("--update-steps", type=int, default=2000, help='budget of "steps"')
    parser.add_argument("--eval-every", type=int, default=None)
    parser.add_argument("--horizon", type=int, default=None, help="MPC horizon (default H=5)")
    parser.add_argument("--shapes", default=None, help="task shapes (default: the task's)")
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--overwrite", action="store_true")
    parser.add_argument("--quick", action="store_true", help="smoke test at tiny sizes")
    args = parser.parse_args()
    if args.quick:
        vars(args).update(QUICK)
    torch.set_num_threads(args.threads)
    seeds = [int(s) for s in args.seeds.split(",") if s.strip()]
    results: dict[str, list[dict[str, Any]]] = {}
    for schedule in [s.strip() for s in args.schedules.split(",") if s.strip()]:
        for seed in seeds:
            spec = run_spec(args, schedule, seed)
            start = time.perf_counter()
            summary = run_one(spec, args.overwrite)
            per_iter = iteration_train_seconds(spec)
            print(f"{schedule} seed {seed}: final {summary['final_error_mm']:.1f} mm, score "
                  f"{summary['score']:.3f}, train {summary['train_seconds']:.1f} s "
                  f"({time.perf_counter() - start:.0f} s now)", flush=True)  # fmt: skip
            results.setdefault(schedule, []).append(
                {"seed": seed, **summary, "train_seconds_per_iteration": per_iter}
            )
    print()
    report(results)
    args.out.mkdir(parents=True, exist_ok=True)
    settings = {k: str(v) if isinstance(v, Path) else v for k, v in vars(args).items()}
    (args.out / "results.json").write_text(
        json.dumps({"args": settings, "runs": results}, indent=1, default=float)
    )


if __name__ == "__main__":
    main()
