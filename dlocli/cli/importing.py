"""`dlo import`: recorded cable trajectories (DEFORM layout, any supported format) into a
marker dataset."""

from __future__ import annotations

from dlocli.cli.common import emit_summary, handle_errors
from dlocli.cli.flags import RunFlags, spec_flags
from dlocli.cli.progress import Bars
from dlocli.processes import signal_token
from dlocli.recorded_cables.importing import run_import
from dlocli.recorded_cables.spec import ImportSpec


@handle_errors
@spec_flags(ImportSpec)
def import_recordings(
    run: RunFlags,
) -> None:
    """Import --source (train/ and eval/ of .pkl pickled (frames, 3, markers) lists, read
    without running code, .npy/.npz/.h5 arrays, motion-capture .csv or ROS 2 bag folders)
    into OUT/dataset.h5 for `dlo train` and `dlo eval`, resampled to --control-hz; prints the
    freeze and straight-line references' scores."""
    with Bars(run.json) as bars:
        summary = run_import(run.spec(), run.overwrite, bars, signal_token())
    emit_summary(summary, run.json, "dlo import")
