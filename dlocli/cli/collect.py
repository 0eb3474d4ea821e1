"""`dlo collect --random`: random-action trajectories into an HDF5 dataset."""

from __future__ import annotations

from typing import Annotated

import typer

from dlocli.cli.common import (
    AcceptChangesFlag,
    ResumeFlag,
    emit_summary,
    handle_errors,
)
from dlocli.cli.flags import RunFlags, spec_flags
from dlocli.cli.progress import Bars
from dlocli.processes import signal_token
from dlocli.runs.collect import collect_random, resumed_spec
from dlocli.specs import CollectSpec


@handle_errors
@spec_flags(CollectSpec)
def collect(
    run: RunFlags,
    random: Annotated[
        bool,
        typer.Option(
            "--random",
            help="Held uniform random actions: the only policy of `dlo collect`, so the flag "
            "may be left out (MPC data come from `dlo online`).",
        ),
    ] = False,
    resume: ResumeFlag = None,
    accept_changes: AcceptChangesFlag = False,
) -> None:
    """Collect random-action episodes into OUT/dataset.h5 (format: `dlocli.data`).

    Each finished episode is saved at once; `--resume OUT` collects only the missing ones.
    """
    run.refuse_with_resume(resume)
    spec = resumed_spec(resume, run.overrides) if resume is not None else run.spec()
    with Bars(run.json, every={"episode": max(spec.episodes // 20, 1)}) as bars:
        summary = collect_random(
            spec,
            run.overwrite,
            bars,
            resume=resume is not None,
            accept_changes=accept_changes,
            cancel=signal_token(),
        )
    emit_summary(summary, run.json, "dlo collect")
