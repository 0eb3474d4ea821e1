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
    invoke_without_command=True,
    # plain help: the rich panels of this Typer/Click show flags as `--json <bool>`
    rich_markup_mode=None,
)

# (command name, "module:function"); each command module imports its heavy libraries (torch,
# simulators) inside the function, so `dlo --help` stays fast.
COMMANDS = [
    ("list", "dlocli.cli.listing:list_plugins"),
    ("goal", "dlocli.cli.goal:goal"),
    ("collect", "dlocli.cli.collect:collect"),
    ("import", "dlocli.cli.importing:import_recordings"),
    ("train", "dlocli.cli.train:train"),
    ("eval", "dlocli.cli.eval:evaluate"),
    ("control", "dlocli.cli.control:control"),
    ("online", "dlocli.cli.online:online"),
    ("bench", "dlocli.cli.bench:bench"),
    ("benchmark", "dlocli.cli.bench:bench"),
    ("export", "dlocli.cli.export:export"),
]


def _register() -> None:
    for name, target in COMMANDS:
        module_name, _, attr = target.partition(":")
        app.command(name)(getattr(importlib.import_module(module_name), attr))


@app.callback()
def _root(
    ctx: typer.Context,
    version: bool = typer.Option(False, "--version", help="Print dlocli's version and exit."),
) -> None:
    """Learn and control the 3D shape of deformable linear objects (cables, ropes)."""
    if version:
        from dlocli import __version__

        typer.echo(f"dlocli {__version__}")
        raise typer.Exit(0)
    if ctx.invoked_subcommand is None:
        typer.echo(ctx.get_help())
        raise typer.Exit(0)


_register()


def main() -> None:
    """The `dlo` entry point: SIGTERM handled like Ctrl-C, usage errors as one line."""
    import sys

    from dlocli.cli.common import print_error
    from dlocli.processes import handle_stop_signals

    # Typer vendors Click; its UsageError is public only as BadParameter's base
    usage_error = next(c for c in typer.BadParameter.__mro__ if c.__name__ == "UsageError")
    handle_stop_signals()
    try:
        code = app(standalone_mode=False)
    except usage_error as exc:
        if exc.ctx is not None and type(exc).__name__ == "NoArgsIsHelpError":
            typer.echo(exc.ctx.get_help())
            sys.exit(0)
        command = exc.ctx.command_path if exc.ctx is not None else "dlo"
        print_error(f"{exc.format_message().rstrip('.')}; see `{command} --help`")
        code = 2
    except typer.Abort:  # Ctrl-C outside a command's own handling
        code = 130
    sys.exit(code if isinstance(code, int) else 0)
