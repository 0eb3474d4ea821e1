"""Why the README's main job closes less of the shape error on the flex rod: one factor at a time,
on the run directories of `dlo online` (flex rod on MuJoCo 4, composite cable on MuJoCo 3; run
each command in the environment of the run's backend).

    python benchmarks/flex_control_gap.py model RUN           # what the models see and predict
    python benchmarks/flex_control_gap.py trials RUN [--horizon H] [--noise-probability P]
                                                 [--max-step S] [--settle-steps S] [--trials N]
                                                 [--iteration K] [--set FIELD=JSON ...]
    python benchmarks/flex_control_gap.py sweep RUN [RUN ...] [--iteration K] [--trials N]
                                                [--set FIELD=JSON ...] [--controller NAME]
    python benchmarks/flex_control_gap.py latency RUN [--iteration K] [--steps T] [--rounds R]
                                                  [--only "NAME;NAME"]
    python benchmarks/flex_control_gap.py pose RUN [--iteration K] [--trials N]
                                               [--offset-mm D] [--turn-deg A] [--roll]
    python benchmarks/flex_control_gap.py reference RUN [--iteration K] [--trials N]
                                                    [--name held-end]
    python benchmarks/flex_control_gap.py horizon RUN [--iteration K] [--steps 1,5,10,20]
                                                  [--from-step S]
    python benchmarks/flex_control_gap.py retrain RUN K OUT [--seed S]
    python benchmarks/flex_control_gap.py ensemble OUT COPY [COPY ...]
    python benchmarks/flex_control_gap.py swing BACKEND [--rod JSON]

``model``: per iteration k, the one-step loss of iteration k's model (normalised change of each
state feature, the training objective) on the validation split it was fitted with (one
episode at these sizes) and on the trials it then drove (unseen); the jitter of the observed
positions and orientations (energy of the second difference over the first's); the middle's
speed per episode. ``trials``: the MPC trials of iteration K's saved model from iteration K's
starts (the run's seeds: trials 1..5 repeat the run's), with planner options changed (``--set``
takes any spec field, e.g. ``mpc.motion_cost=32``); per
trial the final error, the mean and least error of the last 40 steps, and the error after
the grippers then stand still for 50 steps, and how far the grippers end from the goal's own
gripper poses. ``sweep``: planner options (over the paper's: SWEEP_BASE) on iteration K's
models of several runs, N trials each, as ``trials`` runs them: the share of the error closed
over all trials and per run (``--controller held-end``: the no-model servo from the same starts,
with the same action noise). ``latency``: the MPC's milliseconds per control step of the
paper's cost and of the options that damp the swing, through one model, taking turns
(:func:`latency_report`). ``pose``: no model, the grippers driven straight to the goal's own gripper
poses from the same starts (:func:`pose_report`). ``reference``: a registered reference
(``held-end`` by default) from iteration K's trial starts, as the run's references ran
(:func:`reference_report`; a run folder without checkpoints will do). ``horizon``:
iteration K's model open loop on the trials it drove (from step S on), its position error
after 1, 5, 10, 20 steps beside the recorded motion over as many steps. ``retrain``:
iteration 3's model retrained through K-step rollouts (:func:`retrain`), into a copy of the
run at OUT (``--seed``: its batches and input noise). ``ensemble``: retrained copies'
iteration-3 models averaged as one ensemble (:func:`ensemble`), into a copy of the first at
OUT. ``swing``: the sideways swing decay of the task's rod
(examples/calibration/swing_decay.py's measurement). Each prints one JSON object.
"""

from __future__ import annotations

import argparse
import json
import runpy
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

HERE = Path(__file__).resolve().parent
FEATURES = ("x", "y", "z", "qw", "qx", "qy", "qz")
LAST = 40  # steps: the end of an episode the final error is judged on
HOLD = 50  # steps the grippers stand still after a trial


def _datasets(run: Path) -> dict[int, Any]:
    """The run's data per iteration: 0 the initial random episodes, k iteration k's trials."""
    from dlocli.data import load_dataset

    found = {0: load_dataset(run / "data" / "initial.h5")}
    for folder in sorted((run / "data").glob("iter_*")):
        files = [load_dataset(f) for f in sorted(folder.glob("trial_*.h5"))]
        found[int(folder.name.split("_")[1])] = files[0].concat(*files[1:])
    return found


def _episodes(data: Any) -> list[tuple[np.ndarray, np.ndarray]]:
    """(positions, quaternions) of each episode, float64."""
    ends = np.concatenate([[0], np.cumsum(data.episode_lengths + 1)])
    return [
        (data.positions[a:b].astype(float), data.quaternions[a:b].astype(float))
        for a, b in zip(ends[:-1], ends[1:], strict=True)
    ]


