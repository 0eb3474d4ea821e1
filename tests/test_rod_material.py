"""The rod spec's material fields on every backend: each one the spec accepts changes the
physics, the damping defaults are the backends' earlier behaviour, and what a backend cannot
simulate is refused by the spec itself."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from pydantic import ValidationError

from dlocli.backends import runnable_backends
from dlocli.env.shape_env import make_backend
from dlocli.errors import BadInput
from dlocli.migrations import LEGACY_VALUES
from dlocli.specs import BackendSpec, CollectSpec, RodSpec, resolve_spec

from tiny import committed_bench

BACKENDS = runnable_backends()
#: positions every 5th step of MOTION at the default spec, recorded at commit 7473c21 (before
#: the damping fields existed) on an AMD EPYC; bit-identical there with today's code
BEFORE_DAMPING_FIELDS = Path(__file__).parent / "data" / "rod_motion_7473c21.npz"
UNDAMPED_MUJOCO_DT = 0.0005  # s: MuJoCo's explicit elasticity needs it without damping


def motion() -> np.ndarray:
    """(2,6) twists: the right gripper rises at 0.1 m/s while turning about the rod axis."""
    twist = np.zeros((2, 6))
    twist[1] = [0.0, 0.0, 0.1, 0.5, 0.0, 0.0]
    return twist


def run_motion(spec: BackendSpec, steps: int) -> np.ndarray:
    """(steps, N, 7) segment positions and quaternions under ``motion()``."""
    backend = make_backend(spec)
    try:
        backend.reset(0)
        frames = []
        for _ in range(steps):
            assert backend.step(motion()), f"{spec.name} diverged"
            frames.append(np.hstack([backend.segment_positions(), backend.segment_quaternions()]))
        return np.array(frames)
    finally:
        backend.close()


# (field, value): each far from both backends' defaults
MATERIAL_CHANGES = [
    ("length", 0.8),
    ("radius", 0.012),
    ("density", 1500.0),
    ("young_bending", 2e7),
    ("poisson", 0.0),
    ("bending_damping", 0.2),
    ("twist_damping", 0.2),
    ("air_damping", 20.0),
    ("clamp_compliance", "rigid"),
]


@pytest.mark.parametrize("name", BACKENDS)
def test_every_material_field_changes_the_motion(name: str) -> None:
    small = {"n_segments": 10}  # fast; the field's effect does not need a fine rod
    base = run_motion(BackendSpec(name=name, rod=RodSpec(**small)), steps=15)
    for field, value in MATERIAL_CHANGES:
        changed = run_motion(BackendSpec(name=name, rod=RodSpec(**small, **{field: value})), 15)
        difference = np.abs(changed - base).max()
        assert difference > 1e-3, f"{name}: {field}={value} changes the motion by {difference:.1e}"


@pytest.mark.parametrize("name", BACKENDS)
def test_damping_defaults_are_the_earlier_rod_and_zero_damping_changes_it(name: str) -> None:
    archive = np.load(BEFORE_DAMPING_FIELDS)
    if name not in archive.files:
        pytest.skip(f"the {name} backend came after the damping fields: it has no earlier rod")
    recorded = archive[name]
    earlier = RodSpec(**LEGACY_VALUES["rod"])  # the rod of runs saved before these fields
    today = run_motion(BackendSpec(name=name, rod=earlier), steps=30)[4::5, :, :3]
    # bit for bit on the machine that recorded it; other CPUs round differently
    np.testing.assert_allclose(today, recorded, rtol=0, atol=1e-9)

    off = {"bending_damping": 0, "twist_damping": 0, "air_damping": 0}
    undamped = earlier.model_copy(update=off)
    dt = UNDAMPED_MUJOCO_DT if name == "mujoco" else None
    free = run_motion(BackendSpec(name=name, rod=undamped, physics_dt=dt), steps=30)[4::5, :, :3]
    assert np.abs(free - recorded).max() > 1e-3


def test_young_tension_is_refused_the_rods_are_inextensible() -> None:
    assert RodSpec(young_tension=1e8).young_tension == 1e8  # saved specs carry the default
    with pytest.raises(ValidationError, match="inextensible"):
        RodSpec(young_tension=2e8)
    with pytest.raises(BadInput, match="inextensible") as raised:
        resolve_spec(CollectSpec, overrides={"backend.rod.young_tension": 5e7})
    assert "\n" not in str(raised.value)


def test_segment_limits_are_the_spec_s() -> None:
    BackendSpec(name="pybullet", rod=RodSpec(n_segments=31))
    BackendSpec(name="mujoco", rod=RodSpec(n_segments=32))
    with pytest.raises(BadInput, match="at most 31 rod segments") as raised:
        resolve_spec(
            CollectSpec, overrides={"backend.name": "pybullet", "backend.rod.n_segments": 32}
        )
    assert "\n" not in str(raised.value)
    # a spec changed without validation is refused by the backend all the same
    unchecked = BackendSpec(name="pybullet").model_copy(update={"rod": RodSpec(n_segments=32)})
    with pytest.raises(BadInput, match="at most 31 rod segments"):
        make_backend(unchecked)


def test_a_spec_saved_before_the_rod_fields_is_the_earlier_rod_with_its_fingerprint(
    tmp_path: Path,
) -> None:
    from dlocli.bench.spec import BenchSpec, fingerprint
    from dlocli.resume import saved_spec

    saved = BenchSpec().model_dump(mode="json")
    for name in LEGACY_VALUES["rod"]:  # a bench job made before the clamp and damping fields
        del saved["backend"]["rod"][name]
    del saved["backend"]["gravity"]
    path = tmp_path / "spec.json"
    path.write_text(json.dumps(saved))
    earlier = BenchSpec.model_validate(saved_spec(path))
    assert earlier.backend.rod == RodSpec(**LEGACY_VALUES["rod"])
    # its fingerprint is the one it was saved with; today's default rod is another
    legacy = BenchSpec(backend=BackendSpec(rod=RodSpec(**LEGACY_VALUES["rod"])))
    assert fingerprint(earlier) == fingerprint(legacy) != fingerprint(BenchSpec())
    damped = legacy.model_copy(
        update={"backend": BackendSpec(rod=RodSpec(**{**LEGACY_VALUES["rod"], "air_damping": 5.0}))}
    )
    assert fingerprint(damped) != fingerprint(legacy)


def test_committed_bench_jobs_are_marked_as_made_with_the_earlier_rod(tmp_path: Path) -> None:
    from dlocli.bench.spec import BenchSpec, fingerprint
    from dlocli.resume import load_saved_spec

    run = committed_bench("bench_paper", tmp_path / "bench_paper")
    spec = load_saved_spec(BenchSpec, run / "spec.json")
    assert spec.backend.rod == RodSpec(**LEGACY_VALUES["rod"])
    today = spec.model_copy(update={"backend": spec.backend.model_copy(update={"rod": RodSpec()})})
    for path in sorted((run / "jobs").glob("*.json")):
        job = json.loads(path.read_text())
        assert job["fingerprint"] == fingerprint(spec, job["agent"]), path.name
        assert job["fingerprint"] != fingerprint(today, job["agent"]), path.name


def test_committed_bench_jobs_keep_the_composite_cable_in_their_fingerprints(
    tmp_path: Path,
) -> None:
    """MuJoCo 4's flex rod is today's default: a bench on it reruns its jobs rather than taking
    the ones the composite cable made (MuJoCo 3.17) as its own."""
    from dlocli.bench.spec import BenchSpec, fingerprint
    from dlocli.resume import load_saved_spec

    run = committed_bench("bench_paper", tmp_path / "bench_paper")
    spec = load_saved_spec(BenchSpec, run / "spec.json")
    assert spec.backend.name == "mujoco"
    flex = spec.model_copy(
        update={"backend": spec.backend.model_copy(update={"name": "mujoco-flex"})}
    )
    for path in sorted((run / "jobs").glob("*.json")):
        job = json.loads(path.read_text())
        assert job["fingerprint"] == fingerprint(spec, job["agent"]), path.name
        assert job["fingerprint"] != fingerprint(flex, job["agent"]), path.name
