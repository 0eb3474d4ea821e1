"""Does a model learned with one gripper control two? (the paper's Fig. 5, issue 14)

    python benchmarks/bimanual_transfer.py --bench examples/bench_paper \
        --online RUN/work/FP/mpc-s2/online --seed 2 [--epochs 10] [--model mlp]
        [--online-only] [--tasks bimanual,single] [--goals fixed,random] [--json out.json]
        [--mpc curvature_every=1]

Takes the data an ``mpc`` bench job collected online on the single-gripper task (its
``online/`` directory: the initial random data and every trial) and trains, on exactly that
data and with the bench's model and fit settings, two fresh models: one on the recorded
transitions only, one with ``fit.mirror`` (every transition also as its mirrored twin, the
other end acting; :mod:`dlocli.models.mirror`). Each, and the model the job itself learned
online, then controls the rod with the bench's MPC on the bench's bimanual task (the seed's
fixed goal, its evaluation starts: the same episodes as the job's ``bimanual`` row) and on
the single-gripper task it learned on. Doing nothing, random actions and the held-end servo
(no model) on the same episodes are the references. ``--model mlp`` trains the
structure-free baseline instead of the bench's model (the paper's argument for the
Interaction Network is this kind of reuse; the online model is then left out). Fresh models,
not fine-tuned ones: a model's normalisation is fitted on its first data, and single-gripper
data give the left gripper's commands no spread.

``--online-only`` evaluates just the job's own final model (no training: minutes, not
hours); ``--goals fixed,random`` adds the seed's random-goal evaluation episodes, where no
agent has trained around the goal (the bench's bimanual row has the fixed goal only).
``--mpc FIELD=VALUE`` (repeatable) evaluates with other MPC settings than the bench's, e.g.
``curvature_every=1``: the Gauss-Newton Jacobian refreshed at every control step.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path
from typing import Any

import torch

from dlocli.bench.agents import EVAL_CONTROLLER, make_bench_env
from dlocli.bench.jobs import evaluate
from dlocli.bench.spec import BenchSpec
from dlocli.controllers.base import make_controller
from dlocli.controllers.mpc import GradientMPC, MPCSpec
from dlocli.data import Dataset, load_dataset
from dlocli.env.rollout import stream_seed
from dlocli.models.base import build_model
from dlocli.models.checkpoints import load_model
from dlocli.models.fit import fit as fit_model
from dlocli.resume import saved_spec
from dlocli.runs.online import TRAIN


def online_data(online: Path) -> Dataset:
    """The initial data then every trial of an online run directory, in order."""
    files = [online / "data" / "initial.h5", *sorted((online / "data").glob("iter_*/trial_*.h5"))]
    loaded = [load_dataset(f) for f in files]
    return loaded[0].concat(*loaded[1:])


def trained(spec: BenchSpec, data: Dataset, seed: int, epochs: int, mirror: bool) -> Any:
    """A fresh model of the bench's spec trained ``epochs`` epochs on ``data``."""
    torch.manual_seed(stream_seed(seed, TRAIN, 0))
    model = build_model(spec.model, data.n_segments)
    fit = spec.fit.model_copy(  # epochs, whatever schedule the bench's online updates take
        update={"schedule": "epochs", "epochs": epochs, "mirror": mirror,
                "seed": stream_seed(seed, TRAIN, 1) % 2**31}
    )  # fmt: skip
    start = time.perf_counter()
    result = fit_model(model, data, fit)
    print(f"  trained mirror={mirror}: val loss {result.val_loss:.4f}, "
          f"{time.perf_counter() - start:.0f} s", flush=True)  # fmt: skip
    return model


def evaluate_all(
    spec: BenchSpec, seed: int, models: dict[str, Any], settings: list[tuple[str, str]]
) -> list[dict[str, Any]]:
    """Every model (through the bench's MPC) and the references, on every (task, goals)."""
    rows = []
    controller_seed = stream_seed(seed, EVAL_CONTROLLER)
    for task, goals in settings:
        env = make_bench_env(spec, task, goals, seed)
        try:
            controllers = {
                name: GradientMPC(env, model, spec.mpc, seed=controller_seed)
                for name, model in models.items()
            }
            for reference in ("zero", "random", "held-end"):
                controllers[reference] = make_controller(reference, env, seed=controller_seed)
            for name, controller in controllers.items():
                row = {"model": name, "eval_task": task, "eval_goals": goals, "seed": seed}
                row.update(evaluate(controller, env, spec, seed))
                rows.append(row)
                print(f"  {task:8} {goals:6} {name:22} {row['initial_error_mm']:6.1f} -> "
                      f"{row['final_error_mm']:6.1f} mm  score {row['score']:+.2f} "
                      f"(std {row['score_std']:.2f})", flush=True)  # fmt: skip
        finally:
            env.close()
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawTextHelpFormatter
    )
    parser.add_argument("--bench", type=Path, required=True, help="bench run (its spec.json)")
    parser.add_argument("--online", type=Path, required=True, help="an mpc job's online/ dir")
    parser.add_argument("--seed", type=int, required=True, help="that job's seed")
    parser.add_argument("--epochs", type=int, default=None, help="default: the bench's fit")
    parser.add_argument("--model", default=None, help="model name (default: the bench's)")
    parser.add_argument("--online-only", action="store_true", help="no fresh models")
    parser.add_argument("--tasks", default="bimanual,single", help="evaluation tasks")
    parser.add_argument("--goals", default="fixed", help="fixed and/or random")
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--json", type=Path, default=None, help="write the rows here")
    parser.add_argument("--mpc", action="append", default=[], help="FIELD=VALUE of the MPC")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    spec = BenchSpec.model_validate(saved_spec(args.bench / "spec.json"))
    if args.mpc:
        mpc = {**spec.mpc.model_dump(), **dict(field.split("=", 1) for field in args.mpc)}
        spec = spec.model_copy(update={"mpc": MPCSpec.model_validate(mpc)})
    if args.model is not None:
        spec = spec.model_copy(update={"model": spec.model.model_copy(update={"name": args.model})})
    epochs = args.epochs or spec.fit.epochs
    data = online_data(args.online)
    print(f"{data.n_transitions} transitions ({data.n_episodes} episodes); {epochs} epochs")
    last = sorted((args.online / "checkpoints").glob("iter_*.pt"))[-1]
    models = {}
    if args.model is None:
        models[f"online ({last.stem})"] = load_model(last, torch.device("cpu"))
    if not args.online_only:
        name = spec.model.name
        models[f"{name}, fresh"] = trained(spec, data, args.seed, epochs, mirror=False)
        models[f"{name}, fresh + mirror"] = trained(spec, data, args.seed, epochs, mirror=True)
    settings = [(t, g) for t in split(args.tasks) for g in split(args.goals)]
    rows = evaluate_all(spec, args.seed, models, settings)
    if args.json is not None:
        args.json.write_text(json.dumps({"epochs": epochs, "transitions": data.n_transitions,
                                         "model": spec.model.model_dump(mode="json"),
                                         "mpc": spec.mpc.model_dump(mode="json"),
                                         "rows": rows}, indent=1))  # fmt: skip


def split(names: str) -> list[str]:
    return [n.strip() for n in names.split(",") if n.strip()]


if __name__ == "__main__":
    main()
