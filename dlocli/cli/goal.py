"""`dlo goal`: write a reachable goal shape (N,3) in metres to a .npy file."""

from __future__ import annotations

from dlocli.cli.common import emit_summary, handle_errors
from dlocli.cli.flags import RunFlags, spec_flags
from dlocli.errors import BadInput
from dlocli.io import check_writable
from dlocli.specs import GoalSpec


@handle_errors
@spec_flags(GoalSpec)
def goal(
    run: RunFlags,
) -> None:
    """Drive the grippers to a random pose (seeded), let the rod settle, save its shape: a
    goal drawn from the same distribution as the env's goals."""
    from dlocli.env.metrics import shape_error_mm
    from dlocli.env.shape_env import make_goal, save_goal
    from dlocli.runs.checks import check_registered

    spec = run.spec()
    check_registered(spec)
    if spec.out.suffix != ".npy":
        raise BadInput(f"--out {spec.out} must end in .npy (the goal format is a (N,3) .npy array)")
    check_writable(spec.out, "--out", run.overwrite)
    shape = make_goal(spec)
    save_goal(shape, spec.out)
    rest = _rest_shape(spec)
    emit_summary(
        {
            "path": str(spec.out),
            "segments": int(shape.shape[0]),
            "seed": spec.seed,
            "distance_from_rest_mm": round(float(shape_error_mm(rest, shape)), 1),
        },
        run.json,
        "dlo goal",
    )


def _rest_shape(spec: GoalSpec):
    from dlocli.env.shape_env import make_backend

    backend = make_backend(spec.backend, spec.task.control_dt)
    backend.reset(spec.seed)
    shape = backend.segment_positions()
    backend.close()
    return shape
