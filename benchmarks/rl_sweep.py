"""SAC and TD3 hyperparameters under a fixed transition budget: SB3 defaults vs the zoo's.

    OMP_NUM_THREADS=1 python benchmarks/rl_sweep.py [--budget 5000] [--seeds 1]
        [--configs sac,td3/zoo] [-o sac.learning_starts=100] [--backend mujoco]
        [--task single] [--goal-seed 0] [--threads 1] [--workers 1] [--out sweep.json]

Each configuration is an agent (``sac``, ``td3``) and options on top of its spec's defaults
(``dlocli.controllers.sb3_agents``): ``zoo`` is the defaults themselves (rl-baselines3-zoo's
Bullet values, adapted to small budgets), ``sb3`` is stable-baselines3's own constructor
defaults, the others vary one knob of ``zoo``. For every configuration and seed (0, 1, ...)
the agent learns for exactly ``--budget`` transitions on the env of ``make_env(backend, task,
seed=seed)`` with one fixed goal (``dlo goal --seed GOAL_SEED``), then its noise-free policy
runs one episode from each of the fixed evaluation starts (env seeds 1000, 1001, ...). The
do-nothing reference (all-zero actions) runs from the same starts.

Prints one row per run: initial and final shape error (mm, mean over the evaluation
episodes), the score 1 - final/initial, the cumulative reward per episode and the wall and CPU
seconds of learning; then the total budget used: training and evaluation transitions and the
CPU seconds of the whole sweep. ``--out`` writes the same as JSON. ``-o AGENT.KEY=VALUE``
applies to every configuration of that agent (e.g. a smaller ``learning_starts`` for a smoke
test); with ``--budget`` at or below a configuration's ``learning_starts`` it learns nothing.
"""

from __future__ import annotations

import argparse
import json
import os
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np
import yaml

#: stable-baselines3 2.x constructor defaults (SAC: Haarnoja et al. 2018; TD3: Fujimoto et al.
#: 2018 with SB3's lack of action noise), written out so the comparison does not move with ours
SB3_COMMON = {"buffer_size": 1_000_000, "learning_starts": 100, "batch_size": 256,
              "gamma": 0.99, "tau": 0.005, "train_freq": 1, "gradient_steps": 1}  # fmt: skip
SB3_SAC = {**SB3_COMMON, "learning_rate": 3e-4, "net_arch": [256, 256], "use_sde": False}
SB3_TD3 = {**SB3_COMMON, "learning_rate": 1e-3, "net_arch": [400, 300], "action_noise": 0.0}
#: rl-baselines3-zoo's HalfCheetahBulletEnv-v0 values (learning_starts adapted to the budgets)
ZOO_SAC = {"learning_rate": 7.3e-4, "buffer_size": 300_000, "learning_starts": 1000,
           "batch_size": 256, "gamma": 0.98, "tau": 0.02, "train_freq": 8, "gradient_steps": 8,
           "net_arch": [400, 300], "use_sde": True, "log_std_init": -3.0}  # fmt: skip
ZOO_TD3 = {"learning_rate": 1e-3, "buffer_size": 200_000, "learning_starts": 1000,
           "batch_size": 256, "gamma": 0.98, "tau": 0.005, "train_freq": "episode",
           "gradient_steps": -1, "net_arch": [400, 300], "action_noise": 0.1}  # fmt: skip

#: name -> (agent, options), written out in full so the configurations do not move with the
#: agents' defaults (which are the sweep's winners: sac/zoo and td3/sb3)
CONFIGS: dict[str, tuple[str, dict[str, Any]]] = {
    "sac/sb3": ("sac", SB3_SAC),
    "sac/zoo": ("sac", ZOO_SAC),
    "sac/zoo-gamma0.95": ("sac", {**ZOO_SAC, "gamma": 0.95}),
    "sac/zoo-gamma0.99": ("sac", {**ZOO_SAC, "gamma": 0.99}),
    "sac/zoo-no-sde": ("sac", {**ZOO_SAC, "use_sde": False}),
    "td3/sb3": ("td3", SB3_TD3),
    "td3/zoo": ("td3", ZOO_TD3),
    "td3/zoo-gamma0.95": ("td3", {**ZOO_TD3, "gamma": 0.95}),
    "td3/zoo-gamma0.99": ("td3", {**ZOO_TD3, "gamma": 0.99}),
    "td3/zoo-every-step": ("td3", {**ZOO_TD3, "train_freq": 1, "gradient_steps": 1}),
}
EVAL_SEED = 1000


