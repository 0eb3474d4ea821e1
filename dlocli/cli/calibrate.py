"""`dlo calibrate`: fit a simulated rod's material to a recorded cable's motion."""

from __future__ import annotations

from dlocli.calibration.spec import CalibrateSpec
from dlocli.cli.common import ResumeFlag, emit_summary, handle_errors
from dlocli.cli.flags import RunFlags, spec_flags
from dlocli.cli.progress import Bars
from dlocli.events import Event
from dlocli.processes import signal_token
from dlocli.runs.calibrate import resumed_spec, run_calibration


@handle_errors
@spec_flags(CalibrateSpec)
def calibrate(run: RunFlags, resume: ResumeFlag = None) -> None:
    """Fit the rod's material (--parameters) to the --source cable's train recordings by
    CMA-ES on the DEFORM replay score; write OUT/calibrated.yaml (a spec for any command's
    --spec: the rod, the recordings' control period and where their markers sit for
    --observation markers) and OUT/report.{json,md} (eval score before and after, next to
    DEFORM's published physics rows and the freeze reference).

    Grippers follow the innermost held marker of each end (the end markers with rigid
    clamps); the rod is the cable between them, with the cable's mass per length.
    The replays of each generation run in local processes (`--workers`) or as Ray tasks
    (`--executor ray`, on the cluster at `--ray-address`); the same seed fits the same
    material on either. `--resume OUT` continues after the last finished generation
    (`--generations` may change there: more extends the search; so may where replays run)."""
    run.refuse_with_resume(resume)
    spec = resumed_spec(resume, run.overrides) if resume is not None else run.spec()
    with Bars(run.json, _describe) as bars:
        summary = run_calibration(
            spec, run.overwrite, bars, resume=resume is not None, cancel=signal_token()
        )
    summary.pop("eval_per_recording", None)
    emit_summary(summary, run.json, "dlo calibrate")


def _describe(event: Event) -> str:
    """Beside the bar of generations, the best train score so far."""
    if "best_cm" in event.values:
        return f"best train score {event.values['best_cm']:.3f} cm"
    return ""
