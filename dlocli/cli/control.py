"""`dlo control`: closed-loop shape control to a goal shape through a learned model."""

from __future__ import annotations

from typing import Annotated

import typer

from dlocli.cli.common import emit_summary, handle_errors
from dlocli.cli.flags import RunFlags, parse_options, spec_flags
from dlocli.cli.progress import Bars
from dlocli.events import Began, Event
from dlocli.processes import signal_token
from dlocli.registry import controllers
from dlocli.runs.control import ControlSpec, run_control

OPTION_HELP = "Controller option KEY=VALUE, a field of the --controller's spec; repeatable."


def controller_options_help() -> str:
    """The -o help: every registered controller's options and their defaults, from its spec
    (a plugin's module is imported for it, so only --help calls it)."""
    described = []
    for name in controllers.names():
        spec_cls = controllers.spec_cls(name)
        if spec_cls is not None:
            fields = spec_cls().model_dump(mode="json")
            described.append(f"{name}: " + ", ".join(f"{k}={v}" for k, v in fields.items()))
    return f"{OPTION_HELP} {'; '.join(described)}."


@handle_errors
@spec_flags(ControlSpec)
def control(
    run: RunFlags,
    option: Annotated[
        list[str] | None,
        typer.Option("--option", "-o", help=OPTION_HELP, metavar="KEY=VALUE"),
    ] = None,
) -> None:
    """Drive the rod from a seeded random start to the --goal shape; write OUT/summary.json."""
    run.overrides |= parse_options(option or [], "controller_options")
    spec = run.spec()
    with Bars(run.json, _describe, every={"step": max(spec.task.episode_steps // 10, 1)}) as bars:
        summary = run_control(spec, bars, overwrite=run.overwrite, cancel=signal_token())
    summary.pop("versions", None)
    if "code_picks" in summary and not run.json:  # the table: each re-pick's step and code
        picks = summary["code_picks"]
        summary["code_picks"] = ", ".join(f"{p['step']}: {p['code']}" for p in picks)
    emit_summary(summary, run.json, "dlo control")


def _describe(event: Event) -> str:
    """A step's shape error and the controller's latency."""
    if isinstance(event, Began):
        return ""
    record = event.values
    return f"error {record['shape_error_mm']:7.1f} mm  latency {record['latency_ms']:6.1f} ms"


control.lazy_help = {"option": controller_options_help}  # type: ignore[attr-defined]