def select_configs(text: str) -> list[str]:
    """ "sac,td3/zoo" -> every sac configuration and td3/zoo; "" -> all of them."""
    if not text:
        return list(CONFIGS)
    chosen: list[str] = []
    for part in text.split(","):
        matches = [name for name in CONFIGS if part in (name, name.split("/")[0])]
        if not matches:
            raise ValueError(f"--configs: unknown '{part}'; choose from {', '.join(CONFIGS)}")
        chosen += [name for name in matches if name not in chosen]
    return chosen


def parse_overrides(pairs: list[str]) -> dict[str, dict[str, Any]]:
    """``["sac.learning_starts=100"]`` -> {"sac": {"learning_starts": 100}} (YAML values)."""
    out: dict[str, dict[str, Any]] = {}
    for pair in pairs:
        key, sep, text = pair.partition("=")
        agent, dot, field = key.partition(".")
        if not (sep and dot and agent in ("sac", "td3") and field):
            raise ValueError(f"-o {pair!r} must look like sac.KEY=VALUE or td3.KEY=VALUE")
        out.setdefault(agent, {})[field] = yaml.safe_load(text)
    return out


def check_options(names: list[str], args: argparse.Namespace) -> None:
    """Validate every run's options before any run starts (ValueError naming the problem)."""
    from dlocli.controllers.base import controller_spec
    from dlocli.errors import BadInput

    for name in names:
        agent, options = CONFIGS[name]
        try:
            controller_spec(agent, {**options, **args.overrides.get(agent, {})})
        except BadInput as exc:
            raise ValueError(f"{name}: {exc}") from exc


def make_env(args: argparse.Namespace, goal: np.ndarray, seed: int) -> Any:
    """The sweep's env: the task's defaults, the CLI's backend and task, the fixed goal."""
    import dlocli

    return dlocli.make_env(backend=args.backend, task=args.task, goal=goal, seed=seed)


def evaluate(controller: Any, env: Any, episodes: int) -> dict[str, float]:
    """Means over noise-free episodes from env seeds EVAL_SEED, EVAL_SEED + 1, ..."""
    initial, final, reward, steps = [], [], [], 0
    for i in range(episodes):
        obs, info = env.reset(seed=EVAL_SEED + i)
        controller.reset(env.goal)
        initial.append(info["shape_error_mm"])
        total = 0.0
        for _ in range(env.task_spec.episode_steps):
            obs, r, terminated, truncated, info = env.step(controller.act(obs))
            total += float(r)
            steps += 1
            if terminated or truncated:
                break
        final.append(info["shape_error_mm"])
        reward.append(total)
    init, fin = float(np.mean(initial)), float(np.mean(final))
    return {"initial_error_mm": init, "final_error_mm": fin,
            "score": 1.0 - fin / init if init > 0 else 0.0,
            "final_error_mm_std": float(np.std(final)), "reward": float(np.mean(reward)),
            "eval_transitions": steps}  # fmt: skip


def one_run(job: tuple[str, int], args: argparse.Namespace, goal: np.ndarray) -> dict[str, Any]:
    """Learn configuration ``name`` for the budget with ``seed``, then evaluate it."""
    import torch

    from dlocli.controllers.base import make_controller

    torch.set_num_threads(args.threads)
    name, seed = job
    run_cpu = time.process_time()
    eval_env = make_env(args, goal, seed=0)
    if name == "zero":
        controller = make_controller("zero", eval_env)
        wall, cpu, options, resolved = 0.0, 0.0, {}, {}
    else:
        agent_name, options = CONFIGS[name]
        options = {"device": args.device, **options, **args.overrides.get(agent_name, {})}
        agent = make_controller(agent_name, make_env(args, goal, seed), options=options, seed=seed)
        start, cpu = time.perf_counter(), time.process_time()
        agent.learn(args.budget)
        wall, cpu = time.perf_counter() - start, time.process_time() - cpu
        controller, resolved = agent, agent.spec.model_dump()
    result = evaluate(controller, eval_env, args.eval_episodes)
    return {"config": name, "seed": seed, **result, "wall_s": wall, "cpu_s": cpu,
            "run_cpu_s": time.process_time() - run_cpu,
            "transitions": 0 if name == "zero" else args.budget,
            "options": options, "resolved": resolved}  # fmt: skip


