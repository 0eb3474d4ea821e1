"""The cable's code inferred online during control, on each DEFORM cable's calibrated twin.

One small coded model (``arc-mlp-coded-small.yaml``) trained on DLO1-4 together plans with
the gradient MPC on each cable's twin (examples/twin_control/study.py: the same twin, the
same draw of episodes, the same scoring), under four conditions:

  own       the cable's own learned code (`dlo control --cable DATA`)
  mean      the mean of the four codes (`dlo control` without --cable)
  online    the code inferred while it runs (`dlo control --adapt-code`): the mean code
            first, then every --every steps the trained cable's code (or the mean) that best
            predicts the last --window observed frames
  nothing   the reference: zero commands

    dlo import --source $DEFORM/DLO1 --out runs/oc/data/DLO1   # ... DLO4
    dlo train --spec examples/real_cables/arc-mlp-coded-small.yaml --data runs/oc/data/DLO1 \\
        --data runs/oc/data/DLO2 --data runs/oc/data/DLO3 --data runs/oc/data/DLO4 \\
        --out runs/oc/coded
    python examples/real_cables/online_code.py --model runs/oc/coded --data runs/oc/data \\
        --deform $DEFORM --episodes 6 --seeds 0,1,2

Leave-one-out (a cable the model never saw): ``--model`` and ``--own-model`` may name each
cable's own run with ``{cable}``, e.g. the folds of family_leave_one_out.sh: ``--model
OUT/{cable}-with/model`` (trained without the cable; "mean" and "online" plan with it) and
``--own-model OUT/{cable}-with/code`` (the same model with the code `dlo adapt` fitted to the
cable's first recording: "own"); the recorded re-picks below are then skipped (the cable's own
code is no candidate).

Beside, the same re-picks on each cable's own eval recordings (the real cable, held out of
training, its free markers given 2 mm of noise as on the twin): how often a window's pick is
the cable's own code.

Writes examples/real_cables/online_code.json (every episode, and the mean per cable and
condition); --out holds a copy and each cable, condition and seed's rows (a rerun skips those done).
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import os
import time
from pathlib import Path
from typing import Any

import numpy as np

HERE = Path(__file__).resolve().parent
STUDY = HERE.parent / "twin_control" / "study.py"
CABLES = ("DLO1", "DLO2", "DLO3", "DLO4")
CONDITIONS = ("nothing", "own", "mean", "online")


def load_study() -> Any:
    spec = importlib.util.spec_from_file_location("twin_study", STUDY)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def controller(name: str, env: Any, options: argparse.Namespace, cable: str, seed: int) -> Any:
    """The condition's controller on ``env`` (None: doing nothing, drawn per episode)."""
    from dlocli.controllers.base import make_controller
    from dlocli.data import load_dataset
    from dlocli.models.checkpoints import load_planning_model
    from dlocli.models.code_follow import CodeFollower
    from dlocli.models.code_pick import cable_names
    from dlocli.runs.control_code import CodeAdapting, observe_with

    if name == "nothing":
        return None
    run = run_of(options.own_model if name == "own" else options.model, cable)
    model = load_planning_model(run)
    observe_with(model, env)  # the twin's markers (DLO1 has 13, the others 12)
    if name == "own":
        data = load_dataset(options.data / cable)
        assert model.use_recorded_cable(data.held, data.episodes("train")) is not None
    mpc = make_controller("mpc", env, seed=seed, model=model)
    if name != "online":
        return mpc
    names = cable_names(run, model.cable_keys)
    return CodeAdapting(mpc, env, CodeFollower(model, names, options.every, options.window))


def run_of(template: str, cable: str) -> Path:
    """The run a ``--model``-style template names for ``cable``."""
    return Path(template.replace("{cable}", cable))


