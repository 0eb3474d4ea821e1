"""Sim-to-real on one DEFORM cable: does pre-training on the calibrated rod save real data?

    python examples/calibration/sim_to_real.py CALIBRATION_RUN REAL_DATA REAL_RUNS OUT

CALIBRATION_RUN: a `dlo calibrate` run (its spec.json names the cable, calibrated.yaml the
rod); REAL_DATA: the cable's `dlo import` run; REAL_RUNS: the folder of the real-data-only
mlp runs on all 56 train recordings (mlp-s0-eval, ...: examples/real_cables/run.sh); OUT: a
folder for the runs. It simulates 56 trajectories of the calibrated rod
(`dlocli.calibration.simulate`), trains the mlp recipe on them alone, fine-tunes that model on
1, 4, 16 and 56 real train recordings (nested seeded draws) and once more on 16 and
56 for as many steps as the real-only recipe on 56, trains the recipe on 1, 4 and 16
real recordings alone, scores everything on the real eval recordings (`dlo eval`), and
writes OUT/sim_to_real.json and OUT/sim_to_real.png. Step counts (fewer than the recipe's
1000 for fine-tuning and for the small real-only runs) are set below.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import yaml

from dlocli.calibration.fit import load_cable, replay_settings
from dlocli.calibration.simulate import simulate_markers
from dlocli.calibration.spec import CalibrateSpec
from dlocli.data import MarkerDataset, load_dataset
from dlocli.registry import backends
from dlocli.specs import BackendSpec

HERE = Path(__file__).parent
RECIPE = HERE.parent / "real_cables" / "mlp.yaml"
SIMULATED = 56
COUNTS = (1, 4, 16, 56)
LONG_COUNTS = (16, 56)
LONG_SEEDS = 3
PRETRAIN_STEPS, FINETUNE_STEPS, SMALL_REAL_STEPS, RECIPE_STEPS = 1000, 200, 300, 1000


def dlo(*argv: str) -> dict:
    """Run a `dlo` command with --json; its summary."""
    done = subprocess.run([sys.executable, "-m", "dlocli", *argv, "--json"], check=True,
                          capture_output=True, text=True, env=os.environ)  # fmt: skip
    return json.loads(done.stdout)


def simulated_dataset(calibration: Path, out: Path) -> dict:
    """OUT/sim/dataset.h5: the calibrated rod under rigidly moved recorded held motion."""
    spec = CalibrateSpec.model_validate_json((calibration / "spec.json").read_text())
    cable = load_cable(spec)
    rod = BackendSpec.model_validate(
        yaml.safe_load((calibration / "calibrated.yaml").read_text())["backend"]
    )
    backend = backends.get(rod.name)(rod, control_dt=1.0 / spec.rate_hz)
    settings = replay_settings(spec, cable.held)
    sims, dropped = simulate_markers(backend, [r for _, r in cable.train], cable.arc,
                                     SIMULATED, 0, settings)  # fmt: skip
    held = cable.held
    named = {"train": [(f"sim{i}", s) for i, s in enumerate(sims)]}
    data = MarkerDataset.from_trajectories(named, held, {"rate_hz": spec.rate_hz,
                                                         "source": str(calibration)})  # fmt: skip
    (out / "sim").mkdir(parents=True, exist_ok=True)
    data.save(out / "sim" / "dataset.h5")
    return {"simulated": len(sims), "dropped_diverged": dropped}


def real_subsets(real: Path, out: Path) -> None:
    """OUT/real-K/dataset.h5: K train recordings (nested seeded draws) and the eval split."""
    data = load_dataset(real / "dataset.h5")
    train = list(zip(data.episode_names("train"), data.episodes("train"), strict=True))
    evaluation = list(zip(data.episode_names("eval"), data.episodes("eval"), strict=True))
    order = np.random.default_rng(0).permutation(len(train))
    for k in COUNTS:
        picked = [train[i] for i in sorted(order[:k])]
        subset = MarkerDataset.from_trajectories({"train": picked, "eval": evaluation},
                                                 data.held, data.attrs)  # fmt: skip
        (out / f"real-{k}").mkdir(parents=True, exist_ok=True)
        subset.save(out / f"real-{k}" / "dataset.h5")


def train_and_score(name: str, data: Path, real: Path, out: Path, steps: int,
                    init: Path | None = None, seed: int = 0) -> float:  # fmt: skip
    run = out / name
    if not (out / f"{name}-eval" / "summary.json").is_file():
        extra = ["--init-from", str(init)] if init else []
        dlo("train", "--spec", str(RECIPE), "--data", str(data), "--update-steps", str(steps),
            "--seed", str(seed), "--out", str(run), "--overwrite", *extra)  # fmt: skip
        dlo("eval", "--checkpoint", str(run), "--data", str(real), "--out",
            str(out / f"{name}-eval"), "--overwrite")  # fmt: skip
    score = json.loads((out / f"{name}-eval" / "summary.json").read_text())["model_score_cm"]
    print(f"{name}: {score} cm", flush=True)
    return float(score)


def main(calibration: Path, real: Path, real_runs: Path, out: Path) -> None:
    out.mkdir(parents=True, exist_ok=True)
    if not (out / "sim" / "info.json").is_file():
        info = simulated_dataset(calibration, out)
        (out / "sim" / "info.json").write_text(json.dumps(info) + "\n")
    info = json.loads((out / "sim" / "info.json").read_text())
    if not (out / f"real-{COUNTS[-1]}" / "dataset.h5").is_file():
        real_subsets(real, out)
    sim_only = train_and_score("sim-only", out / "sim", real, out, PRETRAIN_STEPS)
    finetuned = {k: train_and_score(f"finetuned-{k}", out / f"real-{k}", real, out,
                                    FINETUNE_STEPS, out / "sim-only") for k in COUNTS}  # fmt: skip
    # the 56 real-only row trains 1000 steps: fine-tune as long for like-for-like points
    # (3 training seeds on the same draw, as the real-only runs on 56)
    long_seeds = {k: [train_and_score(f"finetuned-{k}-long" + (f"-s{s}" if s else ""),
                                      out / f"real-{k}", real, out, RECIPE_STEPS,
                                      out / "sim-only", s) for s in range(LONG_SEEDS)]
                  for k in LONG_COUNTS}  # fmt: skip
    finetuned_long = {k: float(np.mean(v)) for k, v in long_seeds.items()}
    alone = {k: train_and_score(f"real-only-{k}", out / f"real-{k}", real, out,
                                SMALL_REAL_STEPS) for k in COUNTS[:-1]}  # fmt: skip
    recipe_56 = [json.loads((real_runs / f"mlp-s{s}-eval" / "summary.json").read_text())
                 ["model_score_cm"] for s in range(3)]  # fmt: skip
    alone[COUNTS[-1]] = float(np.mean(recipe_56))
    freeze = json.loads((out / "sim-only-eval" / "summary.json").read_text())["freeze_score_cm"]
    result = {"calibration": calibration.name, **info, "sim_only_cm": sim_only,
              "finetuned_cm": finetuned, "finetuned_long_cm": finetuned_long,
              "finetuned_long_seeds_cm": long_seeds,
              "real_only_cm": alone, "real_only_56_seeds_cm": recipe_56,
              "freeze_cm": freeze,
              "steps": {"pretrain": PRETRAIN_STEPS, "finetune": FINETUNE_STEPS,
                        "real_only_small": SMALL_REAL_STEPS, "real_only_56": RECIPE_STEPS,
                        "finetune_long": RECIPE_STEPS}}  # fmt: skip
    (out / "sim_to_real.json").write_text(json.dumps(result, indent=1) + "\n")
    plot(result, out / "sim_to_real.png", calibration.name)


def plot(result: dict, path: Path, title: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(5.5, 3.8))
    ks = list(COUNTS)
    steps = result["steps"]
    ax.plot(ks, [result["real_only_cm"][k] for k in ks], "o-",
            label=f"real data only ({steps['real_only_small']} steps; "
                  f"{steps['real_only_56']} on 56, 3 seeds)")  # fmt: skip
    ax.plot(ks, [result["finetuned_cm"][k] for k in ks], "s-",
            label=f"simulation, then real ({steps['finetune']} steps)")  # fmt: skip
    ax.plot(ks, [result["sim_only_cm"]] * len(ks), "--", label="simulation only (0 real)")
    long, spread = result["finetuned_long_cm"], result["finetuned_long_seeds_cm"]
    label = f"simulation, then real ({steps['finetune_long']} steps, 3 seeds)"
    ax.errorbar(list(long), list(long.values()), fmt="*", markersize=11, label=label,
                yerr=[[long[k] - min(spread[k]) for k in long],
                      [max(spread[k]) - long[k] for k in long]])  # fmt: skip
    seeds_56 = result["real_only_56_seeds_cm"]
    ax.vlines(ks[-1], min(seeds_56), max(seeds_56), color="C0")  # the real-only seeds' range
    ax.set_xscale("log")
    ax.set_xticks(ks, [str(k) for k in ks])
    ax.set_xlabel("real train trajectories")
    ax.set_ylabel("real eval error, DEFORM score (cm)")
    ax.set_title(f"{title} (freeze reference: {result['freeze_cm']:.2f} cm)")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


if __name__ == "__main__":
    main(*(Path(a) for a in sys.argv[1:5]))  # re-running redraws from the finished runs
