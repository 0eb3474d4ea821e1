"""`dlo export --format minari`: a dataset as a Minari dataset for offline-RL libraries."""

from __future__ import annotations

from enum import Enum
from pathlib import Path
from typing import Annotated, Any

import typer

from dlocli.cli.common import JsonFlag, emit_summary, handle_errors
from dlocli.cli.progress import Bars
from dlocli.errors import BadInput
from dlocli.events import Began, Event
from dlocli.processes import signal_token
from dlocli.runs.export import export_minari


class ExportFormat(str, Enum):
    minari = "minari"


@handle_errors
def export(
    run_or_dataset: Annotated[
        Path,
        typer.Argument(
            metavar="RUN_OR_DATASET",
            help="A `dlo collect` run directory or its dataset.h5.",
            show_default=False,
        ),
    ],
    fmt: Annotated[
        ExportFormat, typer.Option("--format", help="Output format (Minari: offline RL).")
    ] = ExportFormat.minari,
    dataset_id: Annotated[
        str | None,
        typer.Option(
            "--dataset-id",
            help="Minari dataset id, namespace/name-vN.  [default: "
            "dlocli/BACKEND-TASK-random-v0, from the dataset's spec]",
        ),
    ] = None,
    out: Annotated[
        Path | None,
        typer.Option(
            "--out",
            help="Folder of Minari datasets (load with MINARI_DATASETS_PATH set to it).  "
            "[default: $MINARI_DATASETS_PATH, else ~/.minari/datasets]",
        ),
    ] = None,
    old_name: Annotated[str | None, typer.Option("--name", hidden=True)] = None,
    old_root: Annotated[Path | None, typer.Option("--root", hidden=True)] = None,
    overwrite: Annotated[
        bool, typer.Option("--overwrite", help="Replace an existing Minari dataset of this id.")
    ] = False,
    skip_diverged: Annotated[
        bool,
        typer.Option(
            "--skip-diverged",
            help="Leave out episodes whose simulation diverged (without it their finite "
            "steps are exported, truncated after the last).",
        ),
    ] = False,
    author: Annotated[
        str | None, typer.Option("--author", help="Author recorded in the Minari metadata.")
    ] = None,
    author_email: Annotated[
        str | None, typer.Option("--author-email", help="Author's contact e-mail.")
    ] = None,
    code_permalink: Annotated[
        str | None,
        typer.Option("--code-permalink", help="Link to the code version that made the data."),
    ] = None,
    json_out: JsonFlag = False,
) -> None:
    """Write a dataset as a Minari dataset (`minari.load_dataset(ID)`).

    Observations are the env's flat observations of the recorded states, actions the task's
    (6 or 12), rewards as stored; the env spec is recorded, so `recover_environment()` works
    after `import dlocli`.
    """
    with Bars(json_out, _describe) as bars:
        summary = export_minari(
            run_or_dataset,
            dataset_id=_one_of(dataset_id, old_name, "--dataset-id", "--name"),
            root=_one_of(out, old_root, "--out", "--root"),
            overwrite=overwrite,
            skip_diverged=skip_diverged,
            author=author,
            author_email=author_email,
            code_permalink=code_permalink,
            progress=bars,
            cancel=signal_token(),
        )
    emit_summary(summary, json_out, f"dlo export --format {fmt.value}")


def _one_of(value: Any, old: Any, flag: str, old_flag: str) -> Any:
    """A flag's value, given under its name or its earlier one (kept working, hidden)."""
    if value is not None and old is not None and value != old:
        raise BadInput(f"{flag} and {old_flag} (its earlier name) differ; pass only {flag}")
    return value if value is not None else old


def _describe(event: Event) -> str:
    """An episode's steps, or that it is left out."""
    if isinstance(event, Began):
        return ""
    steps = event.values["steps"]
    return f"{steps} steps" if event.values["exported"] else f"{steps} steps, left out"
