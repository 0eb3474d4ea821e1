"""`dlo track`: recorded point clouds of a cable into a marker dataset."""

from __future__ import annotations

from dlocli.cli.common import emit_summary, handle_errors
from dlocli.cli.flags import RunFlags, spec_flags
from dlocli.cli.progress import Bars
from dlocli.events import Began, Event
from dlocli.processes import signal_token
from dlocli.tracking.spec import TrackSpec


@handle_errors
@spec_flags(TrackSpec)
def track(
    run: RunFlags,
) -> None:
    """Track the cable through --source's recorded clouds (.npz frame sequences or ROS 2 bags
    of PointCloud2, one per episode, train/ and eval/) into OUT/dataset.h5 of --markers
    markers for `dlo train` and `dlo eval`; the tracker's options through --spec
    (tracker.*)."""
    from dlocli.runs.track import run_track

    with Bars(run.json, _describe) as bars:
        summary = run_track(run.spec(), run.overwrite, bars, signal_token())
    emit_summary(summary, run.json, "dlo track")


def _describe(event: Event) -> str:
    """A tracked episode: its name, split, visible share and time per frame."""
    if isinstance(event, Began):
        return ""
    values = event.values
    return (f"{values['split']}/{values['episode']}  visible {values['visible']:.0%}  "
            f"{values['ms_per_frame']:.1f} ms/frame")  # fmt: skip
