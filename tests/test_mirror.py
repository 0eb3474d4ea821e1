"""The rod's mirrored twin (dlocli/models/mirror.py): proven against both simulators, an
involution on real data, and the training option ``FitSpec.mirror``."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import pytest
import torch

from dlocli.backends import runnable_backends
from dlocli.data import load_dataset
from dlocli.env.metrics import reward as shape_reward
from dlocli.env.shape_env import make_env
from dlocli.models.base import ModelSpec, build_model
from dlocli.models.evaluation import evaluate_model
from dlocli.models.fit import fit as fit_model
from dlocli.models.fitting import BatchDone, Validated
from dlocli.models.mirror import (
    mirror,
    mirror_grippers,
    mirror_states,
    mirror_task_action,
    mirror_transitions,
)
from dlocli.models.rod_training import transition_tensors
from dlocli.models.spec import FitSpec
from dlocli.models.splits import split_episodes

MOTION_STEPS = 60  # control steps of piecewise-constant random commands (1.2 s)
SETTLE_STEPS = 60  # then the grippers stand still and the rod settles (1.2 s)
HOLD_STEPS = 10  # control steps each random command is held


@dataclass(frozen=True)
class Tolerance:
    """Largest difference between the recorded twin and the mirrored recording: the worst
    segment's position (mm) and orientation (degrees), during the motion and once settled."""

    motion_mm: float
    motion_deg: float
    settled_mm: float
    settled_deg: float


# Measured with full-speed random commands (command seeds 0, 1, 2; the rod moves ~55 mm):
# MuJoCo: motion <= 1.31 mm / 0.33 deg, settled <= 0.65 mm / 0.17 deg. Its two ends are
# held by equal welded pads in different kinematic-tree coordinates: the twin agrees up to
# discretisation. PyBullet: motion <= 1.55 mm / 0.36 deg, settled <= 0.70 mm / 0.17 deg; its
# ends are equal fixed constraints, the left one on the multibody's base (when the base was
# driven by resetting its twist instead, the twin differed by up to 44 mm while moving).
# The flex rod (MuJoCo 4): motion 0.095 mm / 0.020 deg, settled 0.005 mm / 0.001 deg (command
# seed 0): both ends are pads of one kind, the rod one flex between them.
# Tolerances: about twice the largest measured (the flex rod's: three to ten times).
TOLERANCES = {
    "mujoco": Tolerance(motion_mm=3.0, motion_deg=1.0, settled_mm=1.5, settled_deg=0.5),
    "mujoco-flex": Tolerance(motion_mm=0.3, motion_deg=0.1, settled_mm=0.05, settled_deg=0.01),
    "pybullet": Tolerance(motion_mm=3.0, motion_deg=1.0, settled_mm=1.5, settled_deg=0.5),
}
REST_TOLERANCE_MM = 0.01  # the rest state is its own twin (measured: 1.3 um, 3.8 um)


def rotation_deg(q1: np.ndarray, q2: np.ndarray) -> np.ndarray:
    """Angle (degrees) of the rotation between unit quaternions (..., 4)."""
    dot = np.abs((q1 * q2).sum(-1)).clip(0.0, 1.0)
    return np.degrees(2.0 * np.arccos(dot))


def random_commands(seed: int) -> np.ndarray:
    """(MOTION_STEPS + SETTLE_STEPS, 6) single-gripper actions: random, then zero."""
    rng = np.random.default_rng(seed)
    held = rng.uniform(-1.0, 1.0, (math.ceil(MOTION_STEPS / HOLD_STEPS), 6))
    motion = np.repeat(held, HOLD_STEPS, axis=0)[:MOTION_STEPS]
    return np.concatenate([motion, np.zeros((SETTLE_STEPS, 6))])


