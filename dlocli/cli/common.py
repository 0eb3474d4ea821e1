"""Shared CLI plumbing: error handling, spec resolution, summaries, common options."""

from __future__ import annotations

import functools
import json
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Annotated, Any, TypeVar

import typer
from rich.console import Console
from rich.table import Table

from dlocli.errors import DloError

F = TypeVar("F", bound=Callable[..., Any])
console = Console(stderr=True)

SpecFile = Annotated[
    Path | None,
    typer.Option("--spec", help="Run spec file (YAML or JSON); flags override its fields."),
]
JsonFlag = Annotated[bool, typer.Option("--json", help="Print the summary as JSON on stdout.")]
ResumeFlag = Annotated[
    Path | None,
    typer.Option(
        "--resume",
        help="Continue the stopped run in this directory: its spec.json rules, flags that "
        "contradict it are refused, finished work is kept.",
    ),
]
OverwriteFlag = Annotated[
    bool, typer.Option("--overwrite", help="Allow writing into an existing non-empty --out.")
]


def handle_errors(fn: F) -> F:
    """Turn library errors into one line on stderr and the documented exit code."""

    @functools.wraps(fn)
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        try:
            return fn(*args, **kwargs)
        except DloError as exc:
            console.print(f"[red]error:[/red] {exc}", highlight=False, soft_wrap=True)
            raise typer.Exit(exc.exit_code) from None
        except KeyboardInterrupt:
            console.print("[yellow]interrupted[/yellow]: finished work was saved")
            raise typer.Exit(130) from None

    return wrapper  # type: ignore[return-value]


def emit_summary(summary: dict[str, Any], as_json: bool, title: str) -> None:
    """JSON on stdout with --json, else a small table on stderr-free stdout."""
    if as_json:
        sys.stdout.write(json.dumps(summary, default=str) + "\n")
        return
    table = Table(title=title, show_header=False)
    for key, value in summary.items():
        table.add_row(key, f"{value:.4g}" if isinstance(value, float) else str(value))
    Console().print(table)
