"""`dlo family`: many simulated cables from calibrated rods and a recorded cable's motion."""

from __future__ import annotations

from dlocli.calibration.family import run_family
from dlocli.calibration.spec import FamilySpec
from dlocli.cli.common import emit_summary, handle_errors
from dlocli.cli.flags import RunFlags, spec_flags
from dlocli.cli.progress import Bars
from dlocli.events import Event
from dlocli.processes import signal_token


@handle_errors
@spec_flags(FamilySpec)
def family(run: RunFlags) -> None:
    """Many simulated cables from calibrated rods, driven by recorded cables' motion.

    Draws --cables materials that span and exceed the --calibrated rods' (young_bending,
    density, bending_damping and air_damping each log-uniformly between the smallest
    calibrated value / --widen and the largest * --widen; the rod its --source cable's times
    a factor in --length-scale), drives each rod with its --source cable's recorded
    held-marker motion (moved rigidly, scaled with the rod; with several --source, cable k
    takes source k mod their count), and writes each cable as a marker
    dataset OUT/sim-NNN/dataset.h5 for `dlo train --data` and `dlo eval --data` (one cable
    code per dataset), with its rod (OUT/sim-NNN/rod.yaml, a spec for --spec) and
    OUT/summary.json: each cable's material and the trajectories kept (a trajectory whose
    simulation diverges is dropped and counted; a cable left with fewer than two train
    trajectories, too few for `dlo train` to validate on, is not written)."""
    with Bars(run.json, _describe) as bars:
        summary = run_family(run.spec(), run.overwrite, bars, signal_token())
    if not run.json:
        summary.pop("rows", None)
        summary.pop("span", None)
    emit_summary(summary, run.json, "dlo family")


def _describe(event: Event) -> str:
    """Beside the bar of trajectories, the cable they belong to."""
    return str(event.values.get("cable", ""))