def drive_both_ways(backend: str, actions: np.ndarray) -> dict[str, np.ndarray]:
    """From the rest state: the right gripper driven by ``actions`` (task ``single``), and
    the left one by their twins (task ``bimanual``, right gripper still); the segment states
    (T+1, N, 7) and gripper poses (T+1, 2, 7) of both."""
    options = {
        "shapes": "near-rest",  # no random motion, no settling: the start is the rest state
        "reset_motion_steps": 0,
        "reset_settle_steps": 0,
        "episode_steps": len(actions),
        "render_mode": None,
    }
    envs = [make_env(backend, task, **options) for task in ("single", "bimanual")]
    twins = mirror_task_action(np.concatenate([np.zeros_like(actions), actions], axis=1))
    record: dict[str, np.ndarray] = {}
    try:
        for env, name, commands in zip(envs, ("right", "left"), (actions, twins), strict=True):
            env.reset(seed=0)
            states, grippers = [env.segment_state()], [env.backend.gripper_poses()]
            for action in commands:
                _, _, _, _, info = env.step(action)
                assert not info["diverged"], f"{backend}: the {name}-driven rod diverged"
                states.append(env.segment_state())
                grippers.append(env.backend.gripper_poses())
            record[f"{name}_states"], record[f"{name}_grippers"] = map(np.array, (states, grippers))
    finally:
        for env in envs:
            env.close()
    return record


@pytest.mark.parametrize("backend", runnable_backends())
def test_the_twin_is_what_the_simulator_does(backend):
    """The rod driven by the left gripper with the twin commands is the mirrored recording
    of the rod driven by the right gripper."""
    record = drive_both_ways(backend, random_commands(seed=0))
    right, left = record["right_states"], record["left_states"]
    twin = mirror_states(right)
    position_mm = 1000.0 * np.linalg.norm(twin[..., :3] - left[..., :3], axis=-1).max(-1)
    angle_deg = rotation_deg(twin[..., 3:], left[..., 3:]).max(-1)
    moved_mm = 1000.0 * np.linalg.norm(right[..., :3] - right[0, :, :3], axis=-1).max()
    motion = slice(0, MOTION_STEPS + 1)
    measured = (
        f"{backend}: rest {position_mm[0]:.4f} mm; motion max {position_mm[motion].max():.3f} mm "
        f"/ {angle_deg[motion].max():.3f} deg; settled {position_mm[-1]:.3f} mm / "
        f"{angle_deg[-1]:.3f} deg; the rod moved up to {moved_mm:.1f} mm"
    )
    print(measured)
    tol = TOLERANCES[backend]
    assert moved_mm > 30.0, measured  # a test of a rod that hardly moves proves nothing
    assert position_mm[0] < REST_TOLERANCE_MM, measured
    # the grippers are pure kinematics (integrate_gripper_poses): the twins agree to rounding
    np.testing.assert_allclose(
        mirror_grippers(record["right_grippers"]), record["left_grippers"], atol=1e-9
    )
    assert position_mm[motion].max() < tol.motion_mm, measured
    assert angle_deg[motion].max() < tol.motion_deg, measured
    assert position_mm[-1] < tol.settled_mm, measured
    assert angle_deg[-1] < tol.settled_deg, measured


def test_mirror_is_an_involution_and_keeps_rewards_on_real_data(small_dataset_dir):
    data = load_dataset(small_dataset_dir)
    twin = mirror(data)
    back = mirror(twin)
    for name in ("positions", "quaternions", "grippers", "actions", "goals", "rewards"):
        np.testing.assert_array_equal(getattr(back, name), getattr(data, name), err_msg=name)
        assert getattr(twin, name).dtype == getattr(data, name).dtype, name
    # single-gripper data: the right end acts; in the twin the left one does
    assert np.abs(data.actions[:, 0]).max() == 0 and np.abs(data.actions[:, 1]).max() > 0
    assert np.abs(twin.actions[:, 1]).max() == 0 and np.abs(twin.actions[:, 0]).max() > 0
    # the twin's rewards are its own (the shape error is kept by the map)
    e = 0
    episode = twin.episode(e)
    recomputed = [shape_reward(p, episode.goal) for p in episode.positions[1:]]
    np.testing.assert_allclose(recomputed, episode.rewards, rtol=1e-5, atol=1e-6)
    # an episode's twin is the dataset twin's episode
    np.testing.assert_array_equal(mirror(data.episode(e)).quaternions, episode.quaternions)
    # the transitions' twins are the twin's transitions
    mapped = mirror_transitions(data.transitions(skip_first=True))
    for key, value in twin.transitions(skip_first=True).items():
        np.testing.assert_array_equal(mapped[key], value, err_msg=key)


