"""What a real cell's tracker costs: the learned-model MPC (Algorithm 1 with the markers
observation) and SAC (the same observation), each trained once per seed on clean markers,
then evaluated under Gaussian marker noise, latency, lost frames and an occlusion; beside the
MPC learned with the full observation, the MPC learned under 5 mm of noise, and doing nothing
and random actions from the same starts to the same goals.

    python examples/robustness/study.py train     # the learners (resumable; hours on 2 CPUs)
    python examples/robustness/study.py evaluate  # every learner under every setting
    python examples/robustness/study.py report    # table.md, results.csv, robustness.png
    python examples/robustness/study.py camera-report  # camera_table.md, camera.csv, camera.png

Everything lands in --out (default runs/robustness); ``report`` writes the table and figure
into this folder. Sizes are options (--budget, --seeds, ...); the committed results say
which were used (results.md).
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np

HERE = Path(__file__).resolve().parent
EVAL_STREAM = 77  # the evaluation episodes' seed stream, apart from every training stream
#: the depth camera without its faults (depth noise, invalid pixels, stray points)
CLEAN_CAMERA = {"noise_mm": 0.0, "noise_growth_mm": 0.0, "invalid_fraction": 0.0,
                "stray_fraction": 0.0}  # fmt: skip

#: the evaluation settings: one fault at a time, then the acceptance setting and all at once
SETTINGS: dict[str, dict[str, Any]] = {
    "clean": {},
    "noise 2 mm": {"noise_mm": 2.0},
    "noise 5 mm": {"noise_mm": 5.0},
    "noise 10 mm": {"noise_mm": 10.0},
    "latency 1": {"latency_steps": 1},
    "latency 3": {"latency_steps": 3},
    "dropout 0.05": {"dropout": 0.05},
    "occlusion": {"occlusion_probability": 0.05, "occlusion_markers": 3, "occlusion_steps": 10},
    # where it breaks: past the grid
    "noise 20 mm": {"noise_mm": 20.0},
    "latency 6": {"latency_steps": 6},
    "dropout 0.3": {"dropout": 0.3},
    "noise 50 mm": {"noise_mm": 50.0},
    "latency 15": {"latency_steps": 15},
    "dropout 0.7": {"dropout": 0.7},
    "5 mm + latency 1": {"noise_mm": 5.0, "latency_steps": 1},
    "all": {"noise_mm": 5.0, "latency_steps": 1, "dropout": 0.05,
            "occlusion_probability": 0.05, "occlusion_markers": 3, "occlusion_steps": 10},
    # a depth camera and the tracker in place of the marker tracker (the pointcloud
    # observation): the camera's defaults (depth noise, stray points, grippers in view), and
    # without its faults
    "camera": {"kind": "pointcloud"},
    "camera clean": {"kind": "pointcloud", "camera": CLEAN_CAMERA},
    # why the camera costs what it costs: a frame every control step (the default camera
    # takes one every second step, 25 Hz), and grippers that hide no cable
    "camera clean 50 Hz": {"kind": "pointcloud", "camera": CLEAN_CAMERA | {"rate_hz": 50.0}},
    "camera clean grippers unseen": {"kind": "pointcloud",
                                      "camera": CLEAN_CAMERA | {"see_grippers": False}},
}  # fmt: skip
#: the settings of the camera's own table (camera.md), beside the clean markers
CAMERA_SETTINGS = ["clean", "camera", "camera clean", "camera clean 50 Hz",
                   "camera clean grippers unseen"]  # fmt: skip


def task(options: argparse.Namespace, observation: dict[str, Any]) -> dict[str, Any]:
    """The paper-scale single task (random-pose starts and a fixed goal per seed)."""
    return {"episode_steps": options.steps, "observation": observation}


MARKERS = {"kind": "markers", "markers": 10}


# ----------------------------------------------------------------------------- learners
def learners(options: argparse.Namespace) -> list[tuple[str, int]]:
    """(learner, seed) of every training job."""
    seeds = range(options.seeds)
    if options.learners is not None:
        return [(name, s) for s in seeds for name in options.learners]
    jobs = [(name, s) for s in seeds for name in ("mpc-markers", "sac-markers", "mpc-full")]
    return jobs + [("mpc-markers-noise5", s) for s in range(options.noise_trained_seeds)]


#: a learner named NAME-20k continues NAME's run to this many transitions (Algorithm 1
#: resumes where it stopped: the same iterations, updates and seeds as one longer run)
LONGER = {"-20k": 20000}
#: a learner named NAME-raw is NAME's model planned from the tracker's raw report
RAW = "-raw"
#: a learner named NAME-prior is NAME's, its model also the camera tracker's prior
PRIOR = "-prior"


def online_spec(options: argparse.Namespace, name: str, seed: int) -> Any:
    from dlocli.runs.online import OnlineSpec

    observation = {"kind": "full"} if name == "mpc-full" else dict(MARKERS)
    if name.endswith("noise5"):
        observation["noise_mm"] = 5.0
    trials = options.trials
    budget = next((n for tag, n in LONGER.items() if name.endswith(tag)), options.budget)
    iters = max(1, (budget // options.steps - options.initial_episodes) // trials)
    fit: dict[str, Any] = {"schedule": "steps", "update_steps": options.update_steps,
                           "lr": options.lr, "eval_every": options.update_steps // 3}  # fmt: skip
    if name != "mpc-full":
        fit |= {"rollout_steps": options.rollout_steps, "rollout_start": 2}
    return OnlineSpec.model_validate({
        "task": task(options, observation), "seed": seed, "iters": iters, "trials": trials,
        "initial_episodes": options.initial_episodes, "model": {"hidden": options.hidden},
        "fit": fit, "out": str(options.out / "learners" / f"{name}-s{seed}"), "threads": 1,
    })  # fmt: skip


def train(job: tuple[argparse.Namespace, str, int]) -> str:
    """One training job (resumes where it stopped)."""
    options, name, seed = job
    import torch

    torch.set_num_threads(1)
    start = time.perf_counter()
    if name.startswith("mpc"):
        train_mpc(options, name, seed)
    else:
        train_sac(options, seed)
    return f"{name}-s{seed}: {time.perf_counter() - start:.0f} s"


def train_mpc(options: argparse.Namespace, name: str, seed: int) -> None:
    from dlocli.rundir import owned
    from dlocli.runs.online.loop import OnlineRun

    spec = online_spec(options, name, seed)
    shorter = next((name.removesuffix(tag) for tag in LONGER if name.endswith(tag)), None)
    if shorter is not None and not spec.out.exists():
        shutil.copytree(options.out / "learners" / f"{shorter}-s{seed}", spec.out)
    spec.out.mkdir(parents=True, exist_ok=True)
    (spec.out / "spec.json").write_text(spec.model_dump_json(indent=1))
    with owned(spec.out):
        run = OnlineRun(spec)
        run.run()
        # the model of every transition collected: one more update after the last trials
        run.update_model(spec.iters + 1, run.dataset_until(spec.iters))


def train_sac(options: argparse.Namespace, seed: int) -> None:
    from dlocli.controllers.base import make_controller
    from dlocli.env.shape_env import make_env

    out = options.out / "learners" / f"sac-markers-s{seed}"
    if (out / "policy" / "model.zip").is_file():
        return
    env = make_env(None, task="single", seed=seed, render_mode=None, **task(options, MARKERS))
    try:
        agent = make_controller("sac", env, seed=seed)
        agent.learn(options.sac_budget)
        agent.save_policy(out / "policy")
    finally:
        env.close()


# ----------------------------------------------------------------------------- evaluation
def evaluate(job: tuple[argparse.Namespace, str, int, str]) -> list[dict[str, Any]]:
    """Every evaluation episode of one learner (or reference) under one setting."""
    options, name, seed, setting = job
    import torch

    from dlocli.controllers.base import make_controller
    from dlocli.env.rollout import episode_scores, rollout, stream_seed
    from dlocli.env.shape_env import make_env

    torch.set_num_threads(1)
    trained_full = name == "mpc-full"
    observation = {"kind": "full"} if trained_full else {**MARKERS, **SETTINGS[setting]}
    env = make_env(None, task="single", seed=seed, render_mode=None, **task(options, observation))
    rows = []
    try:
        controller = make_agent(options, env, name, seed)
        if name.endswith(PRIOR) and getattr(env.tracker, "tracker", None) is not None:
            from dlocli.tracking.model_prior import MarkerModelPrior

            held = env.marker_layout.held
            env.tracker.tracker.prior = MarkerModelPrior(controller.model, held)
        for i in range(options.eval_episodes):
            start = time.perf_counter()
            if name in ("zero", "random"):
                controller = make_controller(name, env, seed=stream_seed(seed, EVAL_STREAM, i, 1))
            episode = rollout(env, controller, stream_seed(seed, EVAL_STREAM, i))
            scores = episode_scores(episode, env.task_spec.episode_steps)
            rows.append({"learner": name, "seed": seed, "setting": setting, "episode": i,
                         **scores, "seconds": round(time.perf_counter() - start, 2),
                         **tracking_errors(env, episode)})  # fmt: skip
    finally:
        env.close()
    return rows


def tracking_errors(env: Any, episode: Any) -> dict[str, float]:
    """What the controller was told of the free markers against where they were, over the
    episode: the mean distance (mm), at the free markers beside the held ones (the grippers
    hide them from a camera), and the share of free marker reports flagged seen."""
    layout = getattr(env, "marker_layout", None)
    if layout is None or episode.markers is None:
        return {}
    from dlocli.env.observation import markers_of_state

    true = markers_of_state(layout, episode.positions, episode.quaternions, episode.grippers)
    steps = min(len(true), len(episode.markers))
    error = np.linalg.norm(episode.markers[:steps] - true[:steps], axis=-1) * 1e3  # (T, M)
    free = np.flatnonzero(~layout.held)
    ends = free[[0, -1]]
    return {"tracking_mm": float(error[:, free].mean()),
            "tracking_ends_mm": float(error[:, ends].mean()),
            "tracking_final_mm": float(error[-1, free].mean()),
            "seen_share": float(episode.visible[:steps][:, free].mean())}  # fmt: skip


def make_agent(options: argparse.Namespace, env: Any, name: str, seed: int) -> Any:
    from dlocli.controllers.base import make_controller
    from dlocli.models.checkpoints import load_planning_model

    if name in ("zero", "random"):
        return None
    name = name.removesuffix(PRIOR)
    raw = name.endswith(RAW)  # the same model, planned from the raw report
    learned = options.out / "learners" / f"{name.removesuffix(RAW)}-s{seed}"
    if name.startswith("sac"):
        agent = make_controller("sac", env, seed=seed)
        agent.load_policy(learned / "policy")
        return agent
    final = sorted((learned / "checkpoints").glob("iter_*.pt"))[-1]
    model = load_planning_model(final)
    options_ = {"tracking": "raw"} if raw else None
    return make_controller("mpc", env, options=options_, seed=seed, model=model)


def evaluation_jobs(options: argparse.Namespace) -> list[tuple[Any, ...]]:
    # doing nothing and random actions do not read the observation: the clean setting only
    jobs = [(options, n, s, "clean") for s in range(options.seeds)
            for n in ("zero", "random", "mpc-full")]  # fmt: skip
    jobs += [(options, n, s, setting) for s in range(options.seeds)
             for n in ("mpc-markers", "sac-markers") for setting in SETTINGS]  # fmt: skip
    jobs += [(options, "mpc-markers-noise5", s, setting)
             for s in range(options.noise_trained_seeds) for setting in SETTINGS]  # fmt: skip
    if options.learners is not None:  # these learners only, the longer runs among them
        longer = [n for n in options.learners if n.endswith((*LONGER, RAW, PRIOR))]
        jobs += [(options, n, s, setting) for s in range(options.seeds) for n in longer
                 for setting in SETTINGS]  # fmt: skip
        jobs = [job for job in jobs if job[1] in options.learners]
    if options.settings is not None:
        jobs = [job for job in jobs if job[3] in options.settings]
    return jobs


def merge_rows(path: Path, rows: list[dict[str, Any]]) -> None:
    """Add ``rows`` to the evaluation file, replacing rows of the same episode."""
    key = lambda r: (r["learner"], r["seed"], r["setting"], r["episode"])  # noqa: E731
    kept = {key(r): r for r in (json.loads(path.read_text()) if path.is_file() else [])}
    kept |= {key(r): r for r in rows}
    path.write_text(json.dumps(list(kept.values()), indent=0))


# ----------------------------------------------------------------------------- report
def report(options: argparse.Namespace) -> None:
    rows = json.loads((options.out / "evaluation.json").read_text())
    write_csv(HERE / "results.csv", rows)
    table = summarise(rows)
    (HERE / "table.md").write_text(markdown(table))
    plot(table, HERE / "robustness.png")
    print(markdown(table))


def write_csv(path: Path, rows: list[dict[str, Any]]) -> None:
    import csv

    fields = list(dict.fromkeys(k for r in rows for k in r))  # camera rows have more columns
    with open(path, "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=fields)
        writer.writeheader()
        writer.writerows(rows)


def camera_report(options: argparse.Namespace) -> None:
    """camera.csv, camera_table.md and camera.png: the marker learners through the depth
    camera beside the clean markers, the exact state, doing nothing and random actions."""
    rows = json.loads((options.out / "evaluation.json").read_text())
    rows = [r for r in rows if r["setting"] in CAMERA_SETTINGS]
    write_csv(HERE / "camera.csv", rows)
    table = summarise(rows)
    extra = {}
    for (name, setting), _ in table.items():
        cell = [r for r in rows if (r["learner"], r["setting"]) == (name, setting)]
        extra[(name, setting)] = {k: float(np.mean([r.get(k, np.nan) for r in cell]))
                                  for k in ("tracking_mm", "tracking_ends_mm", "seen_share",
                                            "seconds")}  # fmt: skip
    lines = ["| learner | observation | seeds | initial error (mm) | final error (mm) | score | "
             "tracking error (mm) | at the held ends (mm) | seen | s / episode |",
             "|---|---|---:|---:|---:|---:|---:|---:|---:|---:|"]  # fmt: skip
    names = sorted({n for n, _ in table}, key=lambda n: (n not in LEARNERS, n))
    order = [n for n in LEARNERS if n in names] + [n for n in names if n not in LEARNERS]
    for name in order:
        for setting in CAMERA_SETTINGS:
            cell, more = table.get((name, setting)), extra.get((name, setting))
            if cell is None:
                continue
            seen, track = _shown(more["seen_share"], 2), _shown(more["tracking_mm"], 1)
            ends = _shown(more["tracking_ends_mm"], 1)
            observed = "full state" if name == "mpc-full" else setting
            if name in ("zero", "random"):  # they read no observation: nothing tracked
                observed, seen, track, ends = "(none)", "", "", ""
            lines.append(
                f"| {name} | {observed} | {cell['seeds']} | {cell['initial']:.1f} | "
                f"{cell['final']:.1f} ± {cell['final_std']:.1f} | "
                f"{cell['score']:.2f} ± {cell['score_std']:.2f} | {track} | {ends} | {seen} | "
                f"{more['seconds']:.1f} |"
            )
    text = "\n".join(lines) + "\n"
    (HERE / "camera_table.md").write_text(text)
    plot_camera(table, order, HERE / "camera.png")
    print(text)


def _shown(value: float, digits: int) -> str:
    """A table cell: blank where no episode measured it (NaN)."""
    return "" if np.isnan(value) else f"{value:.{digits}f}"


def plot_camera(table: dict[tuple[str, str], dict[str, float]], order: list[str],
                path: Path) -> None:  # fmt: skip
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    learners_ = [n for n in order if n not in ("zero", "random", "mpc-full")]
    fig, ax = plt.subplots(figsize=(9, 4.2))
    width = 0.8 / max(len(learners_), 1)
    for i, name in enumerate(learners_):
        cells = [(j, table[(name, s)]) for j, s in enumerate(CAMERA_SETTINGS)
                 if (name, s) in table]  # fmt: skip
        x = [j + (i - (len(learners_) - 1) / 2) * width for j, _ in cells]
        ax.bar(x, [c["score"] for _, c in cells], width, yerr=[c["score_std"] for _, c in cells],
               capsize=2, label=f"{name} ({max(c['seeds'] for _, c in cells)} seeds)")  # fmt: skip
    lines = {"mpc-full": ("mpc-full (exact state)", ":"), "zero": ("doing nothing", "--"),
             "random": ("random actions", "-.")}  # fmt: skip
    for name, (label, style) in lines.items():
        if (name, "clean") in table:
            ax.axhline(table[(name, "clean")]["score"], color="k", lw=0.9, ls=style, label=label)
    ax.axhline(0.9, color="tab:red", lw=0.8, label="issue 54's bar (0.9)")
    ticks = ["markers (clean)" if s == "clean" else s.replace("clean ", "clean\n")
             for s in CAMERA_SETTINGS]  # fmt: skip
    ax.set_xticks(range(len(CAMERA_SETTINGS)), ticks)
    ax.set_ylabel("score, mean of seeds")
    ax.set_ylim(min(-0.1, *(c["score"] - 0.05 for c in table.values())), 1.05)
    ax.set_title("Marker-model MPC through the depth camera (same starts and goals)")
    ax.legend(fontsize=8, ncol=3, loc="upper center", bbox_to_anchor=(0.5, -0.3))
    fig.tight_layout()
    fig.savefig(path, dpi=120)


def summarise(rows: list[dict[str, Any]]) -> dict[tuple[str, str], dict[str, float]]:
    """Per (learner, setting): mean and std over seeds of the per-seed mean final error and
    score, and the mean initial error."""
    cells: dict[tuple[str, str], dict[int, list[dict[str, Any]]]] = {}
    for r in rows:
        cells.setdefault((r["learner"], r["setting"]), {}).setdefault(r["seed"], []).append(r)
    table = {}
    for key, seeds in cells.items():
        final = [np.mean([r["final_error_mm"] for r in rs]) for rs in seeds.values()]
        score = [np.mean([r["score"] for r in rs]) for rs in seeds.values()]
        initial = [np.mean([r["initial_error_mm"] for r in rs]) for rs in seeds.values()]
        table[key] = {"final": float(np.mean(final)), "final_std": float(np.std(final)),
                      "score": float(np.mean(score)), "score_std": float(np.std(score)),
                      "initial": float(np.mean(initial)), "seeds": len(seeds)}  # fmt: skip
    return table


LEARNERS = [
    "zero",
    "random",
    "mpc-full",
    "mpc-markers",
    "mpc-markers-20k",
    "mpc-markers-20k-raw",
    "mpc-markers-noise5",
    "sac-markers",
]


def markdown(table: dict[tuple[str, str], dict[str, float]]) -> str:
    lines = ["| learner | setting | seeds | initial error (mm) | final error (mm) | score |",
             "|---|---|---:|---:|---:|---:|"]  # fmt: skip
    for name in LEARNERS:
        for setting in SETTINGS:
            cell = table.get((name, setting))
            if cell is None:
                continue
            lines.append(
                f"| {name} | {setting} | {cell['seeds']} | {cell['initial']:.1f} | "
                f"{cell['final']:.1f} ± {cell['final_std']:.1f} | "
                f"{cell['score']:.2f} ± {cell['score_std']:.2f} |"
            )
    return "\n".join(lines) + "\n"


def plot(table: dict[tuple[str, str], dict[str, float]], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    settings = list(SETTINGS)
    fig, ax = plt.subplots(figsize=(11, 4.6))
    lines = {"zero": ("doing nothing", "--"), "random": ("random actions", "-."),
             "mpc-full": ("mpc-full (exact state)", ":")}  # fmt: skip
    shown = [n for n in LEARNERS if n not in lines and any((n, s) in table for s in settings)]
    width = 0.8 / len(shown)
    for i, name in enumerate(shown):
        x = [j + (i - (len(shown) - 1) / 2) * width for j, s in enumerate(settings)
             if (name, s) in table]  # fmt: skip
        y = [table[(name, s)]["final"] for s in settings if (name, s) in table]
        err = [table[(name, s)]["final_std"] for s in settings if (name, s) in table]
        seeds = max(table[(name, s)]["seeds"] for s in settings if (name, s) in table)
        ax.bar(x, y, width, yerr=err, label=f"{name} ({seeds} seeds)", capsize=2)
    for name, (label, style) in lines.items():
        if (name, "clean") in table:
            ax.axhline(table[(name, "clean")]["final"], color="k", lw=0.9, ls=style, label=label)
    ax.set_xticks(range(len(settings)), settings, rotation=25, ha="right")
    ax.set_ylabel("final shape error (mm), mean of seeds")
    ax.set_yscale("log")
    ax.set_title("Trained once on clean markers, evaluated under each tracker setting "
                 "(same starts and goals)")  # fmt: skip
    ax.legend(fontsize=8, ncol=4, loc="upper center", bbox_to_anchor=(0.5, -0.32))
    fig.tight_layout()
    fig.savefig(path, dpi=120)


# ----------------------------------------------------------------------------- main
def run_jobs(function: Any, jobs: list[Any], workers: int) -> list[Any]:
    results = []
    with ProcessPoolExecutor(workers) as pool:
        for done, result in enumerate(pool.map(function, jobs), 1):
            print(f"[{done}/{len(jobs)}] {result if isinstance(result, str) else ''}", flush=True)
            results.append(result)
    return results


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("stage", choices=["train", "evaluate", "report", "camera-report"])
    parser.add_argument("--out", type=Path, default=Path("runs/robustness"))
    parser.add_argument("--seeds", type=int, default=3)
    parser.add_argument("--noise-trained-seeds", type=int, default=1)
    parser.add_argument("--budget", type=int, default=20000, help="mpc's transitions")
    parser.add_argument("--sac-budget", type=int, default=20000)
    parser.add_argument("--steps", type=int, default=200, help="episode length T")
    parser.add_argument("--initial-episodes", type=int, default=10)
    parser.add_argument("--trials", type=int, default=10, help="MPC trials per iteration")
    parser.add_argument("--update-steps", type=int, default=500)
    parser.add_argument("--rollout-steps", type=int, default=8)
    parser.add_argument("--lr", type=float, default=1e-3)
    parser.add_argument("--hidden", type=int, default=64)
    parser.add_argument("--eval-episodes", type=int, default=5)
    parser.add_argument("--workers", type=int, default=os.cpu_count() or 1)
    parser.add_argument("--learners", type=lambda s: s.split(","), default=None,
                        help="train or evaluate these learners only (comma-separated)")  # fmt: skip
    parser.add_argument("--settings", type=lambda s: s.split(","), default=None,
                        help="evaluate under these settings only (comma-separated)")  # fmt: skip
    options = parser.parse_args()
    options.out.mkdir(parents=True, exist_ok=True)
    if options.stage == "train":
        run_jobs(train, [(options, n, s) for n, s in learners(options)], options.workers)
    elif options.stage == "evaluate":
        rows = run_jobs(evaluate, evaluation_jobs(options), options.workers)
        merge_rows(options.out / "evaluation.json", [r for rs in rows for r in rs])
    elif options.stage == "report":
        report(options)
    else:
        camera_report(options)


if __name__ == "__main__":
    sys.exit(main())
