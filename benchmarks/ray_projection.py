"""The paper-scale `dlo online` run's wall time on a Ray cluster of n workers, projected
from a measured local Ray run with 2 workers (issue 32).

    python benchmarks/ray_projection.py [--trials 2] [--iters 2] [--epochs 2]
        [--workers 1,2,4,8,16,25,50] [--json]

Measured, on a local Ray instance of 2 CPUs (``--executor ray --workers 2``, the paper's
model, task and T = 200 steps): the seconds of one trial (its MPC and simulation, one
thread), of the reference episodes per trial (doing nothing and random actions), the
transfer and scheduling overhead per trial (an iteration's trial phase x 2 workers, less the
trials' own seconds, per trial; taken from the last iteration, when Ray's workers are warm),
and the driver's model update per transition and epoch. Projected for K = 20 iterations of
N = 50 trials, with E = 50 epochs over all data (the paper's schedule; D grows by N x T
transitions per iteration from 10 initial episodes) and with ``--schedule steps`` (2000
steps per update, each a batch of 64):

    wall(n) = sum over k of update_k + ceil(N / n) x (trial + references + overhead)

A worker beyond N = 50 has nothing to do. The update runs in the driver on its CPU cores
(on a GPU it would take less); trials are taken as equally long.
"""

from __future__ import annotations

import argparse
import json
import math
import statistics
import tempfile
import time
from pathlib import Path
from typing import Any

from dlocli.data import load_dataset
from dlocli.models.checkpoints import read_checkpoint
from dlocli.runs.online import OnlineSpec, RunLayout, start_online

PAPER = {"iters": 20, "trials": 50, "steps": 200, "epochs": 50, "initial_episodes": 10}
STEPS_SCHEDULE = {"update_steps": 2000, "batch_size": 64}


class PhaseClock:
    """When each iteration's trial phase starts and its last trial ends (progress events)."""

    def __init__(self) -> None:
        self.trials_start: dict[int, float] = {}
        self.trials_end: dict[int, float] = {}

    def __call__(self, event: str, info: dict[str, Any]) -> None:
        if event == "trials":
            self.trials_start[info["iteration"]] = time.perf_counter()
        elif event == "trial":
            self.trials_end[info["iteration"]] = time.perf_counter()


def measure(iters: int, trials: int, epochs: int, out: Path) -> dict[str, float]:
    """Run the small Ray run; the per-trial, per-update and overhead seconds it took."""
    spec = OnlineSpec(
        iters=iters, trials=trials, initial_episodes=2, executor="ray", workers=2, seed=0,
        fit={"epochs": epochs, "device": "cpu"}, out=out,
    )  # fmt: skip
    clock = PhaseClock()
    summary = start_online(spec, overwrite=True, progress=clock)
    paths = RunLayout(out)
    last = iters
    seconds = [
        load_dataset(paths.trial(last, j)).attrs["trial_seconds"] for j in range(1, trials + 1)
    ]
    phase = clock.trials_end[last] - clock.trials_start[last]
    first_update = float(read_checkpoint(paths.checkpoint(1))["train_seconds"])
    initial = load_dataset(paths.initial()).n_transitions
    return {
        "trial_s": statistics.median(seconds),
        "references_s": summary["reference_seconds"] / (iters * trials),
        "overhead_s": max(0.0, (phase * spec.workers - sum(seconds)) / trials),
        "update_s_per_transition_epoch": first_update / (epochs * initial),
        "measured_wall_s": summary["seconds"],
    }


def project(measured: dict[str, float], workers: int, schedule: str) -> float:
    """Seconds of the paper-scale run on ``workers`` Ray workers."""
    per_trial = measured["trial_s"] + measured["references_s"] + measured["overhead_s"]
    rate = measured["update_s_per_transition_epoch"]
    total = 0.0
    for k in range(1, PAPER["iters"] + 1):
        data = (PAPER["initial_episodes"] + (k - 1) * PAPER["trials"]) * PAPER["steps"]
        if schedule == "epochs":
            update = PAPER["epochs"] * data * rate
        else:
            update = STEPS_SCHEDULE["update_steps"] * STEPS_SCHEDULE["batch_size"] * rate
        total += update + math.ceil(PAPER["trials"] / workers) * per_trial
    return total


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--iters", type=int, default=2)
    parser.add_argument("--trials", type=int, default=2)
    parser.add_argument("--epochs", type=int, default=2)
    parser.add_argument("--workers", default="1,2,4,8,16,25,50")
    parser.add_argument("--json", action="store_true")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory(prefix="dlo-projection-") as tmp:
        measured = measure(args.iters, args.trials, args.epochs, Path(tmp) / "run")
    counts = [int(n) for n in args.workers.split(",")]
    table = {
        schedule: {n: project(measured, n, schedule) for n in counts}
        for schedule in ("epochs", "steps")
    }
    if args.json:
        print(json.dumps({"measured": measured, "projected_s": table}))
        return
    print(f"measured on a local Ray instance, 2 workers ({args.iters} iterations x "
          f"{args.trials} trials of {PAPER['steps']} steps):")  # fmt: skip
    for name, value in measured.items():
        print(f"  {name:32} {value:10.4g}")
    print(f"projected wall time of K={PAPER['iters']} x N={PAPER['trials']} trials "
          f"(hours), by Ray workers:")  # fmt: skip
    print(f"  {'workers':>8} {'epochs (E=50)':>14} {'steps (2000)':>13}")
    for n in counts:
        print(f"  {n:>8} {table['epochs'][n] / 3600:>14.2f} {table['steps'][n] / 3600:>13.2f}")


if __name__ == "__main__":
    main()
