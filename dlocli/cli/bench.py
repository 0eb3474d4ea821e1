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
from dlocli.events import Began, Event
from dlocli.processes import signal_token

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
        with Bars(run.json, _describe) as bars:
            if resume is not None:
                summary = resume_bench(resume, run.overrides, bars, signal_token())
            else:
                summary = start_bench(run.spec(), run.overwrite, bars, signal_token())
    _emit(summary, run.json)


def _describe(event: Event) -> str:
    """What is to run (above the bar of finished jobs), then each finished job (a line per
    job in a log); a failure as it happens, its cause again in the final error."""
    values = event.values
    if isinstance(event, Began):
        kept = values["total"] - (event.total or 0)
        lines = [f"bench: {event.total:g} job(s) to run, {kept:g} finished job(s) kept"]
        for job, transitions in values["continuing"].items():
            lines.append(f"  {job} continues from its checkpoint at {transitions:,} transitions")
        for job, pid in values["elsewhere"].items():
            lines.append(f"  {job} is running in another process (PID {pid}): left to it")
        return "\n".join(lines)
    if "error" in values:
        return f"{values['job']} failed: {values['error'][:120]}"
    return f"{values['job']} took {values['seconds']:.0f} s"


def _emit(summary: dict[str, Any], as_json: bool) -> None:
    if as_json:
        sys.stdout.write(json.dumps(summary, default=str) + "\n")
        return
    from dlocli.bench.report import markdown_table

    sys.stdout.write(markdown_table(summary["table"]))
    sys.stdout.write(f"results: {summary['out']}  figures: {len(summary['figures'])}\n")
