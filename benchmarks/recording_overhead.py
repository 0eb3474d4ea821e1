"""What `--record RUN.rrd` costs `dlo control`: the same run (same seed, goal and controller)
with and without a recording, interleaved so a busy machine slows both alike.

    python benchmarks/recording_overhead.py [--pairs 5] [--steps 200] [--checkpoint MODEL.pt]

Each run is a `dlo control` process; its wall time (the command as a user waits for it: start-up,
the closed loop, writing the run and the recording) and the closed loop's own `wall_s` (from
summary.json) are compared by their medians. Without ``--checkpoint`` the controller is
``random``, the cheapest there is, so the recording's share of a step is the largest; with
one it is the default gradient MPC through that model. The target is a ratio of at most 1.10.
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path


def run_control(argv: list[str], out: Path, record: Path | None) -> tuple[float, float]:
    """(process wall s, closed-loop wall_s) of one `dlo control` run."""
    flags = ["--out", str(out), "--overwrite", "--json"]
    flags += [] if record is None else ["--record", str(record)]
    start = time.perf_counter()
    subprocess.run([sys.executable, "-m", "dlocli", *argv, *flags], check=True,
                   stdout=subprocess.DEVNULL)  # fmt: skip
    wall = time.perf_counter() - start
    return wall, json.loads((out / "summary.json").read_text())["wall_s"]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--pairs", type=int, default=5)
    parser.add_argument("--steps", type=int, default=200)
    parser.add_argument("--checkpoint", type=Path, default=None)
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as scratch:
        root = Path(scratch)
        goal = root / "goal.npy"
        subprocess.run([sys.executable, "-m", "dlocli", "goal", "--out", str(goal), "--shapes",
                        "near-rest"], check=True, stdout=subprocess.DEVNULL)  # fmt: skip
        argv = ["control", "--goal", str(goal), "--shapes", "near-rest", "--steps",
                str(args.steps), "--seed", "0"]  # fmt: skip
        if args.checkpoint is None:
            argv += ["--controller", "random"]
        else:
            argv += ["--checkpoint", str(args.checkpoint)]
        run_control(argv, root / "warm", None)  # caches (numba, the OS's file cache) warmed
        plain, recorded = [], []
        for _ in range(args.pairs):
            plain.append(run_control(argv, root / "plain", None))
            recorded.append(run_control(argv, root / "recorded", root / "run.rrd"))
        size = (root / "run.rrd").stat().st_size
    controller = "random" if args.checkpoint is None else f"mpc ({args.checkpoint.name})"
    print(f"dlo control, {controller}, {args.steps} steps, {args.pairs} interleaved pairs "
          f"(medians); the recording is {size / 1e3:.0f} kB")  # fmt: skip
    for name, runs in (("without", plain), ("with --record", recorded)):
        walls = ", ".join(f"{wall:.2f}/{loop:.2f}" for wall, loop in runs)
        print(f"  {name:14s} command/closed-loop s, in order: {walls}")
    for name, index in (("command wall", 0), ("closed loop", 1)):
        without = statistics.median(run[index] for run in plain)
        with_ = statistics.median(run[index] for run in recorded)
        print(f"{name:13s} without {without:7.2f} s  with --record {with_:7.2f} s  "
              f"ratio {with_ / without:5.3f}")  # fmt: skip


if __name__ == "__main__":
    main()
