"""A command from outside dlocli: the length of the polyline through a goal's segment
centres."""

from __future__ import annotations

from pathlib import Path

import typer

from dlocli.cli.common import emit_summary, handle_errors


@handle_errors
def goal_length(
    goal: Path = typer.Option(..., "--goal", help="A goal .npy file (N, 3), metres."),
    json: bool = typer.Option(False, "--json", help="Print the summary as JSON."),
) -> None:
    """Length (m) of the polyline through a goal's segment centres."""
    import numpy as np

    from dlocli.env.shape_env import load_goal

    shape = load_goal(goal, int(np.load(goal, mmap_mode="r").shape[0]))
    length = float(np.linalg.norm(np.diff(shape, axis=0), axis=1).sum())
    emit_summary({"goal": str(goal), "length_m": round(length, 6)}, json, "dlo goal-length")
