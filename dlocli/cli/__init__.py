"""The `dlo` command: one Typer app composed of one module per command.

The CLI is thin: parse flags -> resolve the run spec -> call the library -> print a summary.
"""

from __future__ import annotations

import importlib

import typer

app = typer.Typer(
    name="dlo",
    help="Learn and control the 3D shape of deformable linear objects (cables, ropes).",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
)

# (command name, "module:function"): commands are imported lazily, so `dlo --help` stays fast
# and a missing optional dependency only breaks the command that needs it.
COMMANDS = [
    ("list", "dlocli.cli.listing:list_plugins"),
    ("goal", "dlocli.cli.goal:goal"),
    ("collect", "dlocli.cli.collect:collect"),
    ("control", "dlocli.cli.control:control"),
]


def _register() -> None:
    for name, target in COMMANDS:
        module_name, _, attr = target.partition(":")
        try:
            fn = getattr(importlib.import_module(module_name), attr)
        except (ImportError, AttributeError):
            continue  # a command still being written does not break the others
        app.command(name)(fn)


_register()


def main() -> None:
    app()
