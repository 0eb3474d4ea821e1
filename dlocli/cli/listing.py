"""`dlo list`: what is registered (backends, tasks, models, controllers)."""

from __future__ import annotations

from typing import Annotated

import typer
from rich.console import Console
from rich.table import Table

from dlocli import registry
from dlocli.cli.common import handle_errors


@handle_errors
def list_plugins(
    json_out: Annotated[bool, typer.Option("--json", help="Print as JSON.")] = False,
) -> None:
    """List registered backends, tasks, models and controllers."""
    import json

    kinds = {
        "backends": registry.backends,
        "tasks": registry.tasks,
        "models": registry.models,
        "controllers": registry.controllers,
    }
    if json_out:
        print(json.dumps({k: {n: _what(k, r, n) for n in r.names()} for k, r in kinds.items()}))
        return
    table = Table(title="dlocli registry")
    table.add_column("kind")
    table.add_column("name")
    table.add_column("what")
    for kind, reg in kinds.items():
        for name in reg.names():
            table.add_row(kind, name, _what(kind, reg, name))
    Console().print(table)


def _what(kind: str, reg: registry.Registry, name: str) -> str:
    """The entry's summary; a backend's planner defaults after it (what its runs plan with)."""
    summary = reg.summary(name)
    if kind != "backends":
        return summary
    defaults = reg.facts(name).planner_defaults
    for planner, options in defaults.items():
        fields = ", ".join(f"{field} {_spelled(value)}" for field, value in options.items())
        summary += f"; {planner} plans with {fields} unless a run sets them"
    return summary


def _spelled(value: float | bool) -> str:
    """An option's value as a spec file spells it (true/false, 32, 0.001)."""
    return str(value).lower() if isinstance(value, bool) else f"{value:g}"
