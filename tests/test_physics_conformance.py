"""The rod against textbook mechanics on every registered backend (dlocli.backends.conformance).

Each check simulates through the public backend API and compares with a reference computed
in the same run (closed forms, the elastica solved with scipy's ``solve_bvp``): statics within
3% at N = 20, first bending and twist frequencies with damping off within 10%, an asked
damping ratio within 20%. A backend lacking an ability a check needs is skipped with the
reason. The slow checks simulate seconds at the step of the segments' real inertia.
"""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from dlocli.backends import conformance, runnable_backends

NAMES = runnable_backends()
MOTION_MEAN_DISTANCE = 1e-3  # m, between two backends' segments on the same motion


def check_params() -> list:
    return [
        pytest.param(check, name, id=f"{name}-{check.name}", marks=[pytest.mark.slow] * check.slow)
        for check, name in itertools.product(conformance.CHECKS, NAMES)
    ]


@pytest.mark.parametrize(("check", "name"), check_params())
def test_backend_conforms(check: conformance.Check, name: str) -> None:
    reason = conformance.missing(check, name)
    if reason:
        pytest.skip(reason)
    ratio = check.run(name)
    assert abs(ratio - 1.0) <= check.tolerance, (
        f"{name}: {check.name} is {ratio:.3f} of the reference (tolerance {check.tolerance:.0%})"
    )


def test_the_elastica_reference_is_euler_bernoulli_at_small_loads() -> None:
    alpha = 0.01  # w L^3 / EI: the tip drop of the linear theory is alpha L / 8
    assert conformance.elastica_deflection(alpha, 1.0) == pytest.approx(alpha / 8, rel=1e-3)
    # and large loads deflect less than linear theory says
    assert conformance.elastica_deflection(10.0, 1.0) < 10.0 / 8


@pytest.mark.slow
@pytest.mark.skipif(len(NAMES) < 2, reason="one backend: nothing to compare")
def test_backends_agree_on_the_same_motion() -> None:
    paths = {name: conformance.same_motion(name) for name in NAMES}
    for a, b in itertools.combinations(NAMES, 2):
        distance = np.linalg.norm(paths[a] - paths[b], axis=-1)
        assert distance.mean() <= MOTION_MEAN_DISTANCE, (
            f"{a} and {b} are {distance.mean() * 1e3:.2f} mm apart on average "
            f"(largest {distance.max() * 1e3:.2f} mm)"
        )
