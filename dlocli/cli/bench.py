"""`dlo bench` (alias `dlo benchmark`): agents x seeds under one transition budget."""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Annotated, Any

import typer

from dlocli.bench.spec import BenchSpec
from dlocli.cli.common import ResumeFlag, handle_errors
from dlocli.cli.flags import RunFlags, parse_options, spec_flags
from dlocli.cli.progress import Bars

OPTION_HELP = (
    "An option of a learning agent, AGENT.KEY=VALUE (a field of its spec), repeatable: "
    "-o sac.gamma=0.99 -o td3.action_noise=0.2."
)


@handle_errors
@spec_flags(BenchSpec)
def bench(
    run: RunFlags,
    option: Annotated[
        list[str] | None,
        typer.Option("--option", "-o", help=OPTION_HELP, metavar="AGENT.KEY=VALUE"),
    ] = None,
    resume: ResumeFlag = None,
    report: Annotated[
        list[Path] | None,
        typer.Option(
            metavar="RUN",
            help="Redraw figures and table from this run's results.csv (repeat to merge runs "
            "into the first).",
        ),
    ] = None,
) -> None:
    """Compare agents' sample efficiency under one transition budget (paper Figs. 4-7).

    Writes OUT/results.csv, summary.md/json and plots/. A small CPU bench (see
    examples/bench_small.yaml for the agents' sizes):

        dlo bench --spec examples/bench_small.yaml --out runs/bench-small
    """
    from dlocli.bench.run import report_bench, resume_bench, start_bench

    run.refuse_with_resume(resume)
    if report:
        summary = report_bench(report)
    else:
        run.overrides |= parse_options(option or [], "options")
        with Bars(run.json) as bars:
            progress = _BenchProgress(bars)
            if resume is not None:
                summary = resume_bench(resume, run.overrides, progress)
            else:
                summary = start_bench(run.spec(), run.overwrite, progress)
    _emit(summary, run.json)


class _BenchProgress:
    """What is to run, then a bar of finished jobs (a line per job in a log)."""

    def __init__(self, bars: Bars) -> None:
        self.bars = bars
        self.done = 0

    def __call__(self, event: str, info: dict[str, Any]) -> None:
        bars = self.bars
        if event == "start":
            kept = info["total"] - info["todo"]
            bars.note(f"bench: {info['todo']} job(s) to run, {kept} finished job(s) kept")
            for job, transitions in info.get("continuing", {}).items():
                bars.note(f"  {job} continues from its checkpoint at {transitions:,} transitions")
            for job, pid in info.get("elsewhere", {}).items():
                bars.note(f"  {job} is running in another process (PID {pid}): left to it")
            bars.begin("job", info["todo"])
        elif event == "job":
            self.done += 1
            bars.update("job", self.done, info=f"{info['job']} took {info['seconds']:.0f} s")
        elif event == "failed":  # one line as it happens; the causes again in the final error
            self.done += 1
            bars.update("job", self.done, info=f"{info['job']} failed: {info['error'][:120]}")


def _emit(summary: dict[str, Any], as_json: bool) -> None:
    if as_json:
        sys.stdout.write(json.dumps(summary, default=str) + "\n")
        return
    from dlocli.bench.report import markdown_table

    sys.stdout.write(markdown_table(summary["table"]))
    sys.stdout.write(f"results: {summary['out']}  figures: {len(summary['figures'])}\n")
