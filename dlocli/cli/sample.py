"""`dlo sample`: simulated recordings in the forms real data come in (a cable, a camera)."""

from __future__ import annotations

from typing import Annotated, Literal

import typer

from dlocli.cli.common import emit_summary, handle_errors
from dlocli.cli.flags import RunFlags, spec_flags
from dlocli.cli.progress import Bars
from dlocli.processes import signal_token
from dlocli.runs.sample_spec import SampleSpec


@handle_errors
@spec_flags(SampleSpec)
def sample(
    run: RunFlags,
    kind: Annotated[
        Literal["cable", "clouds"] | None,
        typer.Argument(
            help="cable: marker recordings in DEFORM's layout (train/ and eval/ of .pkl, or "
            "--format csv) for `dlo import` and `dlo calibrate`; clouds: a depth camera's "
            ".npz frame sequences for `dlo track`.  [default: cable]",
            show_default=False,
        ),
    ] = None,
) -> None:
    """Write simulated recordings of a cable that both grippers move, into --out's train/ and
    eval/, in the form real data comes in: the input of `dlo import`, `dlo calibrate` and
    `dlo track` when no real cable or camera is at hand."""
    from dlocli.runs.sample import run_sample

    if kind is not None:
        run.overrides["kind"] = kind
    with Bars(run.json) as bars:
        summary = run_sample(run.spec(), run.overwrite, bars, signal_token())
    emit_summary(summary, run.json, "dlo sample")
