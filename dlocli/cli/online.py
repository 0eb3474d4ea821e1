"""`dlo online`: the paper's Algorithm 1 — learn the model online, exploring with MPC."""

from __future__ import annotations

from typing import Any

from dlocli.cli.common import AcceptChangesFlag, ResumeFlag, emit_summary, handle_errors
from dlocli.cli.flags import RunFlags, spec_flags
from dlocli.cli.progress import Bars
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
    with Bars(run.json) as bars:
        callback = _OnlineProgress(bars)
        if resume is not None:
            summary = resume_online(resume, run.overrides, callback, accept_changes)
        else:
            spec = run.spec()
            summary = start_online(spec, run.overwrite, callback)
    summary = {k: v for k, v in summary.items() if k not in ("curve", "offline_curve")} | {
        "curve": [(c["transitions"], round(c["final_error_mm_mean"], 1)) for c in summary["curve"]]
    }
    emit_summary(summary, run.json, "dlo online")


class _OnlineProgress:
    """Bars for iterations, the random episodes, model updates (epochs or gradient steps, as
    the schedule counts them) and trials; each phase restarts its bar."""

    def __init__(self, bars: Bars) -> None:
        self.bars = bars

    def __call__(self, event: str, info: dict[str, Any]) -> None:
        bars = self.bars
        if event == "iteration":  # iteration k starts: k - 1 are done
            bars.update("iteration", info["iteration"] - 1, info["total"],
                        info=f"running {info['iteration']}")  # fmt: skip
        elif event == "initial":
            bars.update("random", info["episode"], info["total"], info="initial episodes")
        elif event == "iteration done":
            bars.update("iteration", info["iteration"], info["total"])
        elif event == "update":
            bars.begin(info["unit"], info["total"])
        elif event == "validation":
            early = "stopped early, best " if info["stopped_early"] else ""
            loss = f"{early}val loss {info['val_loss']:.4f}"
            bars.update(info["unit"], info["count"], info["total"], info=loss)
        elif event == "trials":
            bars.begin("trial", info["total"], done=info["done"])
        elif event == "trial":
            bars.update("trial", info["trial"], info.get("total"),
                        info=f"final error {info['final_error_mm']:.1f} mm")  # fmt: skip