def print_row(row: dict[str, Any]) -> None:
    seed = "-" if row["config"] == "zero" else str(row["seed"])
    print(f"{row['config']:<20} {seed:>4} {row['initial_error_mm']:10.1f} "
          f"{row['final_error_mm']:9.1f} {row['score']:6.2f} {row['reward']:8.1f} "
          f"{row['wall_s']:7.0f} {row['cpu_s']:7.0f}", flush=True)  # fmt: skip


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawTextHelpFormatter
    )
    parser.add_argument("--budget", type=int, default=5000, help="transitions per run")
    parser.add_argument("--seeds", type=int, default=1, help="seeds per config: 0, 1, ...")
    parser.add_argument("--configs", default="", help=f"comma list of {', '.join(CONFIGS)}, "
                        "or an agent name for all of its configs (default: all)")  # fmt: skip
    parser.add_argument("-o", "--option", action="append", default=[], help="AGENT.KEY=VALUE")
    parser.add_argument("--backend", default="mujoco")
    parser.add_argument("--task", default="single")
    parser.add_argument("--goal-seed", type=int, default=0, help="the fixed goal: dlo goal --seed")
    parser.add_argument("--eval-episodes", type=int, default=5)
    parser.add_argument("--threads", type=int, default=1, help="torch threads per run")
    parser.add_argument("--device", default="cpu", help="torch device of the agents")
    parser.add_argument("--workers", type=int, default=1, help="runs in parallel (processes)")
    parser.add_argument("--out", type=Path, help="write the results as JSON")
    args = parser.parse_args()
    if args.budget <= 0 or args.seeds <= 0 or args.eval_episodes <= 0:
        parser.error("--budget, --seeds and --eval-episodes must be positive")
    try:
        args.overrides = parse_overrides(args.option)
        names = select_configs(args.configs)
        check_options(names, args)
    except ValueError as exc:
        parser.error(str(exc))
    os.environ.setdefault("OMP_NUM_THREADS", str(args.threads))
    cpu_start, wall_start = time.process_time(), time.perf_counter()

    from dlocli.env.shape_env import make_goal
    from dlocli.errors import BadInput
    from dlocli.specs import BackendSpec, GoalSpec, TaskSpec

    try:
        goal = make_goal(GoalSpec(backend=BackendSpec(name=args.backend),
                                  task=TaskSpec(name=args.task), seed=args.goal_seed))  # fmt: skip
    except BadInput as exc:
        parser.error(str(exc))
    jobs = [("zero", 0)] + [(name, seed) for name in names for seed in range(args.seeds)]
    print(f"{'config':<20} {'seed':>4} {'initial mm':>10} {'final mm':>9} {'score':>6} "
          f"{'reward':>8} {'wall s':>7} {'cpu s':>7}", flush=True)  # fmt: skip
    rows = []
    with ProcessPoolExecutor(args.workers) as pool:
        for row in pool.map(one_run, jobs, [args] * len(jobs), [goal] * len(jobs)):
            print_row(row)
            rows.append(row)
    total = {
        "train_transitions": sum(row["transitions"] for row in rows),
        "eval_transitions": sum(row["eval_transitions"] for row in rows),
        "cpu_s": sum(row["run_cpu_s"] for row in rows) + time.process_time() - cpu_start,
        "wall_s": time.perf_counter() - wall_start,
    }
    print(f"total: {total['train_transitions']} training and {total['eval_transitions']} "
          f"evaluation transitions, {total['cpu_s']:.0f} CPU s, "
          f"{total['wall_s']:.0f} wall s")  # fmt: skip
    if args.out is not None:
        result = {"budget": args.budget, "seeds": args.seeds, "backend": args.backend,
                  "task": args.task, "goal_seed": args.goal_seed, "options": args.option,
                  "eval_seeds": [EVAL_SEED + i for i in range(args.eval_episodes)],
                  "configs": {n: {"agent": CONFIGS[n][0], "options": CONFIGS[n][1]}
                              for n in names},
                  "rows": rows, "total": total}  # fmt: skip
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps(result, indent=1) + "\n")


if __name__ == "__main__":
    main()
