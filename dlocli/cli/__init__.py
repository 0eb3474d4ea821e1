"""The `dlo` command: one Typer app composed of one module per command.

The CLI is thin: parse flags -> resolve the run spec -> call the library -> print a summary.
"""

from __future__ import annotations

import ast
import importlib
import importlib.util
import sys
import textwrap
import typing
from collections.abc import Callable, Iterator, Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any

import typer
import typer.main
from typer._click import _textwrap as _click_textwrap
from typer.core import TyperCommand, TyperGroup, TyperOption

from dlocli import __version__
from dlocli.cli.common import print_error
from dlocli.processes import handle_stop_signals
from dlocli.threads import fit_this_process

if TYPE_CHECKING:  # Typer carries its own Click; these names are for annotations only
    from typer._click import Context, HelpFormatter

# --help wraps at spaces only: a value such as optimizer=gauss-newton is copied from it, so it
# must not be split at its hyphen (Typer's Click wraps with textwrap, which splits words at
# hyphens by its wordsep_re; its whitespace-only pattern is textwrap's own)
_click_textwrap.TextWrapper.wordsep_re = textwrap.TextWrapper.wordsep_simple_re

# (command name, "module:function"); a command's module is imported only when that command
# runs or shows its help, so `dlo --help` and `dlo --version` import no torch or simulator.
COMMANDS = [
    ("list", "dlocli.cli.listing:list_plugins"),
    ("goal", "dlocli.cli.goal:goal"),
    ("collect", "dlocli.cli.collect:collect"),
    ("import", "dlocli.cli.importing:import_recordings"),
    ("track", "dlocli.cli.track:track"),
    ("calibrate", "dlocli.cli.calibrate:calibrate"),
    ("train", "dlocli.cli.train:train"),
    ("eval", "dlocli.cli.eval:evaluate"),
    ("control", "dlocli.cli.control:control"),
    ("online", "dlocli.cli.online:online"),
    ("bench", "dlocli.cli.bench:bench"),
    ("export", "dlocli.cli.export:export"),
    ("serve", "dlocli.cli.serve:serve"),
]
#: other names of a command: they run it, --help lists only the command
ALIASES = {"benchmark": "bench"}


class _Command(TyperCommand):
    """A command whose options' help may be written when --help is shown: the function's
    ``lazy_help`` maps a parameter to a function of no arguments returning its help (text
    that needs imports the command itself does not)."""

    lazy_help: Mapping[str, Callable[[], str]] = {}

    def format_options(self, ctx: Context, formatter: HelpFormatter) -> None:
        for param in self.params:
            if param.name in self.lazy_help:
                param.help = self.lazy_help[param.name]()
        super().format_options(ctx, formatter)


def _plain_metavars(command: TyperCommand) -> None:
    """Click's metavars (PATH, INTEGER, ...) where an option sets none: Typer's would show
    Python types (``<list[str]>``)."""
    from enum import Enum

    from dlocli.cli.flags import METAVARS, strip_none

    for param in command.params:
        if not isinstance(param, TyperOption) or param.metavar is not None or param.is_flag:
            continue
        kind = strip_none(param.type_descriptor.annotation)
        kind = typing.get_args(kind)[0] if typing.get_origin(kind) is list else kind
        if isinstance(kind, type) and issubclass(kind, Enum):
            param.metavar = "|".join(str(member.value) for member in kind)
        else:
            param.metavar = METAVARS.get(kind) or "VALUE"


class _LazyCommands(Mapping[str, TyperCommand]):
    """The commands by name, each built from its module on first use."""

    def __init__(self, targets: dict[str, str]) -> None:
        self.targets = targets
        self.built: dict[str, TyperCommand] = {}

    def __getitem__(self, name: str) -> TyperCommand:
        if name not in self.built:
            module_name, _, attr = self.targets[name].partition(":")
            function = getattr(importlib.import_module(module_name), attr)
            one = typer.Typer(add_completion=False, pretty_exceptions_enable=False,
                              rich_markup_mode=None)  # fmt: skip
            one.command(name, cls=_Command)(function)
            command = typer.main.get_command(one)
            command.lazy_help = getattr(function, "lazy_help", {})
            _plain_metavars(command)
            self.built[name] = command
        return self.built[name]

    def __iter__(self) -> Iterator[str]:
        return iter(self.targets)

    def __len__(self) -> int:
        return len(self.targets)


def _first_docstring_line(target: str) -> str:
    """The first line of a command function's docstring, read from its source file without
    importing the module."""
    module_name, _, attr = target.partition(":")
    origin = importlib.util.find_spec(module_name).origin
    tree = ast.parse(Path(origin).read_text(encoding="utf-8"))
    function = next(
        node for node in tree.body if isinstance(node, ast.FunctionDef) and node.name == attr
    )
    return (ast.get_docstring(function) or "").strip().splitlines()[0]


def _short_help(text: str, limit: int) -> str:
    """The first sentence of ``text``, cut at a word boundary to ``limit`` characters with
    "..." (the listing's short help, as Click writes it)."""
    words = text.split()
    sentence: list[str] = []
    for word in words:
        sentence.append(word)
        if word.endswith("."):
            break
    if len(" ".join(sentence)) <= limit:
        return " ".join(sentence)
    while sentence and len(" ".join(sentence)) + len("...") > limit:
        sentence.pop()
    return " ".join(sentence) + "..."


def all_commands() -> list[tuple[str, str]]:
    """The built-in commands, then those plugins add through the ``dlocli.commands``
    entry-point group (``name = module:function``, a Typer command function); a plugin cannot
    replace a built-in."""
    from importlib.metadata import entry_points

    built_in = dict(COMMANDS)
    added = [(ep.name, ep.value) for ep in entry_points(group="dlocli.commands")]
    return [*COMMANDS, *((name, target) for name, target in added if name not in built_in)]


class _LazyGroup(TyperGroup):
    """The root group: commands load on first use; its help lists them from their sources."""

    def __init__(self, **attrs: Any) -> None:
        super().__init__(**attrs)
        self.listed = all_commands()
        targets = dict(self.listed)
        self.commands = _LazyCommands(
            {**targets, **{alias: targets[name] for alias, name in ALIASES.items()}}
        )

    def format_commands(self, ctx: Context, formatter: HelpFormatter) -> None:
        limit = formatter.width - 6 - max(len(name) for name, _ in self.listed)
        rows = [
            (name, _short_help(_first_docstring_line(target), limit))
            for name, target in self.listed
        ]
        with formatter.section("Commands"):
            formatter.write_dl(rows)


app = typer.Typer(
    name="dlo",
    cls=_LazyGroup,
    help="Learn and control the 3D shape of deformable linear objects (cables, ropes).",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
    invoke_without_command=True,
    # plain help: the rich panels of this Typer/Click show flags as `--json <bool>`
    rich_markup_mode=None,
)


@app.callback()
def _root(
    ctx: typer.Context,
    version: bool = typer.Option(False, "--version", help="Print dlocli's version and exit."),
) -> None:
    """Learn and control the 3D shape of deformable linear objects (cables, ropes)."""
    if version:
        typer.echo(f"dlocli {__version__}")
        raise typer.Exit(0)
    if ctx.invoked_subcommand is None:
        typer.echo(ctx.get_help())
        raise typer.Exit(0)


def main() -> None:
    """The `dlo` entry point: SIGTERM handled like Ctrl-C, usage errors as one line."""
    fit_this_process()  # before any command imports torch

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
