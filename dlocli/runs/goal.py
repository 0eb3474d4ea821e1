"""`dlo goal`: a reachable goal shape, drawn from the same distribution as the env's goals,
saved as an (N, 3) .npy array in metres."""

from __future__ import annotations

from typing import Any

import numpy as np

from dlocli.env.metrics import shape_error_mm
from dlocli.env.shape_env import make_backend, make_goal, save_goal
from dlocli.errors import BadInput
from dlocli.io import check_writable
from dlocli.runs.checks import check_registered
from dlocli.specs import GoalSpec


def run_goal(spec: GoalSpec, overwrite: bool = False) -> dict[str, Any]:
    """Drive the grippers to a random pose (seeded), let the rod settle and save its shape at
    ``spec.out``; the summary says how far it lies from the rest shape."""
    check_registered(spec)
    if spec.out.suffix != ".npy":
        raise BadInput(f"--out {spec.out} must end in .npy (the goal format is a (N,3) .npy array)")
    check_writable(spec.out, "--out", overwrite)
    shape = make_goal(spec)
    save_goal(shape, spec.out)
    return {
        "path": str(spec.out),
        "segments": int(shape.shape[0]),
        "seed": spec.seed,
        "distance_from_rest_mm": round(float(shape_error_mm(rest_shape(spec), shape)), 1),
    }


def rest_shape(spec: GoalSpec) -> np.ndarray:
    """(N, 3) segment centres of the rod at rest on ``spec``'s backend."""
    backend = make_backend(spec.backend, spec.task.control_dt)
    backend.reset(spec.seed)
    shape = backend.segment_positions()
    backend.close()
    return shape
