"""The markers observation (dlocli/env/observation.py): marker geometry on the real rods, the
tracker's faults measured against the true state, the env's full observation unchanged, and
the marker view a planner estimates the rod with."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from gymnasium.utils.env_checker import check_env

from dlocli.controllers.views import MarkerView, kalman_gain
from dlocli.data import Dataset, load_dataset
from dlocli.env.observation import Tracker, held_markers, marker_layout, markers_of_state
from dlocli.env.rollout import ActionSequence, random_actions, random_episode, rollout
from dlocli.env.shape_env import make_env
from dlocli.errors import BadInput
from dlocli.models.base import valid_model_spec
from dlocli.models.marker_model import build_marker_model
from dlocli.specs import ObservationSpec

from tiny import MUJOCO_ROD

QUICK = {"shapes": "near-rest", "episode_steps": 30, "reset_motion_steps": 10,
         "reset_settle_steps": 10}  # fmt: skip
MARKERS = {"kind": "markers", "markers": 8}


def env_of(backend: str, **observation):
    return make_env(backend, "single", seed=2, render_mode=None, **QUICK,
                    observation={**MARKERS, **observation})  # fmt: skip


@pytest.mark.parametrize("backend", [MUJOCO_ROD, "pybullet"])
def test_markers_env_passes_gymnasium_checker_and_keeps_the_true_state(backend):
    """Faults change what is reported, never the starts, goals or motion: the same seed and
    actions give the same true state as the full observation."""
    full = make_env(backend, "single", seed=2, render_mode=None, **QUICK)
    faulty = env_of(backend, noise_mm=5, latency_steps=2, dropout=0.2, occlusion_probability=0.3)
    try:
        check_env(faulty, skip_render_check=True)
        a, b = random_episode(full, 5, 6), random_episode(faulty, 5, 6)
        assert np.array_equal(a.positions, b.positions) and np.array_equal(a.goal, b.goal)
        assert a.markers is None and b.markers.shape == (31, 10, 3)
        assert np.isfinite(b.markers).all() and not b.visible.all()
        assert faulty.observation_space.shape == (10 * 3 + 10 + 14 + 10 * 3 + 10 * 3,)
    finally:
        full.close()
        faulty.close()


def test_full_observation_is_the_true_state():
    env = make_env(MUJOCO_ROD, "single", seed=1, render_mode=None, **QUICK)
    try:
        obs, _ = env.reset(seed=3)
        obs, *_ = env.step(np.full(6, 0.5))
        parts, state = env.split_observation(obs), env.state_parts()
        assert all(np.array_equal(parts[k], state[k]) for k in state)
    finally:
        env.close()


@pytest.mark.parametrize("backend", [MUJOCO_ROD, "pybullet"])
def test_held_markers_follow_the_gripper_points(backend):
    """At the grippers' points (the default end markers) the robot's kinematics place the
    held markers where the simulated rod has them."""
    env = env_of(backend)
    try:
        episode = random_episode(env, 1, 2)
        layout = env.marker_layout
        true = markers_of_state(layout, episode.positions.astype(float),
                                episode.quaternions.astype(float),
                                episode.grippers.astype(float))  # fmt: skip
        placed = held_markers(layout, episode.grippers.astype(float))
        gap = np.linalg.norm(true[:, layout.held] - placed[:, layout.held], axis=-1)
        assert gap.max() < 1e-3  # 1 mm: the end segment's clamp compliance
        assert layout.held.tolist() == [True] * 2 + [False] * 6 + [True] * 2
        assert layout.on_gripper.tolist() == [True] + [False] * 8 + [True]
    finally:
        env.close()


def test_tracker_faults_match_their_spec():
    rng = np.random.default_rng(0)
    frames = rng.normal(size=(400, 6, 3))
    spec = ObservationSpec(kind="markers", noise_mm=4, latency_steps=3)
    tracker = Tracker(spec, 6)
    tracker.reset(np.random.default_rng(1), frames[0])
    reports = np.array([tracker.report(f)[0] for f in frames[1:]])
    error = reports[3:] - frames[1:-3]  # the report of step t shows the frame of t - 3
    assert abs(error.std() / 4e-3 - 1) < 0.05 and abs(error.mean()) < 3e-4

    lossy = Tracker(ObservationSpec(kind="markers", dropout=0.25), 6)
    lossy.reset(np.random.default_rng(2), frames[0])
    seen = [lossy.report(f) for f in frames[1:]]
    lost = np.array([not visible.any() for _, visible in seen])
    assert 0.18 < lost.mean() < 0.32
    first = int(np.flatnonzero(lost)[0])
    assert np.array_equal(seen[first][0], seen[first - 1][0])  # the last seen, never NaN


def test_occlusion_hides_a_span_for_its_frames():
    spec = ObservationSpec(kind="markers", occlusion_probability=1.0, occlusion_markers=3,
                           occlusion_steps=4)  # fmt: skip
    tracker = Tracker(spec, 10)
    frame = np.zeros((10, 3))
    tracker.reset(np.random.default_rng(0), frame)
    hidden = [~tracker.report(frame)[1] for _ in range(8)]
    for mask in hidden:
        (where,) = np.nonzero(mask)
        assert len(where) == 3 and np.all(np.diff(where) == 1)
    assert all(np.array_equal(hidden[0], h) for h in hidden[:4])


def test_layout_needs_held_and_free_markers():
    spec = ObservationSpec(kind="markers", marker_arc_lengths=(0.3, 0.5, 0.7), gripper_markers=0)
    with pytest.raises(BadInput, match="held end segment"):
        marker_layout(spec, 1.0, 20, (True, True))
    assert marker_layout(spec.model_copy(update={"gripper_markers": 0.1}), 1.0, 20,
                         (True, True)).held.sum() == 2  # fmt: skip
    layout = marker_layout(ObservationSpec(kind="markers", gripper_markers=0), 1.0, 20,
                           (True, False))  # fmt: skip
    assert layout.held.sum() == 1  # a cantilever: only the left end is held


def test_arc_lengths_past_the_rods_ends_sit_on_the_grippers():
    """Two held markers at each end (DEFORM's layout): the outer ones on the grippers, placed
    as gripper_markers places its one."""
    arcs = ObservationSpec(kind="markers", marker_arc_lengths=(-0.1, 0.0, 0.5, 1.0, 1.1),
                           gripper_markers=0)  # fmt: skip
    layout = marker_layout(arcs, 0.8, 20, (True, True))
    assert layout.on_gripper.tolist() == [True, False, False, False, True]
    assert layout.holder.tolist() == [0, 0, -1, 1, 1]
    both = ObservationSpec(kind="markers", marker_arc_lengths=(0.0, 0.5, 1.0), gripper_markers=0.1)
    same = marker_layout(both, 0.8, 20, (True, True))
    for name in ("arc", "segment", "offset", "holder", "lever", "on_gripper"):
        assert np.allclose(getattr(layout, name), getattr(same, name)), name
    with pytest.raises(ValueError, match="gripper_markers 0"):  # both would place them
        ObservationSpec(kind="markers", marker_arc_lengths=(-0.1, 0.5, 1.0))


def test_dataset_keeps_the_reports(tmp_path):
    env = env_of(MUJOCO_ROD, dropout=0.3)
    try:
        episodes = [random_episode(env, s, s + 1) for s in range(2)]
    finally:
        env.close()
    Dataset.from_episodes(episodes).save(tmp_path / "d.h5")
    data = load_dataset(tmp_path / "d.h5")
    assert np.array_equal(data.episode(1).markers, episodes[1].markers.astype(np.float32))
    assert np.array_equal(data.episode(1).visible, episodes[1].visible)


def test_kalman_gain():
    assert kalman_gain(0, 1) == 1
    gains = [kalman_gain(s, 1) for s in (1, 2, 5, 10)]
    assert all(a > b for a, b in zip(gains, gains[1:], strict=False)) and 0 < gains[-1] < 0.2


def marker_model(env):
    layout = env.marker_layout
    spec = valid_model_spec({"name": "in-bilstm", "hidden": 8, "lstm_layers": 1})
    return build_marker_model(spec, len(layout), layout.held).eval().requires_grad_(False)


@pytest.mark.parametrize("backend", [MUJOCO_ROD, "pybullet"])
def test_plan_moves_held_markers_as_the_grippers_move(backend):
    """A plan's held markers (the robot's kinematics) land where the rod's held markers go
    when the env executes it."""
    env = env_of(backend)
    view = MarkerView(env, marker_model(env), torch.device("cpu"))
    try:
        obs, _ = env.reset(seed=4)
        view.observe(obs)
        actions = random_actions(np.random.default_rng(3), 6, 6) * 0.8
        commands = torch.as_tensor(env.task.to_grippers(actions), dtype=torch.float32)[None]
        planned = view._held_along(commands)[0]
        for t, action in enumerate(actions):
            env.step(action)
            state = env.state_parts()
            true = markers_of_state(env.marker_layout, state["positions"].astype(float),
                                    state["quaternions"].astype(float),
                                    state["grippers"].astype(float))  # fmt: skip
            gap = np.linalg.norm(planned[t].numpy() - true, axis=-1)[env.marker_layout.held]
            assert gap.max() < 1.5e-3
    finally:
        env.close()


def test_view_reads_a_clean_report_as_it_is_and_bridges_latency():
    clean, late = env_of(MUJOCO_ROD), env_of(MUJOCO_ROD, latency_steps=2)
    try:
        for env in (clean, late):
            view = MarkerView(env, marker_model(env), torch.device("cpu"))
            obs, _ = env.reset(seed=4)
            view.observe(obs)
            obs, *_ = env.step(np.full(6, 0.3))
            state, before = view.observe(obs)
            seen = torch.as_tensor(env.split_observation(obs)["markers"], dtype=torch.float32)
            free = ~torch.as_tensor(env.marker_layout.held)
            if env is clean:  # gain 1: the report is the estimate
                assert torch.equal(state[0, free], seen[free])
            else:  # rolled 2 steps on from the report by the model: not the report
                assert state.shape == (1, 10, 3) and not torch.equal(state[0, free], seen[free])
    finally:
        clean.close()
        late.close()


def test_rod_model_refused_with_markers_and_marker_model_without():
    from dlocli.controllers.base import make_controller
    from dlocli.models.base import build_model

    env, full = env_of(MUJOCO_ROD), make_env(MUJOCO_ROD, "single", render_mode=None, **QUICK)
    try:
        rod = build_model(valid_model_spec({"name": "mlp"}), 20)
        with pytest.raises(BadInput, match="observes markers"):
            make_controller("mpc", env, model=rod)
        with pytest.raises(BadInput, match="observes the full state"):
            make_controller("mpc", full, model=marker_model(env))
    finally:
        env.close()
        full.close()


def test_planner_acts_through_a_marker_model_under_every_fault():
    from dlocli.controllers.base import make_controller

    env = env_of(MUJOCO_ROD, noise_mm=3, latency_steps=1, dropout=0.1, occlusion_probability=0.1)
    try:
        planner = make_controller("mpc", env, model=marker_model(env),
                                  options={"horizon": 3})  # fmt: skip
        actions = ActionSequence(np.zeros((30, 6)))
        episode = rollout(env, planner, seed=2)
        assert len(episode) == 30 and np.isfinite(episode.actions).all()
        assert rollout(env, actions, seed=2).positions.shape == episode.positions.shape
    finally:
        env.close()


def test_learning_agents_take_the_markers_observation():
    """SAC and PILCO learn from the markers observation as from any other."""
    from dlocli.controllers.base import make_controller

    from tiny import TINY_AGENTS

    env = env_of(MUJOCO_ROD, noise_mm=2)
    try:
        for name in ("sac", "pilco"):
            agent = make_controller(name, env, options=TINY_AGENTS[name], seed=0)
            agent.learn(40)
            obs, _ = env.reset(seed=1)
            assert agent.act(obs).shape == (6,)
    finally:
        env.close()


def test_raw_tracking_plans_from_the_report_as_it_is():
    """tracking="raw": no blending and no latency bridging, the report is the state."""
    from dlocli.controllers.base import make_controller

    env = env_of(MUJOCO_ROD, noise_mm=5, latency_steps=2)
    try:
        planner = make_controller("mpc", env, model=marker_model(env),
                                  options={"horizon": 2, "tracking": "raw"})  # fmt: skip
        obs, _ = env.reset(seed=4)
        planner.reset(env.goal)
        for _ in range(3):
            planner.act(obs)
            obs, *_ = env.step(np.full(6, 0.2))
        planner.act(obs)
        seen = torch.as_tensor(env.split_observation(obs)["markers"], dtype=torch.float32)
        free = ~torch.as_tensor(env.marker_layout.held)
        assert torch.equal(planner._observed[0, free], seen[free])
    finally:
        env.close()
