"""The tracker (dlocli/tracking/) on real simulated cables seen by the simulated depth
camera: its markers against the simulator's true ones, against references measured in the
same run (the markers left where the first frame had them; a hidden span frozen where it
was last seen), its visibility flags, its priors, and bad input refused in one line."""

from __future__ import annotations

import numpy as np
import pytest

from dlocli.env.shape_env import make_env
from dlocli.errors import BadInput
from dlocli.models.base import valid_model_spec
from dlocli.models.marker_model import build_marker_model
from dlocli.specs import TaskSpec
from dlocli.tracking.camera import CloudFrame, DepthCamera
from dlocli.tracking.frames import load_frames, save_frames
from dlocli.tracking.measure import (
    HiddenSpan,
    env_layout,
    policy_action,
    robot_held,
    track_episode,
    true_markers,
)
from dlocli.tracking.model_prior import MarkerModelPrior
from dlocli.tracking.priors import ContinuityPrior, NodePrior
from dlocli.tracking.spec import CameraSpec, TrackerSpec
from dlocli.tracking.tracker import CableTracker

from tiny import MUJOCO_ROD

STEPS = 80  # control steps: 40 frames at 25 per second, the gripper on its way to the goal
CLEAN_VIEW = CameraSpec().clean().model_copy(update={"see_grippers": False})


class StandStill:
    """A prior that expects nothing to move (the reference a prior must beat)."""

    def predict(self, history: np.ndarray, held_next: np.ndarray | None) -> np.ndarray:
        return history[-1]


@pytest.fixture(scope="module", params=[MUJOCO_ROD, "pybullet"])
def env(request):
    env = make_env(request.param, TaskSpec(name="single", goal="random"), seed=0,
                   render_mode=None)  # fmt: skip
    yield env
    env.close()


def tracker_of(env, spec: TrackerSpec | None = None, prior: NodePrior | None = None):
    layout = env_layout(env)
    return layout, CableTracker.for_layout(layout, env.backend.rod.radius, spec, prior)


def still_error(env, layout, seed: int, steps: int) -> float:
    """Mean error (mm) of the free markers left where they were at the start."""
    env.reset(seed=seed)
    first = true_markers(env, layout)
    rng, errors = np.random.default_rng(seed), []
    for step in range(steps + 1):
        if step % 2 == 0:
            errors.append(np.linalg.norm(true_markers(env, layout) - first, axis=1))
        if step < steps:
            env.step(policy_action(env, "oracle", rng))
    return float(np.mean(np.array(errors)[:, ~layout.held])) * 1e3


def test_the_tracker_follows_a_moving_cable_through_a_noisy_camera(env):
    layout, tracker = tracker_of(env)
    camera = DepthCamera(CameraSpec(), env.backend.rod.length)  # noise, strays, grippers
    episode = track_episode(env, camera, tracker, layout, seed=1, steps=STEPS)
    reference = still_error(env, layout, seed=1, steps=STEPS)
    assert reference > 30.0  # the cable moved
    assert episode.errors.mean() < min(6.0, 0.15 * reference)
    assert np.percentile(episode.errors, 95) < 15.0
    # nothing hid the free markers (the grippers hide the held ends)
    assert episode.visible[:, ~layout.held].mean() > 0.9


def test_the_first_frame_is_ordered_from_the_grippers_or_from_the_cloud(env):
    layout, tracker = tracker_of(env)
    env.reset(seed=2)
    frame = DepthCamera(CLEAN_VIEW, env.backend.rod.length).capture(
        env.backend, np.random.default_rng(0)
    )
    truth = true_markers(env, layout)
    free = ~layout.held
    # without the grippers' poses nothing holds the chain's ends: it may slide along the cable
    for held, margin in ((robot_held(env, layout), 6e-3), (None, 20e-3)):
        report = tracker.start(frame, held)
        assert report.markers.shape == (len(layout), 3) and report.chain.shape[1] == 3
        error = np.linalg.norm(report.markers - truth, axis=1)[free]
        assert error.mean() < margin
        # in order from the left gripper: each free marker nearest its own true position
        nearest = np.argmin(
            np.linalg.norm(report.markers[free, None] - truth[None, free], axis=2), axis=1
        )
        assert (nearest == np.arange(free.sum())).all()


def test_a_hidden_third_is_predicted_by_continuity_within_a_margin(env):
    hidden = HiddenSpan(first=7, last=13, start=10, frames=15)
    camera = DepthCamera(CLEAN_VIEW, env.backend.rod.length)
    layout, tracker = tracker_of(env)
    episode = track_episode(env, camera, tracker, layout, 1, STEPS, hidden=hidden)
    # the reference: the hidden span frozen where it was last seen
    _, frozen = tracker_of(env, TrackerSpec(hidden_weight=1e4), StandStill())
    reference = track_episode(env, camera, frozen, layout, 1, STEPS, hidden=hidden)
    during = episode.errors[episode.hidden].mean()
    assert during < min(15.0, 0.5 * reference.errors[reference.hidden].mean())
    after = episode.errors[hidden.start + hidden.frames + 5 :].mean()
    assert after < 6.0  # found again once seen
    # the hidden markers (arcs inside segments 7 to 13) are flagged, the others seen
    inside = (layout.arc > 7.5 / 20) & (layout.arc < 13.5 / 20) & ~layout.on_gripper
    flags = episode.visible[episode.hidden]
    assert not flags[:, inside].any() and flags[:, ~inside & ~layout.on_gripper].mean() > 0.8


