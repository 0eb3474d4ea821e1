"""Shape control of each DEFORM cable's calibrated twin with models learned from its recordings.

The twin (`dlocli.calibration.twin`) is the calibrated rod in a bimanual task in the recorded
cell's geometry, observed through the recorded markers with 2 mm of noise. An episode's goal
is the shape the twin settles into at one eval recording's gripper poses of frame g, its start
the settled shape at frame g - 50 (0.5 s earlier) of the same recording. The twin stands in
for the real cable: its replay error (the calibration's) is reported beside every result.

Controllers (the gradient MPC with the marker model):
  mpc-real       the `mlp` marker model trained on the real train recordings only
                 (examples/real_cables/run.sh, seeds 0-2)
  mpc-twin-real  pre-trained on 56 simulated trajectories of the twin, fine-tuned on the
                 real train recordings (``train`` below; pre-training seed 0, fine-tuning 0-2)
  mpc-online     the marker model learned online in the twin by Algorithm 1 (`dlo online`:
                 random episodes, then iterations of MPC trials; --budget transitions),
                 starts and goals drawn from the train recordings' gripper poses
  sac            SAC (stable-baselines3) trained in the twin at the same budget, same
                 observation
  nothing, random  the references, on the same starts and goals
  goal-poses     an oracle: drives the grippers straight to the poses that made the goal
                 (which no other controller is given), then holds: how much of the task
                 is placing the grippers

    DEFORM=/path/to/DEFORM/data_set python examples/twin_control/study.py train
    python examples/twin_control/study.py learn     # mpc-online and sac in the twin
    python examples/twin_control/study.py evaluate
    python examples/twin_control/study.py report    # table.md, results.csv, twin_control.png

Inputs: the calibrations in examples/calibration/results/CABLE-mujoco/, the real runs of
examples/real_cables/run.sh (--real, default runs/real). Everything lands in --out (default
runs/twin_control); ``report`` writes into this folder.
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import subprocess
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np

HERE = Path(__file__).resolve().parent
EXAMPLES = HERE.parent
RECIPE = EXAMPLES / "real_cables" / "mlp.yaml"
CABLES = ("DLO1", "DLO2", "DLO3", "DLO4")
CONTROLLERS = ("nothing", "random", "goal-poses", "mpc-real", "mpc-twin-real", "mpc-online",
               "sac")  # fmt: skip
START_BEFORE = 50  # frames between an episode's start and its goal (0.5 s)
SIMULATED, PRETRAIN_STEPS, FINETUNE_STEPS = 56, 1000, 1000
EPISODE_STREAM = 42


# --------------------------------------------------------------------------- the twin
def load_twin(cable: str, options: argparse.Namespace, seed: int = 0) -> Any:
    import yaml

    from dlocli.calibration.fit import load_cable
    from dlocli.calibration.spec import CalibrateSpec
    from dlocli.calibration.twin import TwinSettings, make_twin
    from dlocli.specs import BackendSpec

    fields = yaml.safe_load((EXAMPLES / "calibration" / f"{cable}.yaml").read_text())
    spec = CalibrateSpec.model_validate({**fields, "source": options.deform / cable})
    calibrated = yaml.safe_load(
        (options.calibration / f"{cable}-mujoco" / "calibrated.yaml").read_text()
    )
    backend = BackendSpec.model_validate(calibrated["backend"])
    settings = TwinSettings(episode_steps=options.steps, seed=seed)
    recorded = load_cable(spec)
    return make_twin(recorded, backend, spec.rate_hz, settings), spec, recorded


def draw_episodes(twin: Any, seed: int, count: int) -> list[tuple[int, int, int]]:
    """(recording, start frame, goal frame) of ``count`` episodes; grips at most 0.95 rod
    lengths apart at both frames (a taut cable is no shape to hold)."""
    rng = np.random.default_rng([seed, EPISODE_STREAM])
    length = twin.spec.backend.rod.length
    episodes: list[tuple[int, int, int]] = []
    while len(episodes) < count:
        index = int(rng.integers(len(twin.recordings)))
        recording = twin.recordings[index][1]
        goal = int(rng.integers(START_BEFORE + 10, len(recording)))
        start = goal - START_BEFORE
        poses = twin.poses(recording)[[start, goal], :, :3]
        if np.linalg.norm(poses[:, 1] - poses[:, 0], axis=-1).max() <= 0.95 * length:
            episodes.append((index, start, goal))
    return episodes


# --------------------------------------------------------------------------- training
def dlo(*argv: str) -> dict:
    done = subprocess.run([sys.executable, "-m", "dlocli", *argv, "--json"], check=True,
                          capture_output=True, text=True, env=os.environ)  # fmt: skip
    return json.loads(done.stdout)


def simulate(job: tuple[argparse.Namespace, str]) -> str:
    """OUT/CABLE/sim/dataset.h5: the twin under rigidly moved recorded held motion."""
    options, cable = job
    from dlocli.calibration.fit import replay_settings
    from dlocli.calibration.simulate import simulate_markers
    from dlocli.data import MarkerDataset
    from dlocli.registry import backends

    out = options.out / cable / "sim"
    if (out / "dataset.h5").is_file():
        return f"{cable}: simulated data exists"
    twin, spec, recorded = load_twin(cable, options)
    recordings = [r for _, r in recorded.train]
    backend = backends.get(twin.spec.backend.name)(twin.spec.backend, control_dt=1 / spec.rate_hz)
    settings = replay_settings(spec, recorded.held)
    sims, dropped = simulate_markers(backend, recordings, recorded.arc, SIMULATED, 0, settings)
    named = {"train": [(f"sim{i}", s) for i, s in enumerate(sims)]}
    data = MarkerDataset.from_trajectories(
        named, recorded.held, {"rate_hz": spec.rate_hz, "source": "twin"}
    )
    out.mkdir(parents=True, exist_ok=True)
    data.save(out / "dataset.h5")
    (out / "info.json").write_text(json.dumps({"simulated": len(sims), "dropped": dropped}))
    return f"{cable}: {len(sims)} simulated, {dropped} dropped"


def train_job(job: tuple[argparse.Namespace, str, int]) -> str:
    """Pre-train on the twin (seed 0, once per cable), then fine-tune with ``seed``."""
    options, cable, seed = job
    root = options.out / cable
    pretrained = root / "pretrained-s0"
    if not (pretrained / "summary.json").is_file():
        dlo("train", "--spec", str(RECIPE), "--data", str(root / "sim"), "--seed", "0",
            "--update-steps", str(PRETRAIN_STEPS), "--out", str(pretrained),
            "--overwrite")  # fmt: skip
    tuned = root / f"twin-real-s{seed}"
    if not (tuned / "summary.json").is_file():
        dlo("train", "--spec", str(RECIPE), "--data", str(options.real / cable / "data"),
            "--seed", str(seed), "--update-steps", str(FINETUNE_STEPS),
            "--init-from", str(pretrained), "--out", str(tuned), "--overwrite")  # fmt: skip
    return f"{cable} seed {seed}: fine-tuned"


def train(options: argparse.Namespace) -> None:
    for line in run_jobs(simulate, [(options, c) for c in options.cables], options.workers):
        print(line, flush=True)
    # the pre-training runs first, alone per cable; the fine-tunings after it
    jobs = [(options, c, 0) for c in options.cables]
    jobs += [(options, c, s) for s in range(1, options.seeds) for c in options.cables]
    for line in run_jobs(train_job, jobs[: len(options.cables)], options.workers):
        print(line, flush=True)
    for line in run_jobs(train_job, jobs[len(options.cables) :], options.workers):
        print(line, flush=True)


def twin_task_file(options: argparse.Namespace, cable: str, seed: int) -> Path:
    """OUT/CABLE/twin/twin.yaml: the twin with starts and goals at train-recording poses."""
    from dlocli.calibration.twin import write_twin_task

    twin, _, recorded = load_twin(cable, options, seed)
    train = [r for _, r in recorded.train]
    return write_twin_task(twin, train, options.out / cable / f"twin-s{seed}")


def learn_job(job: tuple[argparse.Namespace, str, int, str]) -> str:
    """Algorithm 1 (``mpc-online``) or SAC in the twin, ``options.budget`` transitions."""
    options, cable, seed, name = job
    import torch
    import yaml

    torch.set_num_threads(1)
    out = options.out / cable / f"{name}-s{seed}"
    began = time.perf_counter()
    fields = yaml.safe_load(twin_task_file(options, cable, seed).read_text())
    fields["task"]["goal"] = "random"
    if name == "sac":
        learn_sac(fields, seed, out, options.budget)
    else:
        learn_online(fields, seed, out, options)
    return f"{cable} {name} seed {seed}: {time.perf_counter() - began:.0f} s"


def learn_online(fields: dict, seed: int, out: Path, options: argparse.Namespace) -> None:
    from dlocli.rundir import owned
    from dlocli.runs.online import OnlineSpec
    from dlocli.runs.online.loop import OnlineRun

    steps, trials, initial = fields["task"]["episode_steps"], 5, 10
    import yaml

    recipe = yaml.safe_load(RECIPE.read_text())["model"]
    spec = OnlineSpec.model_validate({
        **fields, "seed": seed, "trials": trials, "initial_episodes": initial,
        "iters": max(1, (options.budget // steps - initial) // trials), "model": recipe,
        "fit": {"schedule": "steps", "update_steps": 500, "lr": 1e-3, "eval_every": 166,
                "rollout_steps": 16, "rollout_start": 2},
        "out": str(out), "threads": 1,
    })  # fmt: skip
    if (out / "checkpoints" / f"iter_{spec.iters + 1:03d}.pt").is_file():
        return
    out.mkdir(parents=True, exist_ok=True)
    (out / "spec.json").write_text(spec.model_dump_json(indent=1))
    with owned(out):
        run = OnlineRun(spec)
        run.run()
        # the model of every transition collected: one more update after the last trials
        run.update_model(spec.iters + 1, run.dataset_until(spec.iters))


def learn_sac(fields: dict, seed: int, out: Path, budget: int) -> None:
    from dlocli.controllers.base import make_controller
    from dlocli.env.shape_env import make_env
    from dlocli.specs import EnvSpec

    if (out / "policy" / "model.zip").is_file():
        return
    spec = EnvSpec.model_validate({**fields, "seed": seed})
    env = make_env(spec.backend, task=spec.task, seed=seed, render_mode=None)
    try:
        agent = make_controller("sac", env, seed=seed)
        agent.learn(budget)
        agent.save_policy(out / "policy")
    finally:
        env.close()


def learn(options: argparse.Namespace) -> None:
    names = [n for n in ("mpc-online", "sac") if n in options.controllers]
    jobs = [(options, c, s, n) for n in names for s in range(options.first_seed, options.seeds)
            for c in options.cables]  # fmt: skip
    for line in run_jobs(learn_job, jobs, options.workers):
        print(line, flush=True)


# --------------------------------------------------------------------------- evaluation
def controller_for(name: str, env: Any, options: argparse.Namespace, cable: str, seed: int) -> Any:
    from dlocli.controllers.base import make_controller
    from dlocli.models.checkpoints import load_planning_model

    if name in ("nothing", "random"):
        return None  # drawn per episode
    if name == "goal-poses":
        return GoalPoses(env)
    if name == "sac":
        agent = make_controller("sac", env, seed=seed)
        agent.load_policy(options.out / cable / f"sac-s{seed}" / "policy")
        return agent
    if name == "mpc-online":
        learned = options.out / cable / f"mpc-online-s{seed}" / "checkpoints"
        run = sorted(learned.glob("iter_*.pt"))[-1]
    else:
        run = {"mpc-real": options.real / cable / f"mlp-s{seed}",
               "mpc-twin-real": options.out / cable / f"twin-real-s{seed}"}[name]  # fmt: skip
    return make_controller("mpc", env, seed=seed, model=load_planning_model(run))


class GoalPoses:
    """The oracle: the grippers driven to the goal's gripper poses at the task's limits."""

    def __init__(self, env: Any) -> None:
        self.env = env

    def reset(self, goal: np.ndarray) -> None:
        pass

    def act(self, obs: np.ndarray) -> np.ndarray:
        from dlocli.env.shapes import gripper_twists_towards, max_twist

        env = self.env
        twists = gripper_twists_towards(env.backend.gripper_poses(), env.goal_gripper_poses,
                                        env.task_spec, np.array([True, True]))  # fmt: skip
        return (twists / max_twist(env.task_spec)).reshape(12)


def marker_errors(env: Any, episode: Any) -> tuple[float, float]:
    """Initial and final mean distance (mm) of the true markers from the goal's markers."""
    from dlocli.env.observation import markers_of_state

    goal = env.goal_markers()
    errors = []
    for t in (0, len(episode.positions) - 1):
        markers = markers_of_state(env.marker_layout, episode.positions[t],
                                   episode.quaternions[t], episode.grippers[t])  # fmt: skip
        errors.append(float(np.linalg.norm(markers - goal, axis=-1).mean() * 1e3))
    return errors[0], errors[1]


