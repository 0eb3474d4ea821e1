"""`dlo online`: the paper's Algorithm 1 — learn the model online, exploring with MPC."""

from __future__ import annotations

from typing import Any

from rich.progress import (
    BarColumn,
    MofNCompleteColumn,
    Progress,
    TextColumn,
    TimeElapsedColumn,
    TimeRemainingColumn,
)

from dlocli.cli.common import (
    AcceptChangesFlag,
    ResumeFlag,
    emit_summary,
    handle_errors,
    progress_bars,
)
from dlocli.cli.flags import RunFlags, spec_flags
from dlocli.runs.online import OnlineSpec as S


@handle_errors
@spec_flags(
    S,
    ["iters", "trials", "task.episode_steps", "fit.schedule", "fit.epochs", "fit.update_steps",
     "initial_episodes", "mpc.horizon",
     "fit.lr", "model.name", "model.hidden", "model.velocity_input", "task.goal", "task.name",
     "task.shapes", "backend.name", "fit.device", "noise_probability", "noise_std", "workers",
     "fit.mirror", "offline", "seed", "out"],
)  # fmt: skip
def online(
    run: RunFlags,
    resume: ResumeFlag = None,
    accept_changes: AcceptChangesFlag = False,
) -> None:
    """Learn the dynamics model online with MPC (paper Algorithm 1); plot the learning curve.

    With no flags this is the paper's setting (K=20, E=50, N=50, T=200, H=5, lr 1e-4); its 50
    epochs over all the data per update take ~45 hours of training on a laptop CPU. With
    `--schedule steps --workers 2` the same run took 1 h 48 min on 2 CPU cores
    (examples/online_paper). For a CPU demo in minutes, see the README's first command.
    """
    from dlocli.runs.online import resume_online, start_online

    run.refuse_with_resume(resume)
    with progress_bars(*_bar_columns(), quiet=run.json) as bars:
        callback = _OnlineProgress(bars).update
        if resume is not None:
            summary = resume_online(resume, run.overrides, callback, accept_changes)
        else:
            spec = run.spec()
            summary = start_online(spec, run.overwrite, callback)
    summary = {k: v for k, v in summary.items() if k not in ("curve", "offline_curve")} | {
        "curve": [(c["transitions"], round(c["final_error_mm_mean"], 1)) for c in summary["curve"]]
    }
    emit_summary(summary, run.json, "dlo online")


def _bar_columns() -> tuple[Any, ...]:
    """Columns of the nested bars (iterations, trials, epochs), with ETA; new for each run,
    as columns cache what they drew."""
    return (
        TextColumn("{task.description:<10}"),
        BarColumn(),
        MofNCompleteColumn(),
        TextColumn("{task.fields[info]}"),
        TimeElapsedColumn(),
        TimeRemainingColumn(),
    )


class _OnlineProgress:
    """The online loop's events shown on nested bars: iterations, trials, epochs."""

    def __init__(self, bars: Progress) -> None:
        self.bars = bars
        self.tasks: dict[str, Any] = {}

    def _bar(self, name: str, total: int | None) -> Any:
        if name not in self.tasks:
            self.tasks[name] = self.bars.add_task(name, total=total, info="")
        return self.tasks[name]

    def update(self, event: str, info: dict[str, Any]) -> None:
        self.bars.start()  # on the first event: bad input never shows a bar
        if event == "iteration":  # iteration k starts: k - 1 are done
            self.bars.update(
                self._bar("iteration", info["total"]),
                completed=info["iteration"] - 1,
                info=f"running {info['iteration']}",
            )
            for name in ("trial", "epoch"):
                if name in self.tasks:
                    self.bars.reset(self.tasks[name])
        elif event == "initial":
            self.bars.update(self._bar("random", info["total"]), completed=info["episode"])
        elif event == "iteration done":
            self.bars.update(self._bar("iteration", info["total"]), completed=info["iteration"],
                             info="")  # fmt: skip
        elif event == "epoch" and "batch" not in info:
            early = "stopped early, best " if info.get("stopped_early") else ""
            self.bars.update(
                self._bar("epoch", info.get("epochs")),
                total=info.get("epochs"),
                completed=info["epoch"],
                info=f"{early}val loss {info.get('val_loss', float('nan')):.4f}",
            )
        elif event == "trial":
            self.bars.update(
                self._bar("trial", info.get("total")),
                completed=info["trial"],
                info=f"final error {info['final_error_mm']:.1f} mm",
            )
