"""`dlo bench` (alias `dlo benchmark`): agents x seeds under one transition budget."""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Annotated, Any

import typer

from dlocli.bench import BenchSpec as S
from dlocli.cli.common import (
    JsonFlag,
    OverwriteFlag,
    SpecFile,
    VelocityInputFlag,
    build_spec,
    console,
    handle_errors,
)
from dlocli.cli.common import opt_help as h


@handle_errors
def bench(
    agents: Annotated[str | None, typer.Option(help=h(S, "agents") + " Comma-separated.")] = None,
    budget: Annotated[int | None, typer.Option(help=h(S, "budget"))] = None,
    seeds: Annotated[int | None, typer.Option(help=h(S, "seeds"))] = None,
    goals: Annotated[str | None, typer.Option(help=h(S, "task.goal"))] = None,
    task: Annotated[str | None, typer.Option(help=h(S, "task.name"))] = None,
    backend: Annotated[str | None, typer.Option(help=h(S, "backend.name"))] = None,
    steps: Annotated[int | None, typer.Option(help=h(S, "task.episode_steps"))] = None,
    evals: Annotated[int | None, typer.Option(help=h(S, "evals"))] = None,
    eval_trials: Annotated[int | None, typer.Option(help=h(S, "eval_trials"))] = None,
    hidden: Annotated[int | None, typer.Option(help=h(S, "model.hidden"))] = None,
    velocity_input: VelocityInputFlag = None,
    epochs: Annotated[int | None, typer.Option(help=h(S, "fit.epochs"))] = None,
    transfer: Annotated[
        bool | None, typer.Option("--transfer/--no-transfer", help=h(S, "transfer"))
    ] = None,
    executor: Annotated[str | None, typer.Option(help=h(S, "executor"))] = None,
    ray_address: Annotated[str | None, typer.Option(help=h(S, "ray_address"))] = None,
    workers: Annotated[int | None, typer.Option(help=h(S, "workers"))] = None,
    seed: Annotated[int | None, typer.Option(help=h(S, "seed"))] = None,
    out: Annotated[Path | None, typer.Option(help=h(S, "out"))] = None,
    resume: Annotated[
        Path | None,
        typer.Option(help="Run the missing jobs of this bench directory (finished jobs are kept)."),
    ] = None,
    report: Annotated[
        list[Path] | None,
        typer.Option(
            help="Redraw figures and table from this run's results.csv (repeat to merge runs "
            "into the first)."
        ),
    ] = None,
    spec_file: SpecFile = None,
    overwrite: OverwriteFlag = False,
    json_out: JsonFlag = False,
) -> None:
    """Compare agents' sample efficiency under one transition budget (paper Figs. 4-7).

    Writes OUT/results.csv, summary.md/json and plots/. A small CPU bench (see
    examples/bench_small.yaml for the agents' sizes):

        dlo bench --spec examples/bench_small.yaml --out runs/bench-small
    """
    from dlocli.bench import report_bench, resume_bench, start_bench

    if report:
        summary = report_bench(report)
    else:
        overrides: dict[str, Any] = {
            "agents": _names(agents),
            "budget": budget,
            "seeds": seeds,
            "task.goal": goals,
            "task.name": task,
            "backend.name": backend,
            "task.episode_steps": steps,
            "evals": evals,
            "eval_trials": eval_trials,
            "model.hidden": hidden,
            # every agent gets the same information: the model's input, the RL observation
            "model.velocity_input": velocity_input,
            "task.observe_velocity": velocity_input,
            "fit.epochs": epochs,
            "transfer": transfer,
            "executor": executor,
            "ray_address": ray_address,
            "workers": workers,
            "seed": seed,
            "out": out,
        }
        progress = _quiet if json_out else _print_progress
        if resume is not None:
            summary = resume_bench(resume, overrides, progress)
        else:
            summary = start_bench(build_spec(S, spec_file, overrides), overwrite, progress)
    _emit(summary, json_out)


def _names(agents: str | None) -> list[str] | None:
    if agents is None:
        return None
    return [name.strip() for name in agents.split(",") if name.strip()]


def _quiet(event: str, info: dict[str, Any]) -> None:
    return None


def _print_progress(event: str, info: dict[str, Any]) -> None:
    if event == "start":
        kept = info["total"] - info["todo"]
        console.print(f"bench: {info['todo']} job(s) to run, {kept} finished job(s) kept")
    elif event == "job":
        console.print(f"  {info['job']} done in {info['seconds']:.0f} s")
    elif event == "failed":
        console.print(f"  [red]{info['error']}[/red]", soft_wrap=True)


def _emit(summary: dict[str, Any], as_json: bool) -> None:
    if as_json:
        sys.stdout.write(json.dumps(summary, default=str) + "\n")
        return
    from dlocli.bench_plots import markdown_table

    sys.stdout.write(markdown_table(summary["table"]))
    sys.stdout.write(f"results: {summary['out']}  figures: {len(summary['figures'])}\n")
