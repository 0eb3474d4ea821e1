"""A small `dlo online` run alone and beside a CPU-bound load, with the old and the new
thread choice, in one run (issue 32).

    python benchmarks/online_contention.py [--old-ref 8b4eaba] [--load 2] [--timeout 900]
        [--args "--iters 2 --trials 2 --steps 40 --epochs 2 --initial-episodes 2"]

"old": the code at ``--old-ref`` (before :mod:`dlocli.threads`: the driver's torch threads at
torch's default, one per core, with OpenMP's default spinning, and trials run in the driver
with the driver's threads). "new": this checkout (threads from the CPUs this process may
use, passive waiting, one thread per trial). Both run the same command in a fresh process
with no ``OMP_*``/``MKL_*`` variables set, so each makes its own choice. The load is
``--load`` processes each spinning a core (``while True: pass``), started before the run
and killed after it.

Printed: each run's wall time, model-update and MPC seconds (from its summary.json), the
load average before and after it, and the slowdown ratios beside the load against alone
for each choice. A run past ``--timeout`` seconds is stopped and reported as at least that.
The machine may be shared: a load average well above the benchmark's own load while it runs
"alone" pollutes the ratios, and the printout says so.
"""

from __future__ import annotations

import argparse
import json
import os
import shlex
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
#: the last commit before dlocli.threads (main, 2026-12-03)
OLD_REF = "8b4eaba"
SMALL_RUN = "--iters 2 --trials 2 --steps 40 --epochs 2 --initial-episodes 2 --lr 1e-3 --seed 0"
SPIN = "while True: pass"


def old_checkout(ref: str, into: Path) -> Path:
    """The package as it was at ``ref``, extracted into ``into`` (no git worktree needed)."""
    archive = subprocess.run(["git", "-C", str(REPO), "archive", ref, "dlocli"],
                             check=True, capture_output=True).stdout  # fmt: skip
    subprocess.run(["tar", "-x", "-C", str(into)], input=archive, check=True)
    return into


def clean_environment(code: Path) -> dict[str, str]:
    """This environment without thread settings, importing dlocli from ``code``."""
    thread_prefixes = ("OMP_", "MKL_", "OPENBLAS_", "KMP_", "GOMP_")
    env = {k: v for k, v in os.environ.items() if not k.startswith(thread_prefixes)}
    return env | {"PYTHONPATH": str(code), "MPLBACKEND": "Agg"}


def timed_run(code: Path, args: list[str], out: Path, timeout: float) -> dict[str, float]:
    """One `dlo online` run; wall seconds, the load average around it, and its time split."""
    cmd = [sys.executable, "-m", "dlocli", "online", *args, "--out", str(out), "--overwrite",
           "--json"]  # fmt: skip
    before = os.getloadavg()[0]
    start = time.perf_counter()
    try:
        subprocess.run(cmd, env=clean_environment(code), cwd=out.parent, check=True,
                       capture_output=True, timeout=timeout)  # fmt: skip
        wall, finished = time.perf_counter() - start, True
    except subprocess.TimeoutExpired:
        wall, finished = timeout, False
    result = {"wall": wall, "finished": finished, "load_before": before,
              "load_after": os.getloadavg()[0]}  # fmt: skip
    if finished:
        summary = json.loads((out / "summary.json").read_text())
        result |= {"train": summary["train_seconds"], "mpc": summary["mpc_seconds"]}
    return result


def uptime() -> str:
    return subprocess.run(["uptime"], capture_output=True, text=True).stdout.strip()


class Load:
    """``n`` processes spinning a core each, for the block."""

    def __init__(self, n: int) -> None:
        self.n = n
        self.procs: list[subprocess.Popen] = []

    def __enter__(self) -> Load:
        self.procs = [subprocess.Popen([sys.executable, "-c", SPIN]) for _ in range(self.n)]
        time.sleep(1.0)  # running before the measured run starts
        return self

    def __exit__(self, *exc: object) -> None:
        for proc in self.procs:
            proc.kill()
            proc.wait()


def report(results: dict[tuple[str, str], dict], load: int, cpus: int) -> str:
    lines = [f"{'choice':6} {'condition':12} {'wall s':>8} {'update s':>9} {'mpc s':>7} "
             f"{'load avg before/after':>22}"]  # fmt: skip
    for (choice, condition), r in results.items():
        wall = f"{r['wall']:.1f}" if r["finished"] else f">{r['wall']:.0f}"
        lines.append(
            f"{choice:6} {condition:12} {wall:>8} {r.get('train', float('nan')):>9.1f} "
            f"{r.get('mpc', float('nan')):>7.1f} "
            f"{r['load_before']:>10.2f} / {r['load_after']:<9.2f}"
        )
    for choice in ("old", "new"):
        alone, loaded = results[choice, "alone"], results[choice, "beside load"]
        bound = "" if loaded["finished"] else "at least "
        lines.append(f"{choice}: beside {load} spinning processes / alone = {bound}"
                     f"{loaded['wall'] / alone['wall']:.2f}x")  # fmt: skip
    new_alone, new_loaded = results["new", "alone"], results["new", "beside load"]
    ratio = new_loaded["wall"] / new_alone["wall"]
    verdict = "met" if new_loaded["finished"] and ratio <= 3.0 else "NOT met"
    bound = "" if new_loaded["finished"] else "at least "
    lines.append(f"acceptance: new beside the load / new alone = {bound}{ratio:.2f}x "
                 f"(at most 3x asked): {verdict}")  # fmt: skip
    own = 1.0  # the run itself keeps about one core busy
    if max(new_alone["load_before"], new_alone["load_after"]) > own + 1.0:
        lines.append(f"POLLUTED: the load average around the 'alone' runs exceeded "
                     f"{own + 1.0:.0f} on {cpus} CPUs (other jobs on this machine)")  # fmt: skip
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--old-ref", default=OLD_REF, help="git commit of the old choice")
    parser.add_argument("--args", default=SMALL_RUN, help="the `dlo online` flags")
    parser.add_argument("--load", type=int, default=2, help="spinning processes beside it")
    parser.add_argument("--timeout", type=float, default=900.0, help="seconds per run at most")
    args = parser.parse_args()
    online = shlex.split(args.args)
    cpus = len(os.sched_getaffinity(0))
    print(f"# python benchmarks/online_contention.py --old-ref {args.old_ref} --load "
          f"{args.load} --args '{args.args}'\n# {time.strftime('%Y-%m-%d %H:%M')} UTC, "
          f"{cpus} CPUs, uptime: {uptime()}",
          flush=True)  # fmt: skip
    results: dict[tuple[str, str], dict] = {}
    with tempfile.TemporaryDirectory(prefix="dlo-contention-") as tmp:
        old = old_checkout(args.old_ref, Path(tmp))
        codes = {"old": old, "new": REPO}
        for condition in ("alone", "beside load"):
            for choice, code in codes.items():
                out = Path(tmp) / f"{choice}-{condition.replace(' ', '-')}" / "run"
                out.parent.mkdir()
                if condition == "alone":
                    results[choice, condition] = timed_run(code, online, out, args.timeout)
                else:
                    with Load(args.load):
                        results[choice, condition] = timed_run(code, online, out, args.timeout)
                print(f"  {choice} {condition}: {results[choice, condition]}", flush=True)
    print(report(results, args.load, cpus))
    print(f"# uptime after: {uptime()}")


if __name__ == "__main__":
    main()
