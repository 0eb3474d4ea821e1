"""Env steps per second: the flex rod on MuJoCo 4 against the composite cable on MuJoCo 3.

    python benchmarks/mujoco_rods_speed.py --mujoco3 VENV3/bin/python --mujoco4 VENV4/bin/python

Each interpreter has dlocli installed beside its MuJoCo (3.17 runs the composite cable,
4.0 the flex rod). Both measure the same env step (benchmarks/sim_throughput.py's
``time_env``: random actions, default rod of 20 segments, 50 Hz control, default physics
step) in turns, ``--rounds`` times each, so that a busy machine slows both alike; the
medians and their ratio (flex / composite) are printed per task.

    python benchmarks/mujoco_rods_speed.py --measure   # one measurement, JSON, this venv
"""

from __future__ import annotations

import argparse
import json
import runpy
import statistics
import subprocess
from pathlib import Path

HERE = Path(__file__).resolve().parent
TASKS = ("single", "bimanual")


def measure(steps: int) -> dict[str, object]:
    """Env and raw physics steps/s of this venv's MuJoCo rod, per task."""
    import mujoco

    # the same measurement as benchmarks/sim_throughput.py (a script, not a module)
    time_env = runpy.run_path(str(HERE / "sim_throughput.py"))["time_env"]

    from dlocli.specs import BackendSpec

    backend = BackendSpec().name
    result: dict[str, object] = {"mujoco": mujoco.__version__, "backend": backend}
    for task in TASKS:
        env_seconds, raw_seconds = time_env(backend, task, steps)
        result[task] = {"env": 1.0 / env_seconds, "raw": 1.0 / raw_seconds}
    return result


def run(python: str, steps: int) -> dict:
    out = subprocess.run(
        [python, __file__, "--measure", "--steps", str(steps)],
        capture_output=True,
        text=True,
        check=True,
    )
    return json.loads(out.stdout.strip().splitlines()[-1])


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawTextHelpFormatter
    )
    parser.add_argument("--measure", action="store_true", help="measure this venv, print JSON")
    parser.add_argument("--mujoco3", help="python of a venv with MuJoCo 3.x")
    parser.add_argument("--mujoco4", help="python of a venv with MuJoCo 4.x")
    parser.add_argument("--steps", type=int, default=400)
    parser.add_argument("--rounds", type=int, default=3)
    args = parser.parse_args()
    if args.measure:
        print(json.dumps(measure(args.steps)))
        return
    if not (args.mujoco3 and args.mujoco4):
        parser.error("give --mujoco3 and --mujoco4 (or --measure)")
    runs: dict[str, list[dict]] = {"3": [], "4": []}
    for _ in range(args.rounds):
        runs["3"].append(run(args.mujoco3, args.steps))
        runs["4"].append(run(args.mujoco4, args.steps))
    old, new = runs["3"][0], runs["4"][0]
    print(
        f"# {old['backend']} on MuJoCo {old['mujoco']} vs {new['backend']} on MuJoCo "
        f"{new['mujoco']}: 20 segments, 50 Hz, default physics step, random actions, "
        f"{args.steps} steps, median of {args.rounds} alternating rounds"
    )
    print(f"{'task':9} {'measure':8} {old['backend']:>12} {new['backend']:>12} {'ratio':>7}")
    for task in TASKS:
        for kind in ("env", "raw"):
            a = statistics.median(r[task][kind] for r in runs["3"])
            b = statistics.median(r[task][kind] for r in runs["4"])
            print(f"{task:9} {kind:8} {a:12.0f} {b:12.0f} {b / a:7.2f}")


if __name__ == "__main__":
    main()
