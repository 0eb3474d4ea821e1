"""Datasets: the documented HDF5 file (``dataset.h5``) every command reads and writes, in
two forms that :func:`load_dataset` tells apart by the file's ``form`` attribute
(:mod:`dlocli.data.format`):

- the rod's full state, collected in simulation (:class:`Dataset`, :mod:`dlocli.data.rod`);
- tracked marker positions, recorded on real cables (:class:`MarkerDataset`,
  :mod:`dlocli.data.markers`), with the benchmark protocol that scores rollouts of them
  (:mod:`dlocli.data.protocol`).

Each form's module documents its arrays; :mod:`dlocli.data.checks` holds the field checks
both run as a file is read.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from dlocli.data.format import DATASET_FILE, FORMAT, MARKERS, decode_attr
from dlocli.data.markers import MarkerDataset, read_marker_arrays
from dlocli.data.rod import Dataset, Episode, read_rod_arrays
from dlocli.errors import BadInput
from dlocli.io import prepare_run_dir, write_json_atomic
from dlocli.rundir import owned

__all__ = ["DATASET_FILE", "Dataset", "Episode", "MarkerDataset", "load_dataset"]


def load_dataset(path: Path) -> Dataset | MarkerDataset:
    """Load a dataset file (or a run directory holding ``dataset.h5``); BadInput if not one.
    A rod dataset is a :class:`Dataset`; a marker dataset (recorded marker positions, e.g.
    from `dlo import`) a :class:`MarkerDataset`."""
    import h5py

    path = Path(path)
    if path.is_dir():
        path = path / DATASET_FILE
    if not path.is_file():
        raise BadInput(
            f"dataset {path} does not exist; make one with `dlo collect --random --out DIR`"
        )
    try:
        with h5py.File(path, "r") as f:
            if f.attrs.get("format") != FORMAT:
                raise BadInput(f"{path} is not a dlocli dataset (no format={FORMAT} attribute)")
            attrs = {k: decode_attr(v) for k, v in f.attrs.items()}
            # the one place the form is read; a file without it (version 1) is the rod's
            if attrs.get("form") == MARKERS:
                return read_marker_arrays(f, path, attrs)
            return read_rod_arrays(f, path, attrs)
    except OSError as exc:
        raise BadInput(
            f"dataset {path} is not a readable HDF5 file ({exc}); re-collect it"
        ) from exc


def save_dataset_run(
    spec: Any, dataset: Dataset | MarkerDataset, summary: dict[str, Any], overwrite: bool
) -> dict[str, Any]:
    """Write a run that made a dataset (``dlo import``, ``dlo track``): its spec, the dataset
    and ``summary`` (given the folder as ``out``) into ``spec.out``; the summary."""
    with owned(spec.out):
        out = prepare_run_dir(spec.out, overwrite)
        write_json_atomic(out / "spec.json", spec.model_dump(mode="json"))
        dataset.save(out / DATASET_FILE)
        summary["out"] = str(out)
        write_json_atomic(out / "summary.json", summary)
    return summary
