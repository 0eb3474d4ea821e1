"""Backend conformance: every registered backend passes the same checks (real physics)."""

from __future__ import annotations

import numpy as np
import pytest

from dlocli.backends import runnable_backends
from dlocli.backends.rotations import (
    quat_normalize,
    quat_rotate,
    quat_to_matrix,
)
from dlocli.env.shape_env import make_backend
from dlocli.errors import BadInput
from dlocli.registry import backends
from dlocli.specs import BackendSpec

BACKENDS = runnable_backends()


@pytest.fixture(params=BACKENDS)
def backend(request):
    b = make_backend(BackendSpec(name=request.param))
    b.reset(0)
    yield b
    b.close()


def smooth_velocities(seed: int, steps: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    v = rng.uniform(-1, 1, (steps // 10 + 1, 2, 6)).repeat(10, axis=0)[:steps]
    return v * np.array([0.1] * 3 + [0.5] * 3)


def test_shapes_and_units(backend):
    n = backend.n_segments
    pos, quat, grip = (
        backend.segment_positions(),
        backend.segment_quaternions(),
        backend.gripper_poses(),
    )
    assert pos.shape == (n, 3) and quat.shape == (n, 4) and grip.shape == (2, 7)
    assert np.allclose(np.linalg.norm(quat, axis=1), 1.0, atol=1e-6)
    seg = backend.rod.segment_length
    gaps = np.linalg.norm(np.diff(pos, axis=0), axis=1)
    assert np.allclose(gaps, seg, rtol=0.1), "segment centres must be one segment length apart"
    # segment x axes point along the rod, from centre i to centre i+1
    axes = quat_rotate(quat, np.array([1.0, 0.0, 0.0]))
    along = np.sum(axes[:-1] * np.diff(pos, axis=0), axis=1) / gaps
    assert np.all(along > 0.9)
    # the grippers hold the rod's end points (metres)
    start = pos[0] - 0.5 * seg * axes[0]
    end = pos[-1] + 0.5 * seg * axes[-1]
    assert np.linalg.norm(start - grip[0, :3]) < 0.01
    assert np.linalg.norm(end - grip[1, :3]) < 0.01
    # rest: grippers 0.9 L apart, rod hanging below them
    assert np.linalg.norm(grip[1, :3] - grip[0, :3]) == pytest.approx(0.9 * backend.rod.length)
    assert pos[:, 2].min() < grip[0, 2] - 0.05


def test_determinism(backend):
    other = make_backend(backend.spec)
    other.reset(0)
    for v in smooth_velocities(1, 30):
        assert backend.step(v) and other.step(v)
    np.testing.assert_array_equal(backend.segment_positions(), other.segment_positions())
    other.close()


def test_reset_restores_rest(backend):
    rest = backend.segment_positions()
    for v in smooth_velocities(2, 20):
        backend.step(v)
    assert not np.allclose(backend.segment_positions(), rest, atol=1e-3)
    backend.reset(0)
    np.testing.assert_allclose(backend.segment_positions(), rest, atol=1e-9)


def test_state_round_trip(backend):
    vels = smooth_velocities(3, 25)
    for v in vels[:10]:
        backend.step(v)
    state = backend.get_state()
    for v in vels[10:]:
        backend.step(v)
    after = backend.segment_positions()
    backend.set_state(state)
    for v in vels[10:]:
        backend.step(v)
    np.testing.assert_allclose(backend.segment_positions(), after, atol=1e-9)


def test_gripper_limits_hold_under_pulling(backend):
    """Pulling the grippers apart for 4 s never exceeds 95% of the rod length, nor tears it."""
    pull = np.zeros((2, 6))
    pull[0, 0], pull[1, 0] = -0.1, 0.1
    for _ in range(200):
        assert backend.step(pull), "pulling apart must not diverge the rod"
    grip = backend.gripper_poses()
    sep = np.linalg.norm(grip[1, :3] - grip[0, :3])
    assert sep <= 0.95 * backend.rod.length + 1e-9
    test_ends_stay_attached(backend)


def test_ends_stay_attached(backend):
    for v in smooth_velocities(4, 100):
        assert backend.step(v)
    pos, quat, grip = (
        backend.segment_positions(),
        backend.segment_quaternions(),
        backend.gripper_poses(),
    )
    seg = backend.rod.segment_length
    start = pos[0] - 0.5 * seg * quat_rotate(quat[0], np.array([1.0, 0, 0]))
    end = pos[-1] + 0.5 * seg * quat_rotate(quat[-1], np.array([1.0, 0, 0]))
    assert np.linalg.norm(start - grip[0, :3]) < 0.01
    assert np.linalg.norm(end - grip[1, :3]) < 0.01


def test_divergence_is_flagged_not_raised(backend):
    state = backend.get_state()
    state[15:] = np.nan
    backend.set_state(state)
    assert backend.step(np.zeros((2, 6))) is False
    assert backend.diverged
    assert backend.step(np.zeros((2, 6))) is False  # further steps are no-ops
    backend.reset(0)
    assert not backend.diverged and backend.step(np.zeros((2, 6)))


def test_render_returns_image(backend):
    img = backend.render(width=96, height=64, goal=backend.segment_positions() + 0.05)
    assert img.shape == (64, 96, 3) and img.dtype == np.uint8
    assert img.std() > 1.0, "the image must show something"


def test_a_backend_the_installed_simulator_cannot_run_refuses_in_one_line():
    """MuJoCo 4 removed the composite cable; MuJoCo 3's 1D flex has no twist: each MuJoCo
    rod refuses the other version with one line naming the other rod and the pin."""
    refused = [name for name in backends.names() if name not in runnable_backends()]
    assert refused, "one of the two MuJoCo rods needs the other MuJoCo major version"
    for name in refused:
        with pytest.raises(BadInput) as raised:
            make_backend(BackendSpec(name=name))
        message = str(raised.value)
        assert "\n" not in message and "--backend mujoco" in message and "pip install" in message


def test_the_default_backend_is_the_mujoco_rod_the_installed_mujoco_runs():
    assert BackendSpec().name in runnable_backends()
    assert BackendSpec().name.startswith("mujoco")


def test_segment_frames_round_trip_through_quaternions():
    from dlocli.backends.mujoco_flex import frames_to_quaternions

    rng = np.random.default_rng(0)
    quats = quat_normalize(rng.normal(size=(500, 4)))  # frames of every orientation
    matrices = quat_to_matrix(quats)
    np.testing.assert_allclose(
        frames_to_quaternions(matrices[..., 0], matrices[..., 1]), quats, atol=1e-12
    )