def test_mirror_is_on_by_default_and_runs_saved_before_it_resume_without_it(tmp_path):
    """(Saved runs keep their fingerprints: tests/test_bench.py::
    test_committed_paper_bench_jobs_resume_without_rerunning.)"""
    import json

    from dlocli.bench.spec import BenchSpec, fingerprint
    from dlocli.resume import saved_spec

    spec = BenchSpec()
    assert spec.fit.mirror is True
    plain = spec.model_copy(update={"fit": spec.fit.model_copy(update={"mirror": False})})
    assert fingerprint(plain) != fingerprint(spec), "a mirrored fit is another job"
    old = spec.model_dump(mode="json")
    del old["fit"]["mirror"]  # a bench saved before the field existed
    old_train = {**spec.fit.model_dump(mode="json"), "data": "d"}
    del old_train["mirror"]  # a train run: the fit fields at the top level
    for name, data in (("bench.json", old), ("train.json", old_train)):
        (tmp_path / name).write_text(json.dumps(data))
    assert BenchSpec.model_validate(saved_spec(tmp_path / "bench.json")).fit.mirror is False
    assert saved_spec(tmp_path / "train.json")["mirror"] is False


def test_data_with_a_free_right_end_are_not_mirrored(small_dataset_dir):
    """A cantilever's twin would have a free left end: no backend simulates that rod."""
    from dlocli.models.rod_training import mirror_applies

    data = load_dataset(small_dataset_dir)
    assert mirror_applies(data)
    spec = {**data.attrs["spec"], "backend": {**data.attrs["spec"]["backend"], "held_ends": "left"}}
    data.attrs = {**data.attrs, "spec": spec}
    assert not mirror_applies(data)


FIT = {"lr": 3e-3, "batch_size": 16, "val_fraction": 0.2, "device": "cpu", "epochs": 4}


@pytest.fixture
def one_torch_thread():
    """A tiny model trains fastest on one thread: a second one only adds synchronisation,
    which costs ten times the work on a loaded machine."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


def test_training_on_twins_doubles_the_data_and_learns_the_other_end(
    small_dataset_dir, one_torch_thread
):
    """The twins double the training transitions (validation stays the recorded data), and a
    model trained with them predicts the left end acting (mirrored held-out episodes) better.

    Measured (model seeds 0-2): one-step error 0.69-0.88 mm with the twins, 1.08-1.40 mm
    without (persistence: 0.98 mm)."""
    data = load_dataset(small_dataset_dir)
    train_eps, val_eps = split_episodes(data.n_episodes, FIT["val_fraction"])
    cpu = torch.device("cpu")
    plain = len(transition_tensors(data, train_eps, cpu)["state"])
    assert len(transition_tensors(data, train_eps, cpu, mirror=True)["state"]) == 2 * plain
    errors, batches = {}, {}
    for flag in (False, True):
        torch.manual_seed(0)
        model = build_model(ModelSpec(name="in-bilstm", hidden=16), data.n_segments)
        seen: list[int] = []

        def progress(event: BatchDone | Validated, seen: list[int] = seen) -> None:
            if isinstance(event, BatchDone):
                seen.append(event.total)

        result = fit_model(model, data, FitSpec(**FIT, mirror=flag), progress=progress)
        np.testing.assert_array_equal(result.val_episodes, val_eps)
        batches[flag] = seen[0]
        errors[flag] = evaluate_model(model, mirror(data), val_eps, horizons=())["one_step_mm"]
    assert batches[False] == math.ceil(plain / FIT["batch_size"])
    assert batches[True] == math.ceil(2 * plain / FIT["batch_size"])
    print(f"one-step error on mirrored held-out episodes: {errors} mm")
    assert errors[True] < 0.9 * errors[False], errors
