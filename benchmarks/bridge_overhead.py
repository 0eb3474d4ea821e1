"""What the robot bridge costs per control step: the env stepped in this process against the
same env stepped through a `dlo serve` cell in another process (lockstep, loopback TCP).

    python benchmarks/bridge_overhead.py [--steps 400]

Prints the median milliseconds per env step of each and their ratio, measured in one run.
"""

from __future__ import annotations

import argparse
import re
import statistics
import subprocess
import sys
import time

import numpy as np

import dlocli


def step_times(env, steps: int) -> list[float]:
    rng = np.random.default_rng(0)
    env.reset(seed=0)
    times = []
    for _ in range(steps):
        action = rng.uniform(-1, 1, env.action_space.shape)
        start = time.perf_counter()
        env.step(action)
        times.append(time.perf_counter() - start)
    return times


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--steps", type=int, default=400)
    steps = parser.parse_args().steps
    here = dlocli.make_env("mujoco", "single", seed=0, render_mode=None, episode_steps=steps)
    local = statistics.median(step_times(here, steps))
    here.close()
    cell = subprocess.Popen(
        [sys.executable, "-m", "dlocli.cli", "serve", "--address", "tcp://127.0.0.1:*"],
        stderr=subprocess.PIPE, text=True,
    )  # fmt: skip
    try:
        address = re.search(r" at (tcp://\S+);", cell.stderr.readline()).group(1)
        there = dlocli.make_env("mujoco", "single", seed=0, render_mode=None,
                                episode_steps=steps, cell=address)  # fmt: skip
        bridged = statistics.median(step_times(there, steps))
        there.close()
    finally:
        cell.terminate()
        cell.wait()
    print(f"env step in this process   {1000 * local:7.3f} ms (median of {steps})")
    print(f"env step through a cell    {1000 * bridged:7.3f} ms")
    print(f"bridged / in-process       {bridged / local:7.2f}x "
          f"(+{1000 * (bridged - local):.3f} ms a step; the control period is 20 ms)")  # fmt: skip


if __name__ == "__main__":
    main()
