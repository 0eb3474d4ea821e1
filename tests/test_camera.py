"""The simulated depth camera (dlocli/tracking/camera.py) on the backends' real rays: each
simulator's rays against the analytic caster on the same state, the cloud on the cable's
surface, the grippers hiding it, the noise model, stray points, and bad cameras refused."""

from __future__ import annotations

import numpy as np
import pytest

from dlocli.backends.base import Backend
from dlocli.backends.rays import CABLE, GRIPPER, TABLE, rotation_matrices
from dlocli.errors import BadInput
from dlocli.registry import backends
from dlocli.tracking.camera import DepthCamera, depth_sigma
from dlocli.tracking.spec import CameraSpec

from tiny import MUJOCO_ROD

BACKENDS = [MUJOCO_ROD, "pybullet"]
CLEAN = CameraSpec().clean().model_dump()


@pytest.fixture(scope="module", params=BACKENDS)
def moved(request):
    """A backend whose right gripper has moved and turned: the rod bent and swinging."""
    backend = backends.get(request.param)()
    backend.reset()
    twist = np.zeros((2, 6))
    twist[1] = (-0.15, 0.1, 0.1, 0.3, 0.0, 0.5)
    for _ in range(40):
        backend.step(twist)
    yield backend
    backend.close()


def axis_distance(backend: Backend, points: np.ndarray, segments: np.ndarray) -> np.ndarray:
    """Each point's distance to the axis of its rod segment (m)."""
    centres = backend.segment_positions()[segments]
    axes = rotation_matrices(backend.segment_quaternions()[segments])[:, :, 0]
    offset = points - centres
    along = np.einsum("ij,ij->i", offset, axes)
    return np.linalg.norm(offset - along[:, None] * axes, axis=1)


def test_simulator_rays_agree_with_the_analytic_caster(moved):
    """The same rays on the same state: MuJoCo's and PyBullet's against capsules and boxes
    cast in numpy (PyBullet's convex ray test is approximate at silhouettes)."""
    camera = DepthCamera({**CLEAN, "width": 200, "height": 150}, moved.rod.length)
    own = moved.cast_rays(camera.origin, camera.rays)
    analytic = Backend.cast_rays(moved, camera.origin, camera.rays)
    hit = np.isfinite(own.distance) & np.isfinite(analytic.distance)
    assert (own.kind == CABLE).sum() > 50 and (own.kind == GRIPPER).sum() > 5
    some = (own.kind != 0) | (analytic.kind != 0)
    agree = own.kind == analytic.kind
    assert agree[some].mean() > 0.9  # PyBullet's capsules are ~0.5 mm thicker (its margin)
    cable = [(hits.kind == CABLE).sum() for hits in (own, analytic)]
    assert abs(cable[0] - cable[1]) <= 0.1 * cable[1]
    both_cable = agree & (own.kind == CABLE)
    assert (own.segment[both_cable] == analytic.segment[both_cable]).mean() > 0.95
    gap = np.abs(own.distance[hit] - analytic.distance[hit])
    assert np.median(gap) < 1e-3 and np.percentile(gap, 90) < 3e-3


def test_the_cloud_lies_on_the_cable_surface_in_the_world_frame(moved):
    camera = DepthCamera({**CLEAN, "see_grippers": False}, moved.rod.length)
    camera.check_view(moved)
    frame = camera.capture(moved, np.random.default_rng(0), time=0.5)
    assert len(frame.points) > 30 and (frame.segment >= 0).all() and frame.time == 0.5
    gap = axis_distance(moved, frame.points, frame.segment) - moved.rod.radius
    assert np.percentile(np.abs(gap), 90) < 1e-3
    # the extrinsics: the camera sits where its spec says and looks along its z axis
    assert np.allclose(frame.viewpoint, np.array(camera.spec.position) * moved.rod.length)
    towards = np.array(camera.spec.look_at) * moved.rod.length - frame.viewpoint
    assert np.allclose(frame.extrinsics[:3, 2], towards / np.linalg.norm(towards))
    # every segment shows, and the points project back inside the image
    assert len(np.unique(frame.segment)) >= 0.8 * moved.n_segments
    local = (frame.points - frame.viewpoint) @ frame.extrinsics[:3, :3]
    pixels = local @ frame.intrinsics.T
    u, v = pixels[:, 0] / pixels[:, 2], pixels[:, 1] / pixels[:, 2]
    assert (u >= 0).all() and (u <= camera.spec.width).all() and (v >= 0).all()


