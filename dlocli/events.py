"""What a long-running command reports while it runs, and the one callback shape that takes it.

Every run (a fit, `dlo train`, collect, control, calibrate, online, bench, eval, track; an
episode's rollout) takes ``progress``, a :data:`Callback`, and calls it with :class:`Event`:
``done`` of ``total`` ``unit`` finished (an epoch, an episode, a trial, a job), with that
unit's numbers in ``values``. A :class:`Began` starts a phase of counting: its ``done`` units
were finished before it (kept from a stopped run), so a rate or an ETA counts from there.
Subclasses exist only where a consumer tells kinds apart (a fit's batches and validations,
:mod:`dlocli.models.fitting`). A fit's ``on_validation`` is no report but a hook: it hands the
live optimiser and random generator to whoever checkpoints them, which events never carry.
The CLI renders events (``dlocli/cli/progress.py``); a callback may raise (a test's
KeyboardInterrupt) to stop the run where it reported; a run stops at its safe points when
the :class:`~dlocli.cancel.CancelToken` it is handed is cancelled.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any


@dataclass(frozen=True)
class Event:
    """``done`` of ``total`` ``unit`` finished (``total`` None: not known), with ``values``:
    what the last unit measured (a loss, an error in mm, a job's name and seconds)."""

    unit: str
    done: float
    total: float | None = None
    values: dict[str, Any] = field(default_factory=dict)


@dataclass(frozen=True)
class Began(Event):
    """A phase counting ``unit`` begins, ``done`` of ``total`` already finished."""


#: what every run function takes as ``progress``
Callback = Callable[[Event], None]


def ignore(event: Event) -> None:
    """The callback of a run nobody watches."""