def evaluate_job(job: tuple[argparse.Namespace, str, int, str]) -> list[dict[str, Any]]:
    options, cable, seed, name = job
    import torch

    from dlocli.calibration.twin import goal_gap_mm
    from dlocli.controllers.base import make_controller
    from dlocli.env.metrics import score
    from dlocli.env.rollout import rollout, stream_seed
    from dlocli.env.shape_env import make_env

    torch.set_num_threads(1)
    twin, _, _ = load_twin(cable, options, seed)
    env = make_env(twin.spec.backend, task=twin.spec.task, seed=seed)
    rows = []
    try:
        controller = controller_for(name, env, options, cable, seed)
        for i, (index, start, goal) in enumerate(draw_episodes(twin, seed, options.episodes)):
            began = time.perf_counter()
            if name in ("nothing", "random"):
                kind = "zero" if name == "nothing" else "random"
                controller = make_controller(kind, env, seed=stream_seed(seed, 7, i))
            recording = twin.recordings[index][1]
            episode = rollout(env, controller, stream_seed(seed, 5, i),
                              options=twin.options(recording, start, goal))  # fmt: skip
            initial, final = marker_errors(env, episode)
            rows.append({
                "cable": cable, "controller": name, "seed": seed, "episode": i,
                "recording": twin.recordings[index][0], "start_frame": start, "goal_frame": goal,
                "initial_marker_error_mm": round(initial, 2),
                "final_marker_error_mm": round(final, 2), "score": round(score(initial, final), 4),
                "goal_gap_mm": round(goal_gap_mm(env, recording[goal], twin), 2),
                "diverged": bool(episode.diverged),
                "seconds": round(time.perf_counter() - began, 2),
            })  # fmt: skip
    finally:
        env.close()
    return rows