def test_grippers_hide_the_cable_ends(moved):
    rng = np.random.default_rng(0)
    hidden = DepthCamera(CLEAN, moved.rod.length).capture(moved, rng)
    clear = DepthCamera({**CLEAN, "see_grippers": False}, moved.rod.length).capture(moved, rng)
    ends = [0, moved.n_segments - 1]
    assert np.isin(hidden.segment, ends).sum() < np.isin(clear.segment, ends).sum()
    middle = moved.n_segments // 2
    assert (hidden.segment == middle).sum() == (clear.segment == middle).sum()


def test_depth_noise_grows_with_distance_and_follows_its_model(moved):
    spec = CameraSpec(width=320, height=240, invalid_fraction=0.0, stray_fraction=0.0)
    noisy = DepthCamera(spec, moved.rod.length)
    clean = DepthCamera(spec.clean(), moved.rod.length)
    a = noisy.capture(moved, np.random.default_rng(1))
    b = clean.capture(moved, np.random.default_rng(1))
    assert np.array_equal(a.segment, b.segment)  # the same pixels: no faults drop any
    axis = a.extrinsics[:3, 2]
    depth = (b.points - b.viewpoint) @ axis
    error = (a.points - b.points) @ axis
    assert len(depth) > 200
    assert 0.8 < np.std(error / depth_sigma(spec, depth)) < 1.2
    sigma = depth_sigma(spec, np.array([0.5, 1.0, 2.0]))
    assert sigma[0] < sigma[1] < sigma[2]


def test_invalid_pixels_and_stray_points_at_their_rates(moved):
    spec = CameraSpec(invalid_fraction=0.3, stray_fraction=0.1, width=320, height=240)
    frame = DepthCamera(spec, moved.rod.length).capture(moved, np.random.default_rng(2))
    full = DepthCamera(
        {**CLEAN, "width": 320, "height": 240}, moved.rod.length
    ).capture(moved, np.random.default_rng(2))  # fmt: skip
    cable = (frame.segment >= 0).sum()
    assert abs(cable / len(full.points) - 0.7) < 0.1
    assert (frame.segment < 0).sum() == round(0.1 * cable)
    # strays are table or gripper pixels: off the cable
    strays = frame.points[frame.segment < 0]
    assert np.min(np.linalg.norm(strays[:, None] - full.points[None], axis=2), axis=1).max() > 0


def test_the_table_is_in_the_scene(moved):
    camera = DepthCamera(CLEAN, moved.rod.length)
    hits = camera.cast(moved)
    table = hits.kind == TABLE
    assert table.any()
    points = camera.origin + hits.distance[table, None] * camera.rays[table]
    assert np.allclose(points[:, 2], 0.0, atol=1e-9)


@pytest.mark.parametrize(
    "fields, words",
    [
        ({"width": 0}, "width"),
        ({"fov_deg": 180}, "fov_deg"),
        ({"fx": -5.0}, "focal"),
        ({"cx": 500.0}, "cx"),
        ({"look_at": (0.0, -1.6, 1.1)}, "look_at"),
        ({"min_range": 3.0, "max_range": 2.0}, "max_range"),
    ],
)
def test_intrinsics_that_make_no_image_are_one_line_bad_input(fields, words):
    with pytest.raises(BadInput) as caught:
        DepthCamera(fields)
    message = str(caught.value)
    assert "\n" not in message and words in message and message.startswith("camera")


def test_a_camera_that_does_not_see_the_cable_is_refused(moved):
    away = DepthCamera({"look_at": (0.0, -3.0, 1.1)}, moved.rod.length)
    with pytest.raises(BadInput) as caught:
        away.check_view(moved)
    assert "does not see the cable" in str(caught.value) and "\n" not in str(caught.value)
    DepthCamera(CLEAN, moved.rod.length).check_view(moved)  # the default one does