def _jitter(series: np.ndarray) -> tuple[float, float]:
    """(energy of the second difference, of the first) over time of a (T, ...) series."""
    second, first = np.diff(series, 2, axis=0), np.diff(series, axis=0)
    return float(np.sum(second**2)), float(np.sum(first**2))


def motion(data: Any, control_dt: float) -> dict[str, Any]:
    """The middle segment's speed (m/s) per episode, the largest segment turning rate (rad/s)
    and the jitter of positions and orientations."""
    speeds, turning, jitter = [], [], np.zeros((2, 2))
    for positions, quats in _episodes(data):
        middle = positions[:, positions.shape[1] // 2]
        speeds.append(float(np.linalg.norm(np.diff(middle, axis=0), axis=1).max() / control_dt))
        aligned = quats.copy()
        for t in range(1, len(aligned)):  # q and -q are one rotation: keep the series continuous
            aligned[t] *= np.where(np.sum(aligned[t] * aligned[t - 1], -1) < 0, -1.0, 1.0)[:, None]
        change = np.linalg.norm(np.diff(aligned, axis=0), axis=-1)
        turning.append(float(2.0 * change.max() / control_dt))
        jitter += [_jitter(positions), _jitter(aligned)]
    return {
        "middle_speed_max_per_episode": [round(s, 3) for s in speeds],
        "turning_max_rad_s": round(max(turning), 3),
        "position_jitter": round(jitter[0, 0] / jitter[0, 1], 4),
        "orientation_jitter": round(jitter[1, 0] / jitter[1, 1], 4),
    }


def one_step_loss(model: Any, data: Any, episodes: np.ndarray | None = None) -> dict[str, Any]:
    """The training objective per state feature on ``data``'s ``episodes`` (None: all)."""
    import torch

    from dlocli.models.base import target_delta

    arrays = data.transitions(episodes)
    t = {k: torch.as_tensor(v, dtype=torch.float32) for k, v in arrays.items()}
    with torch.no_grad():
        target = (target_delta(t["state"], t["next_state"]) - model.delta_mean) / model.delta_std
        features = model.normalize(t["state"], t["action"], t["previous_state"])
        error = ((model.predict_delta(*features) - target) ** 2).mean(dim=(0, 1)).numpy()
    return {
        "all": round(float(error.mean()), 4),
        "positions": round(float(error[:3].mean()), 4),
        "orientations": round(float(error[3:].mean()), 4),
        "per_feature": {f: round(float(e), 4) for f, e in zip(FEATURES, error, strict=True)},
    }


def open_loop_error(
    model: Any, data: Any, steps: tuple[int, ...], first: int = 1
) -> dict[str, Any]:
    """The model's open-loop position error (mm, mean over segments and starts) after each
    of ``steps`` steps of the recorded actions, from every 5th step of every episode from
    step ``first`` on, beside the recorded motion over as many steps (what predicting no
    change would miss)."""
    import torch

    found: dict[str, Any] = {}
    for h in steps:
        errors, moved = [], []
        for e in range(data.n_episodes):
            episode = data.episode(e)
            states = np.concatenate([episode.positions, episode.quaternions], -1)
            starts = np.arange(max(first, 1), len(episode.actions) - h + 1, 5)
            if len(starts) == 0:
                continue
            t = torch.as_tensor(states, dtype=torch.float32)
            actions = torch.as_tensor(episode.actions, dtype=torch.float32)
            windows = torch.stack([actions[s : s + h] for s in starts])
            with torch.no_grad():
                predicted = model.rollout(t[starts], windows, t[starts - 1])[:, -1, :, :3]
            truth = t[starts + h, :, :3]
            errors.append((predicted - truth).norm(dim=-1).mean(-1))
            moved.append((truth - t[starts, :, :3]).norm(dim=-1).mean(-1))
        found[str(h)] = {
            "error_mm": round(1000.0 * float(torch.cat(errors).mean()), 2),
            "motion_mm": round(1000.0 * float(torch.cat(moved).mean()), 2),
        }
    return found


def horizon_report(run: Path, k: int, steps: tuple[int, ...], first: int = 1) -> dict[str, Any]:
    """Iteration k's model, open loop on the trials it drove from step ``first`` on
    (:func:`open_loop_error`; 100: the second half, where a trial ends near its goal)."""
    from dlocli.models.checkpoints import load_model

    model = load_model(run / "checkpoints" / f"iter_{k:02d}.pt").eval()
    return {"run": str(run), "iteration": k, "from_step": first,
            "its_trials": open_loop_error(model, _datasets(run)[k], steps, first)}  # fmt: skip


def retrain(run: Path, k: int, out: Path, epochs: int = 10, seed: int = 0) -> dict[str, Any]:
    """Iteration 3's model retrained from iteration 2's weights on the same data (initial and
    iterations 1-2; lr 1e-3, batch 64, input noise 0.1, no mirror) through k-step open-loop
    rollouts of the recorded actions (k = 1: the one-step loss), as many gradient steps for
    every k; written into ``out``, a copy of the run, for ``trials`` and ``horizon``. ``seed``
    draws the batches and the input noise."""
    import shutil
    import time

    import torch

    from dlocli.models.base import apply_delta, target_delta
    from dlocli.models.checkpoints import load_model, save_checkpoint

    torch.manual_seed(seed)
    torch.set_num_threads(1)
    data = _datasets(run)
    seen = data[0].concat(data[1], data[2])
    rows_of, _ = seen.transition_index(None, False)
    t = {key: torch.as_tensor(v, dtype=torch.float32) for key, v in seen.transitions().items()}
    n = len(rows_of)
    last = np.minimum(np.arange(n) + k - 1, n - 1)
    starts = np.flatnonzero((np.arange(n) + k - 1 < n) & (rows_of[last] == rows_of + k - 1))
    model = load_model(run / "checkpoints" / "iter_02.pt").train().requires_grad_(True)
    optimizer = torch.optim.Adam(model.parameters(), lr=1e-3)
    gen = torch.Generator().manual_seed(seed)
    began = time.perf_counter()
    for _ in range(epochs * (n // 64)):
        idx = torch.as_tensor(starts)[torch.randint(len(starts), (64,), generator=gen)]
        state, previous = t["state"][idx], t["previous_state"][idx]
        state = state + 0.1 * model.delta_std * torch.randn(state.shape, generator=gen)
        loss = torch.zeros(())
        for j in range(k):
            target = (target_delta(state, t["next_state"][idx + j]) - model.delta_mean) / (
                model.delta_std
            )
            change = model.predict_delta(*model.normalize(state, t["action"][idx + j], previous))
            loss = loss + torch.mean((change - target) ** 2) / k
            previous, state = state, apply_delta(state, change * model.delta_std + model.delta_mean)
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
    seconds = time.perf_counter() - began
    shutil.rmtree(out, ignore_errors=True)
    shutil.copytree(run, out, ignore=shutil.ignore_patterns("tensorboard", "plots"))
    save_checkpoint(model.eval(), out / "checkpoints" / "iter_03.pt")
    return {"run": str(run), "k": k, "out": str(out), "train_seconds": round(seconds),
            "its_trials": open_loop_error(model, data[3], (1, 5, 10, 20))}  # fmt: skip


def ensemble(out: Path, copies: list[Path]) -> dict[str, Any]:
    """The iteration-3 models of ``copies`` (``retrain`` outputs of one run) as one ensemble
    (their predicted changes averaged every step, :mod:`dlocli.models.ensemble`; the first
    copy's normalisation), written into ``out``, a copy of the first, for ``trials`` and
    ``sweep``."""
    import shutil

    from dlocli.models.base import DynamicsModel
    from dlocli.models.checkpoints import load_model, save_checkpoint

    members = [load_model(c / "checkpoints" / "iter_03.pt") for c in copies]
    spec = members[0].spec.model_copy(update={"members": len(members)})
    model = DynamicsModel(spec, members[0].n_segments)
    buffers = {k: v for k, v in members[0].state_dict().items() if not k.startswith("network.")}
    model.load_state_dict(buffers, strict=False)
    for slot, member in zip(model.network.members, members, strict=True):
        slot.load_state_dict(member.network.state_dict())
    shutil.rmtree(out, ignore_errors=True)
    shutil.copytree(copies[0], out)
    save_checkpoint(model.eval(), out / "checkpoints" / "iter_03.pt")
    return {"out": str(out), "members": [str(c) for c in copies]}


def model_report(run: Path) -> dict[str, Any]:
    from dlocli.models.checkpoints import load_model
    from dlocli.models.splits import split_episodes

    spec = json.loads((run / "spec.json").read_text())
    data = _datasets(run)
    report: dict[str, Any] = {"run": str(run), "backend": spec["backend"]["name"]}
    report["motion"] = {k: motion(d, spec["task"]["control_dt"]) for k, d in data.items()}
    losses = {}
    for k in sorted(d for d in data if d > 0):
        model = load_model(run / "checkpoints" / f"iter_{k:02d}.pt").eval()
        seen = data[0].concat(*[data[j] for j in range(1, k)])
        _, held_out = split_episodes(seen.n_episodes, spec["fit"]["val_fraction"])
        losses[k] = {
            "validation_episodes": held_out.tolist(),
            "validation": one_step_loss(model, seen, held_out),
            "its_trials": one_step_loss(model, data[k]),
        }
    report["one_step_loss"] = losses
    return report


def trials_report(
    run: Path, k: int, n: int, changes: dict[str, Any], controller: str | None = None,
    rest_from_data: bool = False,
) -> dict[str, Any]:  # fmt: skip
    """Iteration k's model driving n trials from iteration k's starts, ``changes`` applied to
    the run's spec (nested dicts); ``controller``: another registered controller instead of
    the run's planner (e.g. the ``held-end`` reference), with the same action noise;
    ``rest_from_data``: the model given the rest states of the run's data before iteration k,
    as a run writes them into its checkpoints now (for runs made before they did)."""
    import torch

    from dlocli.controllers.base import make_controller
    from dlocli.env.metrics import shape_error_mm
    from dlocli.env.rollout import NoisyPolicy, rollout, stream_seed
    from dlocli.env.shape_env import make_env_from_spec
    from dlocli.models.checkpoints import load_planning_model
    from dlocli.runs.online.spec import NOISE, TRIAL, OnlineSpec
    from dlocli.runs.online.trials import env_spec

    fields = json.loads((run / "spec.json").read_text())
    for path, value in changes.items():
        *parents, name = path.split(".")
        node = fields
        for parent in parents:
            node = node[parent]
        node[name] = value
    spec = OnlineSpec.model_validate(fields)
    checkpoint = (run / "checkpoints" / f"iter_{k:02d}.pt").read_bytes()
    torch.set_num_threads(1)  # as the run's trials
    env = make_env_from_spec(env_spec(spec))
    rest = run_rest_states(run, spec, k) if rest_from_data else None
    rows, start = [], time.perf_counter()
    try:
        for j in range(1, n + 1):
            seed = stream_seed(spec.seed, TRIAL, k, j)
            model = load_planning_model(checkpoint, "cpu")
            if rest is not None:
                model.rest_states = rest
            name = controller or spec.planner
            planner = make_controller(name, env, options=spec.mpc, seed=seed, model=model)
            noise = np.random.default_rng(stream_seed(spec.seed, NOISE, k, j))
            policy = NoisyPolicy(planner, noise, spec.noise_probability, spec.noise_std)
            episode = rollout(env, policy, seed)
            error = shape_error_mm(episode.positions, episode.goal)
            off_mm, off_deg, roll_deg, tilt_deg = gripper_offset(env)
            for _ in range(HOLD):
                env.step(np.zeros(env.action_space.shape))
            held = float(shape_error_mm(env.state_parts()["positions"], episode.goal))
            rows.append({
                "initial_mm": float(error[0]), "final_mm": float(error[-1]),
                "last40_mean_mm": float(error[-LAST:].mean()),
                "last40_least_mm": float(error[-LAST:].min()), "held_mm": held,
                "score": 1.0 - float(error[-1]) / float(error[0]),
                "gripper_off_mm": off_mm, "gripper_off_deg": off_deg,
                "gripper_roll_deg": roll_deg, "gripper_tilt_deg": tilt_deg,
            })  # fmt: skip
    finally:
        env.close()
    return {"run": str(run), "iteration": k, "trials": n, "changes": changes,
            "mean": per_key(np.mean, rows),
            "seconds": round(time.perf_counter() - start, 1), "per_trial": rows}  # fmt: skip


def run_rest_states(run: Path, spec: Any, k: int) -> dict[str, np.ndarray]:
    """The rest states (:mod:`dlocli.controllers.rest_roll`) of run's data before iteration k:
    its initial episodes and iterations 1 to k - 1's trials."""
    from dlocli.controllers.rest_roll import rest_states
    from dlocli.data import load_dataset
    from dlocli.env.tasks import make_task

    files = [run / "data" / f"iter_{it:02d}" / f"trial_{j:03d}.h5"
             for it in range(1, k) for j in range(1, spec.trials + 1)]  # fmt: skip
    data = load_dataset(run / "data" / "initial.h5").concat(*map(load_dataset, files))
    found = rest_states(data, make_task(spec.task.name).moving, spec.task.control_dt)
    return {name: array.astype(np.float64) for name, array in found.items()}


#: the planner options every ``sweep`` row sets, at the paper's (the runs' own specs may differ)
SWEEP_BASE = {
    "mpc.servo_cost": 0.0,
    "mpc.motion_cost": 0.0,
    "mpc.damping": 0.01,
    "mpc.settle_steps": 0,
    "mpc.jacobian": "full",
    "mpc.curvature_every": 25,
    "mpc.disturbance": "none",
    "mpc.servo_above_mm": 0.0,
    "mpc.rest_roll": False,
}


def sweep_report(
    runs: list[Path], k: int, n: int, changes: dict[str, Any], controller: str | None = None
) -> dict[str, Any]:
    """``changes`` (over SWEEP_BASE) on iteration k's model of each run, n trials each: the
    share of the initial error closed over all trials (1 - sum final / sum initial) and per run
    (``controller`` as :func:`trials_report` takes it)."""
    settings = {**SWEEP_BASE, **changes}
    reports = [trials_report(run, k, n, settings, controller) for run in runs]
    initial = sum(r["mean"]["initial_mm"] for r in reports)
    final = sum(r["mean"]["final_mm"] for r in reports)
    return {"changes": changes, "controller": controller or "the run's planner",
            "runs": [str(r) for r in runs], "iteration": k, "trials": n,
            "closed": round(1.0 - final / initial, 3),
            "per_run": [round(1.0 - r["mean"]["final_mm"] / r["mean"]["initial_mm"], 3)
                        for r in reports],
            "final_mm": round(final / len(reports), 1)}  # fmt: skip


#: the planners ``latency`` times: the paper's cost, and the options that damp the swing
LATENCY_SETTINGS = {
    "paper": SWEEP_BASE,
    "motion_cost 32": {**SWEEP_BASE, "mpc.motion_cost": 32.0},
    "motion_cost 32, damping 1": {**SWEEP_BASE, "mpc.motion_cost": 32.0, "mpc.damping": 1.0},
    "settle_steps 2": {**SWEEP_BASE, "mpc.settle_steps": 2},
    "motion_cost 32, damping 1, curvature_every 5": {
        **SWEEP_BASE,
        "mpc.motion_cost": 32.0,
        "mpc.damping": 1.0,
        "mpc.curvature_every": 5,
    },
    "motion_cost 32, damping 1, curvature_every 5, background": {
        **SWEEP_BASE,
        "mpc.motion_cost": 32.0,
        "mpc.damping": 1.0,
        "mpc.curvature_every": 5,
        "mpc.refresh": "background",
    },
    **{
        f"motion_cost 32, damping 1, shifted Jacobian every {k}{' + drift' * drift}": {
            **SWEEP_BASE,
            "mpc.motion_cost": 32.0,
            "mpc.damping": 1.0,
            "mpc.jacobian": "shifted",
            "mpc.curvature_every": k,
            **({"mpc.disturbance": "drift"} if drift else {}),
        }
        for k, drift in ((5, False), (3, False), (5, True), (4, True), (3, True))
    },
    "motion_cost 32, damping 1, servo_cost 0.001": {
        **SWEEP_BASE,
        "mpc.motion_cost": 32.0,
        "mpc.damping": 1.0,
        "mpc.servo_cost": 0.001,
    },
    "servo_cost 0.001": {**SWEEP_BASE, "mpc.servo_cost": 0.001},
    "motion_cost 32, damping 1, servo_cost 0.001, rest_roll": {
        **SWEEP_BASE,
        "mpc.motion_cost": 32.0,
        "mpc.damping": 1.0,
        "mpc.servo_cost": 0.001,
        "mpc.rest_roll": True,
    },
    "motion_cost 32, damping 1, servo_cost 0.001, servo_above_mm 0.2": {
        **SWEEP_BASE,
        "mpc.motion_cost": 32.0,
        "mpc.damping": 1.0,
        "mpc.servo_cost": 0.001,
        "mpc.servo_above_mm": 0.2,
    },
    **{
        f"motion_cost 32, damping 1, servo_cost 0.001, roll_search {s}": {
            **SWEEP_BASE,
            "mpc.motion_cost": 32.0,
            "mpc.damping": 1.0,
            "mpc.servo_cost": 0.001,
            "mpc.roll_search": s,
        }
        for s in (10, 20)
    },
    "motion_cost 32, damping 1, drift": {
        **SWEEP_BASE,
        "mpc.motion_cost": 32.0,
        "mpc.damping": 1.0,
        "mpc.disturbance": "drift",
    },
}


def latency_report(
    run: Path, k: int, steps: int, rounds: int, only: list[str] | None = None,
    rest_from_data: bool = False,
) -> dict[str, Any]:  # fmt: skip
    """The MPC's time per control step (ms: median, mean) of each LATENCY_SETTINGS planner
    through iteration k's model, one thread, on the same starts, the planners taking turns
    episode by episode (so a busy host slows each alike); ``rounds`` episodes of ``steps``;
    ``rest_from_data`` as in :func:`trials_report`."""
    import torch

    from dlocli.controllers.base import make_controller
    from dlocli.env.shape_env import make_env_from_spec
    from dlocli.models.checkpoints import load_planning_model
    from dlocli.runs.online.spec import OnlineSpec
    from dlocli.runs.online.trials import env_spec

    spec = OnlineSpec.model_validate(json.loads((run / "spec.json").read_text()))
    checkpoint = (run / "checkpoints" / f"iter_{k:02d}.pt").read_bytes()
    torch.set_num_threads(1)
    env = make_env_from_spec(env_spec(spec))
    chosen = {name: LATENCY_SETTINGS[name] for name in ["paper", *(only or [])]}
    chosen = chosen if only else LATENCY_SETTINGS
    rest = run_rest_states(run, spec, k) if rest_from_data else None
    times: dict[str, list[float]] = {name: [] for name in chosen}
    try:
        for episode in range(-1, rounds):  # episode -1 warms torch and the simulator up
            for name, settings in chosen.items():
                options = spec.mpc.model_copy(
                    update={path.split(".", 1)[1]: value for path, value in settings.items()}
                )
                model = load_planning_model(checkpoint, "cpu")
                if rest is not None:
                    model.rest_states = rest
                planner = make_controller("mpc", env, options=options, seed=episode, model=model)
                obs, _ = env.reset(seed=max(episode, 0))
                planner.reset(env.goal)
                for _ in range(steps if episode >= 0 else 5):
                    action = planner.act(obs)
                    if episode >= 0:
                        times[name].append(planner.last_latency_ms)
                    obs, *_ = env.step(action)
    finally:
        env.close()
    report = {
        name: {"median_ms": round(float(np.median(t)), 2), "mean_ms": round(float(np.mean(t)), 2)}
        for name, t in times.items()
    }
    for entry in report.values():
        entry["mean_over_paper"] = round(entry["mean_ms"] / report["paper"]["mean_ms"], 2)
    return {"run": str(run), "iteration": k, "steps": steps, "rounds": rounds, "ms": report}


def gripper_offset(env: Any) -> tuple[float, float, float, float]:
    """How far the moving grippers stand from the goal's own gripper poses at the episode's end:
    the largest position offset (mm) and turn (degrees), and the largest turn's parts about
    the gripper's own x axis (the rod's axis where it holds the rod: roll, a turn the shape
    barely shows) and about the axes across it (tilt), degrees."""
    from dlocli.backends.rotations import quat_rotate
    from dlocli.env.shapes import rotation_between

    moving = env.backend.moving
    poses, goal = env.backend.gripper_poses()[moving], env.goal_gripper_poses[moving]
    offset = np.linalg.norm(poses[:, :3] - goal[:, :3], axis=1).max() * 1000.0
    turns = rotation_between(poses[:, 3:], goal[:, 3:])  # (G, 3) world frame
    axes = quat_rotate(poses[:, 3:], np.array([1.0, 0.0, 0.0]))
    roll = np.abs(np.sum(turns * axes, axis=1))
    tilt = np.linalg.norm(turns - (turns * axes).sum(1, keepdims=True) * axes, axis=1)
    largest = int(np.argmax(np.linalg.norm(turns, axis=1)))
    turn = np.linalg.norm(turns[largest])
    return tuple(float(v) for v in (offset, *np.degrees([turn, roll[largest], tilt[largest]])))


def pose_report(
    run: Path, k: int, n: int, offset_mm: float = 0.0, turn_deg: float = 0.0, roll: bool = False
) -> dict[str, Any]:
    """No model: from iteration k's first n starts, the grippers driven straight to the goal's
    own gripper poses at the task's velocity limits and held there to the episode's end (and
    HOLD steps more): how close the rod comes when the grippers are exactly right; or, with
    ``offset_mm`` / ``turn_deg``, when the moving grippers stand that far off (a random
    direction and axis per trial): how much a gripper placed wrong costs the shape."""
    from dlocli.env.metrics import shape_error_mm
    from dlocli.env.rollout import stream_seed
    from dlocli.env.shape_env import make_env_from_spec
    from dlocli.env.shapes import gripper_twists_towards, max_twist
    from dlocli.resume import load_saved_spec
    from dlocli.runs.online.spec import TRIAL, OnlineSpec
    from dlocli.runs.online.trials import env_spec

    spec = load_saved_spec(OnlineSpec, run / "spec.json")
    env = make_env_from_spec(env_spec(spec))
    rows = []
    try:
        for j in range(1, n + 1):
            env.reset(seed=stream_seed(spec.seed, TRIAL, k, j))
            goal, moving, task = np.asarray(env.goal), env.backend.moving, env.task_spec
            rng = np.random.default_rng(j)
            targets = misplaced(env.goal_gripper_poses, moving, offset_mm, turn_deg, rng, roll)
            errors = [float(shape_error_mm(env.state_parts()["positions"], goal))]
            for _ in range(task.episode_steps + HOLD):
                twists = gripper_twists_towards(env.backend.gripper_poses(), targets, task, moving)
                env.step(env.task.from_grippers(twists / max_twist(task)))
                errors.append(float(shape_error_mm(env.state_parts()["positions"], goal)))
            final = errors[task.episode_steps]
            rows.append({
                "initial_mm": errors[0], "final_mm": final, "held_mm": errors[-1],
                "score": 1.0 - final / errors[0],
            })  # fmt: skip
    finally:
        env.close()
    return {"run": str(run), "iteration": k, "trials": n, "offset_mm": offset_mm,
            "turn_deg": turn_deg, "roll": roll, "mean": per_key(np.mean, rows),
            "median": per_key(np.median, rows), "per_trial": rows}  # fmt: skip


def reference_report(run: Path, k: int, n: int, name: str) -> dict[str, Any]:
    """The registered reference ``name`` (no model, no checkpoint needed) from iteration k's
    first n trial starts, as the run's own references ran: one episode each."""
    from dlocli.env.rollout import stream_seed
    from dlocli.env.shape_env import make_env_from_spec
    from dlocli.resume import load_saved_spec
    from dlocli.runs.online.spec import TRIAL, OnlineSpec
    from dlocli.runs.online.trials import env_spec
    from dlocli.runs.references import reference_episode_scores

    spec = load_saved_spec(OnlineSpec, run / "spec.json")
    env = make_env_from_spec(env_spec(spec))
    try:
        rows = [reference_episode_scores(env, name, stream_seed(spec.seed, TRIAL, k, j), j)
                for j in range(1, n + 1)]  # fmt: skip
    finally:
        env.close()
    keys = ("initial_error_mm", "final_error_mm", "score")
    rows = [{key: row[key] for key in keys} for row in rows]
    return {"run": str(run), "iteration": k, "trials": n, "reference": name,
            "mean": per_key(np.mean, rows), "median": per_key(np.median, rows),
            "closed": round(1.0 - sum(r["final_error_mm"] for r in rows)
                            / sum(r["initial_error_mm"] for r in rows), 3)}  # fmt: skip


def per_key(statistic: Any, rows: list[dict[str, float]]) -> dict[str, float]:
    """``statistic`` (np.mean, np.median) of each field over the trials' rows, rounded."""
    return {key: round(float(statistic([r[key] for r in rows])), 3) for key in rows[0]}


def misplaced(
    poses: np.ndarray,
    moving: np.ndarray,
    offset_mm: float,
    turn_deg: float,
    rng: Any,
    roll: bool = False,
) -> np.ndarray:
    """``poses`` with each moving gripper shifted by ``offset_mm`` and turned by ``turn_deg``
    (world frame), each in a random direction; with ``roll`` the turn is about the gripper's
    own x axis."""
    from dlocli.backends.rotations import (
        quat_from_rotvec,
        quat_multiply,
        quat_normalize,
        quat_rotate,
    )

    out = poses.copy()
    for gripper in np.flatnonzero(moving):
        direction, axis = (v / np.linalg.norm(v) for v in rng.normal(size=(2, 3)))
        out[gripper, :3] += direction * offset_mm / 1000.0
        if roll:  # about the gripper's own x axis, the rod's where it is held, either way
            axis = quat_rotate(out[gripper, 3:], np.array([1.0, 0.0, 0.0])) * rng.choice([-1, 1])
        turn = quat_from_rotvec(axis * np.radians(turn_deg))
        out[gripper, 3:] = quat_normalize(quat_multiply(turn, out[gripper, 3:]))
    return out


def swing_report(backend: str, rod: dict[str, Any]) -> dict[str, Any]:
    from dlocli.specs import BackendSpec

    script = HERE.parent / "examples" / "calibration" / "swing_decay.py"
    swing = runpy.run_path(str(script))["swing"]
    found = swing(BackendSpec.model_validate({"name": backend, "rod": rod}))
    return {"backend": backend, "rod": rod, **{k: round(v, 4) for k, v in found.items()}}


def spec_settings(items: list[str]) -> dict[str, Any]:
    """``--set FIELD=JSON`` items as {dotted field: value}."""
    return {path: json.loads(value) for path, value in (i.split("=", 1) for i in items)}


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = parser.add_subparsers(dest="what", required=True)
    sub.add_parser("model").add_argument("run", type=Path)
    trials = sub.add_parser("trials")
    trials.add_argument("run", type=Path)
    trials.add_argument("--iteration", type=int, default=3)
    trials.add_argument("--trials", type=int, default=10)
    trials.add_argument("--horizon", type=int)
    trials.add_argument("--noise-probability", type=float)
    trials.add_argument("--max-step", type=float)
    trials.add_argument("--settle-steps", type=int)
    trials.add_argument("--set", action="append", default=[], metavar="FIELD=JSON",
                        help="any other spec field, e.g. mpc.motion_cost=4")  # fmt: skip
    trials.add_argument("--rest-from-data", action="store_true",
                        help="give the model the rest states of the run's data before the "
                        "iteration (runs made before checkpoints carried them)")  # fmt: skip
    many = sub.add_parser("sweep")
    many.add_argument("runs", type=Path, nargs="+")
    many.add_argument("--iteration", type=int, default=3)
    many.add_argument("--trials", type=int, default=8)
    many.add_argument("--set", action="append", default=[], metavar="FIELD=JSON")
    many.add_argument("--controller", help="a registered controller instead of the planner")
    timing = sub.add_parser("latency")
    timing.add_argument("run", type=Path)
    timing.add_argument("--iteration", type=int, default=3)
    timing.add_argument("--steps", type=int, default=100)
    timing.add_argument("--rounds", type=int, default=5)
    timing.add_argument(
        "--only", type=lambda text: text.split(";"), default=None,
        help="the planners to time beside the paper's, by name, separated by ';'",
    )  # fmt: skip
    timing.add_argument("--rest-from-data", action="store_true")
    pose = sub.add_parser("pose")
    pose.add_argument("run", type=Path)
    pose.add_argument("--iteration", type=int, default=3)
    pose.add_argument("--trials", type=int, default=10)
    pose.add_argument("--offset-mm", type=float, default=0.0)
    pose.add_argument("--turn-deg", type=float, default=0.0)
    pose.add_argument("--roll", action="store_true", help="turn about the gripper's x axis")
    ref = sub.add_parser("reference")
    ref.add_argument("run", type=Path)
    ref.add_argument("--iteration", type=int, default=3)
    ref.add_argument("--trials", type=int, default=10)
    ref.add_argument("--name", default="held-end", help="a registered reference controller")
    horizon = sub.add_parser("horizon")
    horizon.add_argument("run", type=Path)
    horizon.add_argument("--iteration", type=int, default=3)
    horizon.add_argument("--steps", default="1,5,10,20")
    horizon.add_argument("--from-step", type=int, default=1)
    again = sub.add_parser("retrain")
    again.add_argument("run", type=Path)
    again.add_argument("k", type=int)
    again.add_argument("out", type=Path)
    again.add_argument("--seed", type=int, default=0)
    together = sub.add_parser("ensemble")
    together.add_argument("out", type=Path)
    together.add_argument("copies", type=Path, nargs="+")
    swing = sub.add_parser("swing")
    swing.add_argument("backend")
    swing.add_argument("--rod", type=json.loads, default={}, help="rod fields, JSON")
    args = parser.parse_args(argv)
    if args.what == "model":
        report = model_report(args.run)
    elif args.what == "trials":
        changes = {
            path: value
            for path, value in (
                ("mpc.horizon", args.horizon),
                ("noise_probability", args.noise_probability),
                ("mpc.max_step", args.max_step),
                ("mpc.settle_steps", args.settle_steps),
            )
            if value is not None
        }
        changes.update(spec_settings(args.set))
        report = trials_report(args.run, args.iteration, args.trials, changes,
                               rest_from_data=args.rest_from_data)  # fmt: skip
    elif args.what == "sweep":
        report = sweep_report(
            args.runs, args.iteration, args.trials, spec_settings(args.set), args.controller
        )
    elif args.what == "latency":
        report = latency_report(args.run, args.iteration, args.steps, args.rounds, args.only,
                                args.rest_from_data)  # fmt: skip
    elif args.what == "reference":
        report = reference_report(args.run, args.iteration, args.trials, args.name)
    elif args.what == "pose":
        report = pose_report(
            args.run, args.iteration, args.trials, args.offset_mm, args.turn_deg, args.roll
        )
    elif args.what == "horizon":
        steps = tuple(int(h) for h in args.steps.split(","))
        report = horizon_report(args.run, args.iteration, steps, args.from_step)
    elif args.what == "retrain":
        report = retrain(args.run, args.k, args.out, seed=args.seed)
    elif args.what == "ensemble":
        report = ensemble(args.out, args.copies)
    else:
        report = swing_report(args.backend, args.rod)
    json.dump(report, sys.stdout)
    print()


if __name__ == "__main__":
    main()
