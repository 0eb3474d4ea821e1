"""`dlo online`: the paper's Algorithm 1 — learn the model online, exploring with MPC."""

from __future__ import annotations

from dlocli.cli.common import AcceptChangesFlag, ResumeFlag, emit_summary, handle_errors
from dlocli.cli.flags import RunFlags, spec_flags
from dlocli.cli.progress import Bars
from dlocli.events import Event
from dlocli.processes import signal_token
from dlocli.runs.online import OnlineSpec, resume_online, start_online


@handle_errors
@spec_flags(OnlineSpec)
def online(
    run: RunFlags,
    resume: ResumeFlag = None,
    accept_changes: AcceptChangesFlag = False,
) -> None:
    """Learn the dynamics model online with MPC (paper Algorithm 1); plot the learning curve.

    With no flags this is the paper's setting (K=20, E=50, N=50, T=200, H=5, lr 1e-4), whose
    50 epochs over all the data per update cost more each iteration; `--schedule steps
    --workers 2` keeps each update's cost fixed (examples/online_paper; timings in
    docs/results.md). For a CPU demo in minutes, see the README's first command.
    """
    run.refuse_with_resume(resume)
    with Bars(run.json, _describe) as bars:
        if resume is not None:
            summary = resume_online(resume, run.overrides, bars, accept_changes, signal_token())
        else:
            spec = run.spec()
            summary = start_online(spec, run.overwrite, bars, signal_token())
    summary = {k: v for k, v in summary.items() if k not in ("curve", "offline_curve")} | {
        "curve": [(c["transitions"], round(c["final_error_mm_mean"], 1)) for c in summary["curve"]]
    }
    emit_summary(summary, run.json, "dlo online")


def _describe(event: Event) -> str:
    """Beside the bars of iterations, the random episodes, model updates (epochs or gradient
    steps, as the schedule counts them; each update restarts its bar) and trials."""
    values = event.values
    if "running" in values:  # iteration k starts: k - 1 are done
        return f"running {values['running']}"
    if event.unit == "random":
        return "initial episodes"
    if "val_loss" in values:
        early = "stopped early, best " if values["stopped_early"] else ""
        return f"{early}val loss {values['val_loss']:.4f}"
    if "final_error_mm" in values:
        return f"final error {values['final_error_mm']:.1f} mm"
    return ""
