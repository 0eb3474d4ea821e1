"""Progress of a command, shown wherever it runs.

On an interactive terminal (stdout and stderr both): rich bars on stderr, one per unit counted
(iteration, trial, epoch, step, episode, job), each labelled with its unit. Anywhere else (a
log file, `nohup`, a cluster job, CI): one plain line on stdout per finished unit, with the
time since its phase began and an ETA, so a log shows a run's progress as it happens.

Every command renders its run's :class:`~dlocli.events.Event` through one path: :class:`Bars`
is the run's ``progress`` callback; the command only says how a unit's numbers read
(``describe``) and how often a log gets a line of a unit (``every``).

Nothing is shown before the first unit, so a command refused on bad input prints one line.
With ``quiet`` (``--json``) nothing is shown at all.
"""

from __future__ import annotations

import sys
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any

from rich.console import Console
from rich.progress import (
    BarColumn,
    MofNCompleteColumn,
    Progress,
    ProgressColumn,
    TextColumn,
    TimeElapsedColumn,
)
from rich.text import Text

from dlocli.cli.common import console
from dlocli.events import Began, Event


def eta_seconds(elapsed: float, done: float, total: float | None) -> float | None:
    """Seconds left at the pace of the units finished so far (None before the first)."""
    if not total or done <= 0:
        return None
    return max(elapsed / done * (total - done), 0.0)


def clock(seconds: float | None) -> str:
    """``1:02:03``; ``-:--:--`` when unknown."""
    if seconds is None:
        return "-:--:--"
    s = int(round(seconds))
    return f"{s // 3600}:{s // 60 % 60:02d}:{s % 60:02d}"


class _EtaColumn(ProgressColumn):
    """ETA from the bar's own elapsed time and finished units. Rich's column estimates speed
    from a recent window only, so units longer than that (an iteration) would get no ETA."""

    def render(self, task: Any) -> Text:
        if not task.total or task.completed >= task.total:
            return Text("")
        first = task.fields.get("first", 0)  # units done before this phase's clock started
        left = eta_seconds(task.elapsed or 0.0, task.completed - first, task.total - first)
        return Text(clock(left), style="cyan")


@dataclass
class _Phase:
    """One bar's current phase: when it began, units done, and how often a line is written."""

    started: float = field(default_factory=time.monotonic)
    first: float = 0
    done: float = 0
    total: float | None = None
    every: int | None = 1
    task_id: Any = None


def _no_text(event: Event) -> str:
    return ""


class Bars:
    """The bars of one command; a context manager, and the ``progress`` callback of its run.

    Called with an event, a :class:`~dlocli.events.Began` starts (or restarts, for a new
    phase) the bar counting its unit, with ``describe``'s text for it as a note above; any
    other event moves its unit's bar, ``describe``'s text beside it. Off a terminal a bar
    writes a line every ``every[unit]`` finished units (each one by default, None for none:
    batches within an epoch)."""

    def __init__(
        self,
        quiet: bool,
        describe: Callable[[Event], str] = _no_text,
        every: Mapping[str, int | None] | None = None,
    ) -> None:
        self.quiet = quiet
        self.describe = describe
        self.every = dict(every or {})
        self.live = sys.stdout.isatty() and sys.stderr.isatty()
        self.plain = Console(file=sys.stdout, highlight=False, soft_wrap=True)
        self.bars = Progress(
            TextColumn("{task.description:<10}"),
            BarColumn(),
            MofNCompleteColumn(),
            TextColumn("{task.fields[info]}"),
            TimeElapsedColumn(),
            _EtaColumn(),
            console=console,
            disable=quiet or not self.live,
        )
        self.phases: dict[str, _Phase] = {}

    def __enter__(self) -> Bars:
        return self

    def __exit__(self, *exc: object) -> None:
        if self.bars.live.is_started:  # stopping a bar never shown would print a blank line
            self.bars.stop()

    def __call__(self, event: Event) -> None:
        """Render one event of the run."""
        text = self.describe(event)
        if isinstance(event, Began):
            if text:
                self.note(text)
            self.begin(event.unit, event.total, done=event.done)
        else:
            self.update(event.unit, event.done, event.total, info=text)

    def begin(self, unit: str, total: float | None, done: float = 0) -> None:
        """A new phase of the bar counting ``unit``: from ``done`` of ``total``, its clock and
        text reset."""
        phase = self.phases.get(unit) or _Phase()
        phase.started, phase.first, phase.done = time.monotonic(), done, done
        phase.total, phase.every = total, self.every.get(unit, 1)
        fields = {"total": total, "completed": done, "info": "", "first": done}
        if phase.task_id is None:
            phase.task_id = self.bars.add_task(unit, **fields)
        else:
            self.bars.reset(phase.task_id, **fields)
        self.phases[unit] = phase

    def update(self, unit: str, done: float, total: float | None = None, info: str = "") -> None:
        """``done`` units of the bar finished (a bar not begun begins now)."""
        if unit not in self.phases:
            self.begin(unit, total)
        phase = self.phases[unit]
        if done < phase.done:  # counting again: a new phase
            self.begin(unit, total)
        phase.total = total if total is not None else phase.total
        if self.live and not self.quiet:
            self.bars.start()
            self.bars.update(phase.task_id, completed=done, total=phase.total, info=info)
        elif not self.quiet and phase.every and self._crossed(phase, done):
            self._line(unit, done, phase, info)
        phase.done = max(done, phase.done)

    @staticmethod
    def _crossed(phase: _Phase, done: float) -> bool:
        """``done`` passed a multiple of ``every`` (or the end) since the last update."""
        every = phase.every or 1
        return done > phase.done and (done // every > phase.done // every or done == phase.total)

    def note(self, text: str) -> None:
        """A line of its own (above the bars on a terminal)."""
        if self.quiet:
            return
        console = self.bars.console if self.live else self.plain
        console.print(text, markup=False, highlight=False, soft_wrap=True)

    def _line(self, unit: str, done: float, phase: _Phase, info: str) -> None:
        elapsed = time.monotonic() - phase.started
        of = f"/{phase.total:g}" if phase.total else ""
        parts = [f"{unit} {done:g}{of}", info, f"elapsed {clock(elapsed)}"]
        if phase.total and done < phase.total:
            left = eta_seconds(elapsed, done - phase.first, phase.total - phase.first)
            parts.append(f"eta {clock(left)}")
        self.plain.print("  ".join(p for p in parts if p), markup=False)