def evaluate(options: argparse.Namespace) -> None:
    jobs = [(options, c, s, n) for n in options.controllers for c in options.cables
            for s in range(options.first_seed, options.seeds)]  # fmt: skip
    path = options.out / options.results
    for found in run_jobs(evaluate_job, jobs, options.workers):
        rows = json.loads(path.read_text()) if path.is_file() else []
        keys = {(r["cable"], r["controller"], r["seed"]) for r in found}
        rows = [r for r in rows if (r["cable"], r["controller"], r["seed"]) not in keys] + found
        tmp = path.with_suffix(".tmp")
        tmp.write_text(json.dumps(rows, indent=1) + "\n")
        tmp.replace(path)
        first = found[0]
        mean = np.mean([r["final_marker_error_mm"] for r in found])
        print(f"{first['cable']} {first['controller']} seed {first['seed']}: "
              f"final {mean:.1f} mm", flush=True)  # fmt: skip


# --------------------------------------------------------------------------- report
def report(options: argparse.Namespace) -> None:
    rows = merged_rows(options.out)
    with open(HERE / "results.csv", "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)
    replay = {c: json.loads((options.calibration / f"{c}-mujoco" / "report.json").read_text())
              for c in CABLES if (options.calibration / f"{c}-mujoco").is_dir()}  # fmt: skip
    table = summarise(rows)
    (HERE / "table.md").write_text(markdown(table, rows, replay))
    plot(table, HERE / "twin_control.png")
    print((HERE / "table.md").read_text())


def merged_rows(out: Path) -> list[dict[str, Any]]:
    """Every OUT/evaluation*.json's rows (evaluations run side by side write apart), a
    later file's rows replacing an earlier one's of the same cable, controller and seed."""
    merged: dict[tuple[str, str, int], list[dict[str, Any]]] = {}
    for path in sorted(out.glob("evaluation*.json")):
        found: dict[tuple[str, str, int], list[dict[str, Any]]] = {}
        for row in json.loads(path.read_text()):
            found.setdefault((row["cable"], row["controller"], row["seed"]), []).append(row)
        merged.update(found)
    return [row for rows in merged.values() for row in rows]


def summarise(rows: list[dict[str, Any]]) -> dict[tuple[str, str], dict[str, float]]:
    """Per (cable, controller): the mean over seeds of each seed's mean final error and
    score, their spread over seeds, and the mean initial error."""
    out = {}
    for key in sorted({(r["cable"], r["controller"]) for r in rows}):
        mine = [r for r in rows if (r["cable"], r["controller"]) == key]
        seeds = sorted({r["seed"] for r in mine})
        finals, scores = (per_seed(mine, seeds, f) for f in ("final_marker_error_mm", "score"))
        out[key] = {"final": float(np.mean(finals)), "final_std": float(np.std(finals)),
                    "score": float(np.mean(scores)), "score_std": float(np.std(scores)),
                    "initial": float(np.mean([r["initial_marker_error_mm"] for r in mine])),
                    "seeds": len(seeds), "episodes": len(mine),
                    "diverged": sum(r["diverged"] for r in mine)}  # fmt: skip
    return out


def per_seed(rows: list[dict[str, Any]], seeds: list[int], field: str) -> list[float]:
    """Each seed's mean of ``field``."""
    return [float(np.mean([r[field] for r in rows if r["seed"] == s])) for s in seeds]


def markdown(table: dict, rows: list[dict[str, Any]], replay: dict[str, Any]) -> str:
    cables = sorted({c for c, _ in table})
    lines = ["| cable | controller | final marker error (mm) | score | initial (mm) | "
             "episodes (seeds) |", "|---|---|---:|---:|---:|---:|"]  # fmt: skip
    for cable in cables:
        for name in CONTROLLERS:
            if (cable, name) not in table:
                continue
            t = table[cable, name]
            lines.append(f"| {cable} | {name} | {t['final']:.1f} ± {t['final_std']:.1f} | "
                         f"{t['score']:.3f} ± {t['score_std']:.3f} | {t['initial']:.1f} | "
                         f"{t['episodes']} ({t['seeds']}) |")  # fmt: skip
    lines += ["", "| cable | twin's replay error (cm, eval) | twin goal vs recorded markers "
              "(mm, free markers) |", "|---|---:|---:|"]  # fmt: skip
    for cable in cables:
        gaps = [r["goal_gap_mm"] for r in rows
                if r["cable"] == cable and r["controller"] == "nothing"]  # fmt: skip
        replay_cm = replay.get(cable, {}).get("eval_calibrated_cm", float("nan"))
        lines.append(f"| {cable} | {replay_cm:.2f} | {np.mean(gaps):.1f} |")
    return "\n".join(lines) + "\n"


def plot(table: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    cables = sorted({c for c, _ in table})
    names = [n for n in CONTROLLERS if any((c, n) in table for c in cables)]
    fig, ax = plt.subplots(figsize=(8, 4))
    width = 0.8 / len(names)
    for k, name in enumerate(names):
        x = np.arange(len(cables)) + (k - (len(names) - 1) / 2) * width
        values = [table.get((c, name), {}).get("final", np.nan) for c in cables]
        spread = [table.get((c, name), {}).get("final_std", 0.0) for c in cables]
        ax.bar(x, values, width, yerr=spread, label=name, capsize=2)
    ax.set_xticks(np.arange(len(cables)), cables)
    ax.set_yscale("log")  # the learners' few mm beside the references' hundreds
    ax.set_ylabel("final marker error (mm, log scale)")
    ax.set_title("Shape control of the calibrated twins (2 mm marker noise, mean of seeds)")
    ax.legend(fontsize=8, ncol=2)
    fig.tight_layout()
    fig.savefig(path, dpi=120)


# --------------------------------------------------------------------------- main
def run_jobs(function: Any, jobs: list[Any], workers: int) -> list[Any]:
    if workers <= 1:
        return [function(job) for job in jobs]
    with ProcessPoolExecutor(workers) as pool:
        return list(pool.map(function, jobs))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("command", choices=("train", "learn", "evaluate", "report"))
    parser.add_argument("--deform", type=Path, default=Path(os.environ.get("DEFORM", "DEFORM")))
    parser.add_argument("--real", type=Path, default=Path("runs/real"))
    parser.add_argument("--calibration", type=Path,
                        default=EXAMPLES / "calibration" / "results")  # fmt: skip
    parser.add_argument("--out", type=Path, default=Path("runs/twin_control"))
    parser.add_argument("--cables", type=lambda s: s.split(","), default=list(CABLES))
    parser.add_argument("--controllers", type=lambda s: s.split(","), default=list(CONTROLLERS))
    parser.add_argument("--seeds", type=int, default=3)
    parser.add_argument("--first-seed", type=int, default=0,
                        help="learn, evaluate: seeds from this one")  # fmt: skip
    parser.add_argument("--episodes", type=int, default=6, help="episodes per seed")
    parser.add_argument("--steps", type=int, default=500,
                        help="control steps per episode (learn: of its episodes)")  # fmt: skip
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--results", default="evaluation.json",
                        help="evaluate: the file under --out its rows go to")  # fmt: skip
    parser.add_argument("--budget", type=int, default=10000, help="transitions of mpc-online, sac")
    options = parser.parse_args()
    options.out.mkdir(parents=True, exist_ok=True)
    commands = {"train": train, "learn": learn, "evaluate": evaluate, "report": report}
    commands[options.command](options)


if __name__ == "__main__":
    main()
