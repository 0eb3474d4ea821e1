"""The rod against textbook mechanics, per backend: simulated / reference at N = 20.

Runs every check of ``dlocli.backends.conformance`` (the same ones
tests/test_physics_conformance.py asserts: references computed there, closed forms and the
elastica solved with scipy's ``solve_bvp``) on every backend that runs here (MuJoCo 3 runs
the composite cable "mujoco", MuJoCo 4 the flex rod "mujoco-flex"), the earlier rod's
self-weight (``clamp_compliance="rigid"``) for comparison, both backends on the same 2 s
motion, and what PyBullet adds to the segments' rotary inertia at its default step.

    python benchmarks/rod_physics.py > benchmarks/results/rod_physics.txt           # MuJoCo 3
    python benchmarks/rod_physics.py > benchmarks/results/rod_physics_mujoco4.txt   # MuJoCo 4
"""

from __future__ import annotations

import itertools
import subprocess
import sys
import time
from datetime import date

import numpy as np

from dlocli.backends import conformance, runnable_backends
from dlocli.backends.base import material_physics_dt
from dlocli.env.shape_env import make_backend
from dlocli.registry import backends
from dlocli.specs import BackendSpec, RodSpec


def commit() -> str:
    try:
        return subprocess.run(
            ["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True, check=True
        ).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


def ratio_cell(check: conformance.Check, name: str) -> str:
    if conformance.missing(check, name):
        return "cannot"
    ratio = check.run(name)
    mark = "" if abs(ratio - 1) <= check.tolerance else " !"
    return f"{ratio:.3f}{mark}"


def earlier_rod_self_weight(name: str) -> str:
    rod = conformance.static_rod(clamp_compliance="rigid")
    backend = conformance.cantilever(name, rod)
    try:
        drop = backend.gripper_poses()[0, 2] - conformance.settle(backend)[2]
    finally:
        backend.close()
    return f"{drop / conformance.self_weight_deflection(rod):.3f}"


def added_inertia(rod: RodSpec) -> str:
    if "pybullet" not in backends.names():
        return "-"
    backend = make_backend(BackendSpec(name="pybullet", rod=rod))
    try:
        return f"{backend.added_inertia:.0f}x"
    finally:
        backend.close()


def main() -> None:
    import mujoco

    names = runnable_backends()
    print(
        f"# python benchmarks/rod_physics.py, {date.today()}, on {commit()}, MuJoCo "
        f"{mujoco.__version__}; "
        "simulated / reference (! = outside the tolerance)"
    )
    print(
        f"N {conformance.SEGMENTS}, E 1e7 Pa, r 0.01 m, rho 1000 kg/m^3; statics: the "
        f"{conformance.SHORT} m rod (air damping {conformance.STATIC_AIR_DAMPING:g}/s to settle)"
        "; dynamics: gravity and damping off, at material_physics_dt "
        f"({material_physics_dt(conformance.paper_rod()) * 1e3:.3f} ms for the 1 m rod, "
        f"{material_physics_dt(conformance.short_rod()) * 1e6:.0f} us for the 0.2 m rod)"
    )
    print(f"{'check':40s}{'tolerance':>10s}" + "".join(f"{n:>12s}" for n in names))
    for check in conformance.CHECKS:
        start = time.perf_counter()
        cells = [ratio_cell(check, n) for n in names]
        print(
            f"{check.name:40s}{check.tolerance:>10.0%}" + "".join(f"{c:>12s}" for c in cells),
            f"  ({time.perf_counter() - start:.0f} s)",
        )
        sys.stdout.flush()
    cells = [earlier_rod_self_weight(n) for n in names]
    print(
        f"{'earlier rod (rigid clamp), self-weight':40s}{'':>10s}"
        + "".join(f"{c:>12s}" for c in cells)
    )
    paths = {n: conformance.same_motion(n) for n in names}
    for a, b in itertools.combinations(names, 2):
        distance = np.linalg.norm(paths[a] - paths[b], axis=-1)
        print(
            f"same 2 s motion (10 cm, 0.5 rad), {a} vs {b}: mean {distance.mean() * 1e3:.2f} mm, "
            f"max {distance.max() * 1e3:.2f} mm (air damping {conformance.MOTION_AIR_DAMPING:g}/s"
            ", material_physics_dt)"
        )
    print(
        "pybullet's added rotary inertia at its default 2 ms step, default damping: "
        f"1 m rod {added_inertia(RodSpec())}, 0.2 m rod {added_inertia(RodSpec(length=0.2))}; "
        "undamped: 1 m rod "
        f"{added_inertia(RodSpec(**conformance.UNDAMPED))}, 0.2 m rod "
        f"{added_inertia(RodSpec(length=0.2, **conformance.UNDAMPED))}"
    )


if __name__ == "__main__":
    main()
