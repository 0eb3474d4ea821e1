"""`dlo goal`: write a reachable goal shape (N,3) in metres to a .npy file."""

from __future__ import annotations

from dlocli.cli.common import emit_summary, handle_errors
from dlocli.cli.flags import RunFlags, spec_flags
from dlocli.runs.goal import run_goal
from dlocli.specs import GoalSpec


@handle_errors
@spec_flags(GoalSpec)
def goal(
    run: RunFlags,
) -> None:
    """Drive the grippers to a random pose (seeded), let the rod settle, save its shape: a
    goal drawn from the same distribution as the env's goals."""
    emit_summary(run_goal(run.spec(), run.overwrite), run.json, "dlo goal")