def test_the_continuity_prior_keeps_velocity_held_nodes_and_spacing():
    held = np.array([True, False, False, True])
    prior = ContinuityPrior(held, np.full(3, 0.1), damping=0.5)
    line = np.stack([np.arange(4) * 0.1, np.zeros(4), np.zeros(4)], axis=1)
    moving = np.stack([line, line + [0.0, 0.0, 0.02]])
    out = prior.predict(moving, held_next=line[held] + [0.0, 0.0, 0.03])
    assert np.allclose(out[held, 2], 0.03) and np.allclose(out[~held, 2], 0.03)
    apart = prior.predict(line[None] * [3.0, 1.0, 1.0], held_next=None)
    assert (np.linalg.norm(np.diff(apart, axis=0), axis=1) <= 0.1 + 1e-3).all()
    with pytest.raises(BadInput):
        prior.predict(np.zeros((2, 5, 3)), None)


def test_the_marker_model_prior_wraps_one_model_step(env):
    layout = env_layout(env)
    spec = valid_model_spec({"name": "mlp"})
    model = build_marker_model(spec, len(layout), layout.held)
    prior = MarkerModelPrior(model, layout.held)
    env.reset(seed=0)
    frames = np.stack([true_markers(env, layout)] * 2)
    held_next = frames[-1][layout.held] + [0.0, 0.0, 0.01]
    out = prior.predict(frames, held_next)
    assert out.shape == (len(layout), 3) and np.isfinite(out).all()
    assert np.allclose(out[layout.held], held_next, atol=1e-6)
    _, tracker = tracker_of(env, prior=prior)
    camera = DepthCamera(CLEAN_VIEW, env.backend.rod.length)
    episode = track_episode(env, camera, tracker, layout, seed=0, steps=10)
    assert np.isfinite(episode.errors).all()
    with pytest.raises(BadInput) as caught:
        MarkerModelPrior(model, ~layout.held)
    assert "\n" not in str(caught.value)


def test_bad_clouds_and_held_positions_are_one_line_bad_input(env):
    layout, tracker = tracker_of(env)
    env.reset(seed=0)
    frame = DepthCamera(CLEAN_VIEW, env.backend.rod.length).capture(
        env.backend, np.random.default_rng(0)
    )
    held = robot_held(env, layout)
    nan = frame.points.copy()
    nan[3, 1] = np.nan
    empty = CloudFrame(np.zeros((0, 3)), frame.extrinsics, frame.intrinsics)
    cases = [
        (lambda: tracker.start(CloudFrame(nan, frame.extrinsics, frame.intrinsics), held), "NaN"),
        (lambda: tracker.start(empty, held), "0 cable points"),
        (lambda: tracker.start(frame, held[:1]), "held markers"),
    ]
    for call, words in cases:
        with pytest.raises(BadInput) as caught:
            call()
        assert words in str(caught.value) and "\n" not in str(caught.value)


def test_frame_files_round_trip_and_bad_ones_are_refused(env, tmp_path):
    layout = env_layout(env)
    camera = DepthCamera(CameraSpec(), env.backend.rod.length)
    env.reset(seed=0)
    rng = np.random.default_rng(0)
    frames, held = [], []
    for step in range(4):
        frames.append(camera.capture(env.backend, rng, time=0.04 * step))
        held.append(robot_held(env, layout))
        env.step(policy_action(env, "oracle", rng))
    path = tmp_path / "clouds.npz"
    save_frames(path, frames, np.stack(held))
    read = load_frames(path)
    assert len(read.frames) == 4 and np.allclose(read.held, np.stack(held))
    for a, b in zip(read.frames, frames, strict=True):
        assert np.allclose(a.points, b.points, atol=1e-6) and a.time == b.time
        assert np.array_equal(a.extrinsics, b.extrinsics)
    _, tracker = tracker_of(env)
    tracker.start(read.frames[0], read.held[0])
    assert np.isfinite(tracker.step(read.frames[1], read.held[1]).markers).all()

    good = dict(np.load(path))
    nan = {**good, "points": good["points"].copy()}
    nan["points"][5, 0] = np.nan
    cases = {
        "NaN": nan,
        "no points": {**good, "points": np.zeros((0, 3)), "counts": np.zeros(4, dtype=int)},
        "first frame has no points": {
            **good, "counts": np.concatenate([[0, good["counts"][0] + good["counts"][1]],
                                              good["counts"][2:]]),
        },
        "lacks times": {k: v for k, v in good.items() if k != "times"},
        "expected (n, 3)": {**good, "points": good["points"][:, :2]},
    }  # fmt: skip
    for words, arrays in cases.items():
        bad = tmp_path / "bad.npz"
        np.savez(bad, **arrays)
        with pytest.raises(BadInput) as caught:
            load_frames(bad)
        assert words in str(caught.value) and "\n" not in str(caught.value), words
    (tmp_path / "text.npz").write_text("not a zip")
    with pytest.raises(BadInput, match="not a readable .npz"):
        load_frames(tmp_path / "text.npz")
