"""Shared CLI plumbing: error handling, spec resolution, summaries, common options."""

from __future__ import annotations

import errno
import functools
import json
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Annotated, Any, NoReturn, TypeVar

import typer
from rich.console import Console
from rich.markup import escape
from rich.table import Table

from dlocli.errors import DloError
from dlocli.processes import Terminated, pending_stop, raise_if_stopped, stop_handled

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
AcceptChangesFlag = Annotated[
    bool,
    typer.Option(
        "--accept-changes",
        help="With --resume: continue although spec.json or an input file changed since the "
        "run started (the run directory then no longer describes one run exactly).",
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
            result = fn(*args, **kwargs)
            raise_if_stopped()  # a Ctrl-C a library swallowed still ends in exit 130
            return result
        except DloError as exc:
            print_error(str(exc))
            raise typer.Exit(exc.exit_code) from None
        except KeyboardInterrupt as exc:
            _report_stop(isinstance(exc, Terminated))
        except Exception as exc:
            stop = pending_stop()
            if stop is not None:  # the error followed a stop (a worker pool broken by Ctrl-C)
                _report_stop(stop is Terminated)
            if not isinstance(exc, OSError):
                raise
            print_error(os_error_line(exc))
            raise typer.Exit(2 if is_path_error(exc) else 1) from None

    return wrapper  # type: ignore[return-value]


#: longest error line printed: a message quoting a huge path or value keeps its start (what)
#: and its end (the fix)
MAX_ERROR_CHARS = 500


def _report_stop(terminated: bool) -> NoReturn:
    """One line for Ctrl-C or SIGTERM, and its exit code (130 or 143)."""
    stop_handled()
    what = "terminated (SIGTERM)" if terminated else "interrupted"
    console.print(f"[yellow]{what}[/yellow]: finished work was saved")
    raise typer.Exit(143 if terminated else 130) from None


def print_error(line: str) -> None:
    line = " ".join(line.split())  # one line, whatever a library's message held
    if len(line) > MAX_ERROR_CHARS:
        half = MAX_ERROR_CHARS // 2
        line = f"{line[:half]} ... {line[-half:]}"
    console.print(f"[red]error:[/red] {escape(line)}", highlight=False, soft_wrap=True)


#: operating-system errors about a path the user gave (exit 2); others (disk full, ...) exit 1
PATH_ERRORS = (FileNotFoundError, IsADirectoryError, NotADirectoryError, PermissionError)
#: error numbers of a path that cannot name a file (too long, a symlink loop)
PATH_ERRNOS = (errno.ENAMETOOLONG, errno.ELOOP)


def is_path_error(exc: OSError) -> bool:
    return isinstance(exc, PATH_ERRORS) or exc.errno in PATH_ERRNOS


def os_error_line(exc: OSError) -> str:
    """One line naming the path, what the system said and what to do."""
    where = f" {exc.filename}" if exc.filename else ""
    what = exc.strerror or type(exc).__name__
    if is_path_error(exc):
        return f"cannot use{where}: {what}; pass a path you can write to (or read from)"
    if exc.errno == errno.EFBIG:
        return f"{what}{where}: the file size limit stops it; raise `ulimit -f` and run again"
    return f"{what}{where}; free space or fix the file system and run again"


def emit_summary(summary: dict[str, Any], as_json: bool, title: str) -> None:
    """JSON on stdout with --json, else a small table on stderr-free stdout."""
    if as_json:
        sys.stdout.write(json.dumps(summary, default=str) + "\n")
        return
    table = Table(title=title, show_header=False)
    for key, value in summary.items():
        table.add_row(key, f"{value:.4g}" if isinstance(value, float) else str(value))
    Console().print(table)
