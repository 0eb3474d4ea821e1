"""`dlo eval`: a trained model's one-step and open-loop errors on a dataset, next to
persistence's (:mod:`dlocli.models.evaluation`); on recorded cables, the data set's published
protocol (:mod:`dlocli.recorded_cables.evaluation`)."""

from __future__ import annotations

from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import Any

from dlocli.cancel import CancelToken
from dlocli.data import Dataset, MarkerDataset, load_dataset
from dlocli.errors import BadInput
from dlocli.events import Began, Callback, Event, ignore
from dlocli.io import check_writable, prepare_run_dir, write_json_atomic
from dlocli.models.base import check_control_rate
from dlocli.models.checkpoints import load_model
from dlocli.models.evaluation import HORIZONS, evaluation_parts
from dlocli.models.marker_training import predict_episodes
from dlocli.models.spec import EvalSpec
from dlocli.plots import plot_rollout
from dlocli.recorded_cables.evaluation import (
    MARKER_PARTS,
    marker_evaluation_parts,
    plot_error_by_horizon,
)
from dlocli.rundir import owned
from dlocli.runs.recording import RunRecording, check_record_path


def run_evaluation(
    spec: EvalSpec,
    overwrite: bool = False,
    record: Path | None = None,
    progress: Callback | None = None,
    cancel: CancelToken | None = None,
) -> dict[str, Any]:
    """`dlo eval`: the errors of ``spec.checkpoint`` on ``spec.data``; with ``spec.out``, the
    spec and the summary are written there; with ``record`` (a marker dataset), a recording of
    the eval trajectories beside the model's open-loop predictions.

    ``progress`` gets a Began of the measurements (unit "measurement": on rod data the one-step
    errors, then each horizon's; on markers the model's scores, each reference's, the timing),
    then an Event per measurement (``values``: its ``name`` and its summary entries).
    ``cancel`` stops it before each measurement: the summary of those made, marked
    ``stopped``, is written to ``spec.out`` before the stop is raised again (none made:
    nothing is written, an earlier run's files there are left as they were)."""
    progress, cancel = progress or ignore, cancel or CancelToken()
    if spec.checkpoint is None or spec.data is None:
        raise BadInput("dlo eval needs --checkpoint (a trained model) and --data (a dataset)")
    if spec.plot is not None and spec.plot.suffix != ".png":
        raise BadInput(f"--plot {spec.plot} must end in .png")
    if spec.plot is not None:
        check_writable(spec.plot, "--plot", overwrite)
    check_record_path(record, overwrite)
    dataset = load_dataset(spec.data)
    if record is not None and not isinstance(dataset, MarkerDataset):
        raise BadInput(
            f"--record on dlo eval records recorded markers; {spec.data} is simulated rod data "
            "(record a `dlo control` run instead), drop --record"
        )
    if isinstance(dataset, MarkerDataset):
        dataset.require_split("eval")
    net = load_model(spec.checkpoint, spec.device, form=dataset.form)  # the data's form
    serves_any = isinstance(dataset, MarkerDataset) and net.network.any_count
    if dataset.n_segments != net.n_segments and not serves_any:
        raise BadInput(
            f"model {spec.checkpoint} is for {net.n_segments} segments but {spec.data} has "
            f"{dataset.n_segments}; evaluate on matching data"
        )
    if dataset.control_dt is not None:
        check_control_rate(net, dataset.control_dt, f"model {spec.checkpoint}",
                           f"{spec.data} is", "evaluate it on data at {hz} Hz")  # fmt: skip
    summary: dict[str, Any] = {}
    if spec.out is None:
        _measure(spec, net, dataset, record, summary, progress, cancel)
        return summary
    made: list[Event] = []  # the measurements made, which a stop keeps

    def report(event: Event) -> None:
        if not isinstance(event, Began):
            made.append(event)
        progress(event)

    with owned(spec.out):  # one writer per run directory
        out = prepare_run_dir(spec.out, overwrite)
        try:
            _measure(spec, net, dataset, record, summary, report, cancel)
        except KeyboardInterrupt as stop:
            if made:
                summary["stopped"] = type(stop).__name__
                write_json_atomic(out / "spec.json", spec.model_dump(mode="json"))
                write_json_atomic(out / "summary.json", summary)
            raise
        write_json_atomic(out / "spec.json", spec.model_dump(mode="json"))
        write_json_atomic(out / "summary.json", summary)
    return summary


def record_predictions(path: Path, net: Any, dataset: MarkerDataset, name: str) -> None:
    """The eval trajectories one after the other, each beside the model's open-loop
    prediction of it (the protocol's, from frame 1)."""
    episodes = dataset.episodes("eval")
    recording = RunRecording(path, name)
    try:
        step = 0
        for recorded, predicted in zip(
            episodes, predict_episodes(net, episodes, dataset.held), strict=True
        ):
            step = recording.add_prediction(recorded, predicted, dataset.held, step)
    finally:
        recording.close()


def _measure(
    spec: EvalSpec,
    net: Any,
    dataset: Dataset | MarkerDataset,
    record: Path | None,
    summary: dict[str, Any],
    progress: Callback,
    cancel: CancelToken,
) -> None:
    """Fill ``summary`` measurement by measurement (``cancel`` checked before each), then
    draw the plot and the recording."""
    summary |= {"checkpoint": str(spec.checkpoint), "data": str(spec.data)}
    if isinstance(dataset, MarkerDataset):
        if net.spec.cable_code:
            summary["cable_code"] = _choose_code(net, dataset)
        curves: dict[str, dict[str, list[float]]] = {"free_error_mm": {}, "abs_error_cm": {}}

        def parts() -> Iterator[tuple[str, dict[str, Any]]]:
            for name, measured, curve in marker_evaluation_parts(net, dataset):
                for key, values in curve.items():
                    curves[key].update(values)
                yield name, measured

        summary |= {"split": "eval", "episodes": len(dataset.episodes("eval"))}
        _measured(parts(), MARKER_PARTS, summary, progress, cancel)
        if spec.plot is not None:
            plot_error_by_horizon(summary, curves, dataset.rate_hz, spec.plot)
            summary["plot"] = str(spec.plot)
        if record is not None:
            record_predictions(record, net, dataset, Path(spec.data).stem)
            summary["recording"] = str(record)
        if spec.out is not None:
            write_json_atomic(Path(spec.out) / "error_by_frame.json", curves)
        return
    parts = evaluation_parts(net, dataset, max_starts=spec.max_starts)
    _measured(parts, 1 + len(HORIZONS), summary, progress, cancel)
    if spec.plot is not None:
        plot_rollout(net, dataset, 0, spec.plot)
        summary["plot"] = str(spec.plot)


def _measured(
    parts: Iterable[tuple[str, dict[str, Any]]],
    total: int,
    summary: dict[str, Any],
    progress: Callback,
    cancel: CancelToken,
) -> None:
    """Each measurement of ``parts`` into ``summary``, reported as it is made; ``cancel``
    checked before the first and after each."""
    progress(Began("measurement", 0, total))
    cancel.raise_if_cancelled()
    for done, (name, measured) in enumerate(parts, 1):
        summary.update(measured)
        progress(Event("measurement", done, total, {"name": name, **measured}))
        cancel.raise_if_cancelled()


def _choose_code(net: Any, dataset: MarkerDataset) -> str:
    """Use the code the model learned for this cable's recordings, the mean code where it
    learned none; say which."""
    if net.use_recorded_cable(dataset.held, dataset.episodes("train")) is not None:
        return "its own: the model holds a code for this cable's train recordings"
    return f"the mean of {len(net.cable_keys)}: the model did not train on this cable"