def evaluate(
    study: Any, options: argparse.Namespace, cable: str, name: str, seed: int
) -> list[dict]:
    import torch

    from dlocli.controllers.base import make_controller
    from dlocli.env.metrics import score
    from dlocli.env.rollout import rollout, stream_seed
    from dlocli.env.shape_env import make_env

    torch.set_num_threads(1)
    twin, _, _ = study.load_twin(cable, options, seed)
    env = make_env(twin.spec.backend, task=twin.spec.task, seed=seed)
    rows = []
    try:
        policy = controller(name, env, options, cable, seed)
        for i, (index, start, goal) in enumerate(study.draw_episodes(twin, seed, options.episodes)):
            began = time.perf_counter()
            if name == "nothing":
                policy = make_controller("zero", env, seed=stream_seed(seed, 7, i))
            recording = twin.recordings[index][1]
            episode = rollout(env, policy, stream_seed(seed, 5, i),
                              options=twin.options(recording, start, goal))  # fmt: skip
            initial, final = study.marker_errors(env, episode)
            row = {
                "cable": cable, "condition": name, "seed": seed, "episode": i,
                "recording": twin.recordings[index][0], "start_frame": start, "goal_frame": goal,
                "initial_marker_error_mm": round(initial, 2),
                "final_marker_error_mm": round(final, 2), "score": round(score(initial, final), 4),
                "diverged": bool(episode.diverged),
                "seconds": round(time.perf_counter() - began, 2),
            }  # fmt: skip
            if name == "online":
                row |= policy.summary()
            rows.append(row)
            code = f" ({row['code_final']})" if name == "online" else ""
            print(f"{cable} {name} {i}: {initial:.1f} -> {final:.1f} mm{code}", flush=True)
    finally:
        env.close()
    return rows


def recorded_picks(options: argparse.Namespace) -> dict[str, dict[str, Any]]:
    """Per cable: every re-pick (every --every frames, the last --window) along its eval
    recordings, 2 mm of noise on the free markers; the share that is the cable's own code."""
    from collections import Counter

    import torch

    from dlocli.data import load_dataset
    from dlocli.models.checkpoints import load_planning_model
    from dlocli.models.code_follow import CodeFollower
    from dlocli.models.code_pick import cable_names

    torch.set_num_threads(1)
    if "{cable}" in options.model:  # leave-one-out: the cable's own code is no candidate
        return {}
    model = load_planning_model(Path(options.model))
    names = cable_names(Path(options.model), model.cable_keys)
    rng = np.random.default_rng(0)
    found = {}
    for cable in options.cables:
        data = load_dataset(options.data / cable)
        model.held = model.held.new_tensor(data.held)
        picks = []
        for episode in data.episodes("eval"):
            follower = CodeFollower(model, names, options.every, options.window)
            noisy = episode.copy()
            noisy[:, ~data.held] += rng.normal(0, 0.002, noisy[:, ~data.held].shape)
            picks += [p.name for t, f in enumerate(noisy) if (p := follower.observe(t, f))]
        own = picks.count(f"{cable}'s code")
        found[cable] = {"picks": len(picks), "own_pct": round(100 * own / max(len(picks), 1), 1),
                        "counts": dict(Counter(picks).most_common())}  # fmt: skip
        print(cable, "eval recordings:", json.dumps(found[cable]), flush=True)
    return found


def summarise(rows: list[dict]) -> dict[str, dict[str, dict[str, float]]]:
    """Per cable and condition: the mean over episodes (of every seed) of the final error
    (mm), score and initial error, the spread of the seeds' mean scores; for the online
    code, how many episodes ended on the cable's own code, and its share of all picks."""
    table: dict[str, dict[str, dict[str, float]]] = {}
    for cable in CABLES:
        for name in CONDITIONS:
            mine = [r for r in rows if r["cable"] == cable and r["condition"] == name]
            if not mine:
                continue
            entry = {"final_mm": round(mean_of(mine, "final_marker_error_mm"), 2),
                     "score": round(mean_of(mine, "score"), 4),
                     "initial_mm": round(mean_of(mine, "initial_marker_error_mm"), 2),
                     "score_seed_std": round(seed_spread(mine), 4),
                     "episodes": len(mine)}  # fmt: skip
            if name == "online":
                own = f"{cable}'s code"
                entry["final_code_own"] = sum(r["code_final"] == own for r in mine)
                picks = [p["code"] for r in mine for p in r["code_picks"]]
                entry["picks_own_pct"] = round(100 * picks.count(own) / max(len(picks), 1), 1)
            table.setdefault(cable, {})[name] = entry
    return table


