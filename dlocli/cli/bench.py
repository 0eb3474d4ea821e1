"""`dlo bench` (alias `dlo benchmark`): agents x seeds under one transition budget."""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Annotated, Any

import typer
from rich.markup import escape

from dlocli.bench.spec import BenchSpec as S
from dlocli.cli.common import ResumeFlag, console, handle_errors
from dlocli.cli.flags import RunFlags, parse_options, spec_flags

OPTION_HELP = (
    "An option of a learning agent, AGENT.KEY=VALUE (a field of its spec), repeatable: "
    "-o sac.gamma=0.99 -o td3.action_noise=0.2."
)


@handle_errors
@spec_flags(
    S,
    ["agents", "budget", "seeds", "task.goal", "task.name", "task.shapes", "backend.name",
     "task.episode_steps", "evals", "eval_trials", "model.hidden", "model.velocity_input",
     "fit.epochs", "transfer", "executor", "ray_address", "workers", "threads", "seed", "out"],
)  # fmt: skip
def bench(
    run: RunFlags,
    option: Annotated[list[str] | None, typer.Option("--option", "-o", help=OPTION_HELP)] = None,
    resume: ResumeFlag = None,
    report: Annotated[
        list[Path] | None,
        typer.Option(
            help="Redraw figures and table from this run's results.csv (repeat to merge runs "
            "into the first)."
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
        progress = _quiet if run.json else _print_progress
        if resume is not None:
            summary = resume_bench(resume, run.overrides, progress)
        else:
            summary = start_bench(run.spec(), run.overwrite, progress)
    _emit(summary, run.json)


def _quiet(event: str, info: dict[str, Any]) -> None:
    return None


def _print_progress(event: str, info: dict[str, Any]) -> None:
    if event == "start":
        kept = info["total"] - info["todo"]
        console.print(f"bench: {info['todo']} job(s) to run, {kept} finished job(s) kept")
        for job, transitions in info.get("continuing", {}).items():
            console.print(f"  {job} continues from its checkpoint at {transitions:,} transitions")
        for job, pid in info.get("elsewhere", {}).items():
            console.print(f"  {job} is running in another process (PID {pid}): left to it")
    elif event == "job":
        console.print(f"  {info['job']} done in {info['seconds']:.0f} s")
    elif event == "failed":
        console.print(f"  {info['job']} [red]failed[/red]: {escape(info['error'])}", soft_wrap=True)


def _emit(summary: dict[str, Any], as_json: bool) -> None:
    if as_json:
        sys.stdout.write(json.dumps(summary, default=str) + "\n")
        return
    from dlocli.bench.report import markdown_table

    sys.stdout.write(markdown_table(summary["table"]))
    sys.stdout.write(f"results: {summary['out']}  figures: {len(summary['figures'])}\n")
