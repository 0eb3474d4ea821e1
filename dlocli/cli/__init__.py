"""The `dlo` command: one Typer app composed of one module per command.

The CLI is thin: parse flags -> resolve the run spec -> call the library -> print a summary.
"""

from __future__ import annotations

import ast
import importlib
import importlib.util
import sys
import typing
from collections.abc import Callable, Iterator, Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any

import typer
import typer.main
from typer.core import TyperCommand, TyperGroup, TyperOption

from dlocli import __version__
from dlocli.cli.common import print_error
from dlocli.errors import BadInput
from dlocli.processes import handle_stop_signals
from dlocli.threads import fit_this_process

if TYPE_CHECKING:
    from importlib.metadata import EntryPoint

#: a hyphen while Click wraps --help: a character its wrapping never splits a word at
_HELD_HYPHEN = "\u2011"


class _HelpFormatter(typer.Context.formatter_class):  # type: ignore[valid-type,misc]
    """--help wrapped at spaces only: a value such as optimizer=gauss-newton is copied from
    it, so it must not be split at its hyphen (Click wraps with textwrap, which splits words
    at hyphens). Hyphens are held as a one-character stand-in while Click wraps, so the lines
    break where they would at spaces alone."""

    def write_dl(self, rows: Any, col_max: int = 30, col_spacing: int = 2) -> None:
        start = len(self.buffer)
        held = [(first, second.replace("-", _HELD_HYPHEN)) for first, second in rows]
        super().write_dl(held, col_max, col_spacing)
        self.buffer[start:] = [s.replace(_HELD_HYPHEN, "-") for s in self.buffer[start:]]

    def write_text(self, text: str) -> None:
        start = len(self.buffer)
        super().write_text(text.replace("-", _HELD_HYPHEN))
        self.buffer[start:] = [s.replace(_HELD_HYPHEN, "-") for s in self.buffer[start:]]


class _Context(typer.Context):
    """A command's context: its --help through :class:`_HelpFormatter`."""

    formatter_class = _HelpFormatter


# (command name, "module:function"); a command's module is imported only when that command
# runs or shows its help, so `dlo --help` and `dlo --version` import no torch or simulator.
COMMANDS = [
    ("list", "dlocli.cli.listing:list_plugins"),
    ("goal", "dlocli.cli.goal:goal"),
    ("collect", "dlocli.cli.collect:collect"),
    ("sample", "dlocli.cli.sample:sample"),
    ("import", "dlocli.cli.importing:import_recordings"),
    ("track", "dlocli.cli.track:track"),
    ("calibrate", "dlocli.cli.calibrate:calibrate"),
    ("family", "dlocli.cli.family:family"),
    ("train", "dlocli.cli.train:train"),
    ("eval", "dlocli.cli.eval:evaluate"),
    ("adapt", "dlocli.cli.adapt:adapt"),
    ("control", "dlocli.cli.control:control"),
    ("online", "dlocli.cli.online:online"),
    ("bench", "dlocli.cli.bench:bench"),
    ("export", "dlocli.cli.export:export"),
    ("view", "dlocli.cli.view:view"),
    ("serve", "dlocli.cli.serve:serve"),
    ("keys", "dlocli.cli.keys:keys"),
]
#: other names of a command: they run it, --help lists only the command
ALIASES = {"benchmark": "bench"}


class _Command(TyperCommand):
    """A command whose options' help may be written when --help is shown: the function's
    ``lazy_help`` maps a parameter to a function of no arguments returning its help (text
    that needs imports the command itself does not)."""

    lazy_help: Mapping[str, Callable[[], str]] = {}
    context_class = _Context

    def format_options(self, ctx: typer.Context, formatter: _HelpFormatter) -> None:
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


def _build_command(name: str, target: str) -> TyperCommand:
    """The command ``name`` from its function ``target`` ("module:function")."""
    module_name, _, attr = target.partition(":")
    function = getattr(importlib.import_module(module_name), attr)
    one = typer.Typer(add_completion=False, pretty_exceptions_enable=False,
                      rich_markup_mode=None)  # fmt: skip
    one.command(name, cls=_Command)(function)
    command = typer.main.get_command(one)
    command.lazy_help = getattr(function, "lazy_help", {})
    _plain_metavars(command)
    return command


class _LazyCommands(Mapping[str, TyperCommand]):
    """The commands by name, each built from its module on first use; a plugin's that cannot
    be built is BadInput naming the plugin, its entry point and the problem."""

    def __init__(self, targets: dict[str, str], plugins: Mapping[str, str]) -> None:
        self.targets = targets
        self.plugins = plugins  # plugin command -> where it comes from
        self.built: dict[str, TyperCommand] = {}

    def __getitem__(self, name: str) -> TyperCommand:
        if name not in self.built:
            try:
                self.built[name] = _build_command(name, self.targets[name])
            except Exception as exc:  # whatever a plugin's module raises on import
                if name not in self.plugins:  # a built-in's failure is dlocli's bug: traceback
                    raise
                raise BadInput(
                    f"{self.plugins[name]} is broken: {type(exc).__name__}: {exc}; fix or "
                    "reinstall that package, or uninstall it"
                ) from None
        return self.built[name]

    def __iter__(self) -> Iterator[str]:
        return iter(self.targets)

    def __len__(self) -> int:
        return len(self.targets)