def mean_of(rows: list[dict], key: str) -> float:
    return float(np.mean([r[key] for r in rows]))


def seed_spread(rows: list[dict]) -> float:
    """The standard deviation over seeds of each seed's mean score."""
    seeds = sorted({r["seed"] for r in rows})
    return float(np.std([mean_of([r for r in rows if r["seed"] == s], "score") for s in seeds]))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--model", required=True,
                        help="the coded model's run ({cable}: each cable's own)")  # fmt: skip
    parser.add_argument("--own-model", default=None,
                        help="the run 'own' plans with (default --model)")  # fmt: skip
    parser.add_argument("--data", type=Path, required=True, help="folder of DLO1..4 datasets")
    parser.add_argument("--deform", type=Path, default=Path(os.environ.get("DEFORM", "DEFORM")))
    parser.add_argument("--calibration", type=Path,
                        default=HERE.parent / "calibration" / "results")  # fmt: skip
    parser.add_argument("--out", type=Path, default=Path("runs/online_code"))
    parser.add_argument("--cables", type=lambda s: s.split(","), default=list(CABLES))
    parser.add_argument("--conditions", type=lambda s: s.split(","), default=list(CONDITIONS))
    parser.add_argument("--episodes", type=int, default=6)
    parser.add_argument("--seeds", type=lambda s: [int(x) for x in s.split(",")], default=[0],
                        help="seeds, comma-separated: each draws its own episodes")  # fmt: skip
    parser.add_argument("--steps", type=int, default=500, help="control steps per episode")
    parser.add_argument("--every", type=int, default=50, help="--adapt-every")
    parser.add_argument("--window", type=int, default=100, help="--adapt-window")
    parser.add_argument("--result", type=Path, default=HERE / "online_code.json")
    options = parser.parse_args()
    options.own_model = options.own_model or options.model
    options.out.mkdir(parents=True, exist_ok=True)
    study = load_study()
    rows: list[dict] = []
    for seed in options.seeds:
        for cable in options.cables:
            for name in options.conditions:
                saved = options.out / f"{cable}-{name}-s{seed}.json"
                if not saved.is_file():
                    found = evaluate(study, options, cable, name, seed)
                    saved.write_text(json.dumps(found, indent=1))
                rows += json.loads(saved.read_text())
    result = {
        "model": options.model, "own_model": options.own_model, "seeds": options.seeds,
        "episodes": options.episodes,
        "steps": options.steps, "adapt_every": options.every, "adapt_window": options.window,
        "summary": summarise(rows), "recorded_picks": recorded_picks(options), "rows": rows,
    }  # fmt: skip
    (options.out / "online_code.json").write_text(json.dumps(result, indent=1) + "\n")
    # here: each re-pick as [step, code] (--out keeps every candidate's score), a row a line
    result["rows"] = [{**r, "code_picks": [[p["step"], p["code"]] for p in r["code_picks"]]}
                      if "code_picks" in r else r for r in rows]  # fmt: skip
    lines = ",\n  ".join(json.dumps(r) for r in result.pop("rows"))
    head = json.dumps(result, indent=1)[:-2]
    options.result.write_text(f'{head},\n "rows": [\n  {lines}\n ]\n}}\n')
    for cable, entries in result["summary"].items():
        print(cable, json.dumps(entries))


if __name__ == "__main__":
    main()
