"""`dlo view RUN`: a run's 3D recording in the Rerun viewer (the 'view' extra)."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from dlocli.cli.common import handle_errors
from dlocli.runs.view import view as view_run


@handle_errors
def view(
    run: Annotated[
        Path,
        typer.Argument(
            metavar="RUN",
            help="A recording (.rrd), a `dlo control --record` run directory, or a run of saved "
            "episodes (`dlo collect`, `dlo online`: its recording is written as "
            "RUN/recording.rrd first).",
            show_default=False,
        ),
    ],
) -> None:
    """Open a run's 3D recording (rod, goal, grippers, markers, plan, error) in Rerun."""
    typer.echo(view_run(run))