def _first_docstring_line(target: str) -> str:
    """The first line of a command function's docstring, read from its source file without
    importing the module ("" where it has none, or is not a ``def`` of a source file);
    ValueError naming the problem where the module or the function cannot be found."""
    module_name, _, attr = target.partition(":")
    if not module_name or not attr.isidentifier():
        raise ValueError(f"{target!r} is not 'module:function'")
    spec = importlib.util.find_spec(module_name)
    if spec is None:
        raise ValueError(f"no module named {module_name!r}")
    if spec.origin is None or not spec.origin.endswith(".py"):
        return ""  # compiled, or a namespace package: no source to read
    tree = ast.parse(Path(spec.origin).read_text(encoding="utf-8"), filename=spec.origin)
    for node in tree.body:
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)) and node.name == attr:
            return ((ast.get_docstring(node) or "").strip().splitlines() or [""])[0]
    bound = _other_names(tree)
    if attr in bound or "*" in bound:
        return ""  # bound by an import or an assignment: known only by importing it
    raise ValueError(f"module {module_name} has no function {attr!r}")


def _other_names(tree: ast.Module) -> set[str]:
    """Names a module binds at its top level other than by ``def`` ("*": a star import)."""
    names: set[str] = set()
    for node in tree.body:
        if isinstance(node, (ast.Import, ast.ImportFrom)):
            names |= {(a.asname or a.name).partition(".")[0] for a in node.names}
        elif isinstance(node, ast.ClassDef):
            names.add(node.name)
        elif isinstance(node, (ast.Assign, ast.AnnAssign, ast.AugAssign)):
            targets = node.targets if isinstance(node, ast.Assign) else [node.target]
            names |= {n.id for t in targets for n in ast.walk(t) if isinstance(n, ast.Name)}
    return names


def _listed_help(name: str, target: str, plugins: Mapping[str, str]) -> str:
    """The help line of command ``name`` in `dlo --help`. A plugin's that cannot be read is
    listed as broken, with a warning on stderr naming the plugin, its entry point and the
    problem: one broken plugin hides no other command."""
    if name not in plugins:
        return _first_docstring_line(target)
    try:
        return _first_docstring_line(target)
    except Exception as exc:  # a plugin's package may raise anything on import
        problem = str(exc) if isinstance(exc, ValueError) else f"{type(exc).__name__}: {exc}"
        sys.stderr.write(" ".join(f"warning: {plugins[name]} is broken: {problem}".split()))
        sys.stderr.write("\n")
        return f"BROKEN plugin command: `dlo {name}` says why"


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


def plugin_commands() -> list[EntryPoint]:
    """The commands plugins add through the ``dlocli.commands`` entry-point group
    (``name = module:function``, a Typer command function); a plugin cannot replace a
    built-in."""
    from importlib.metadata import entry_points

    built_in = dict(COMMANDS)
    return [ep for ep in entry_points(group="dlocli.commands") if ep.name not in built_in]


def _plugin_origin(ep: EntryPoint) -> str:
    """Where a plugin command comes from: its package and its entry point."""
    dist = getattr(ep, "dist", None)  # set where the entry point came from a distribution
    package = dist.name if dist is not None else "an unknown package"
    return (
        f"plugin command '{ep.name}' (package {package}, entry point dlocli.commands: "
        f"{ep.name} = {ep.value})"
    )


class _LazyGroup(TyperGroup):
    """The root group: commands load on first use; its help lists them from their sources."""

    context_class = _Context

    def __init__(self, **attrs: Any) -> None:
        super().__init__(**attrs)
        plugins = plugin_commands()
        self.listed = [*COMMANDS, *((ep.name, ep.value) for ep in plugins)]
        self.plugins = {ep.name: _plugin_origin(ep) for ep in plugins}
        targets = dict(self.listed)
        self.commands = _LazyCommands(
            {**targets, **{alias: targets[name] for alias, name in ALIASES.items()}},
            self.plugins,
        )

    def format_commands(self, ctx: typer.Context, formatter: _HelpFormatter) -> None:
        limit = formatter.width - 6 - max(len(name) for name, _ in self.listed)
        rows = [
            (name, _short_help(_listed_help(name, target, self.plugins), limit))
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
    except BadInput as exc:  # a broken plugin command, found as it is looked up
        print_error(str(exc))
        code = exc.exit_code
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
