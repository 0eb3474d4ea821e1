"""The dataset file's identity, shared by the rod (:mod:`dlocli.data.rod`) and marker
(:mod:`dlocli.data.markers`) datasets: its format tag, version, name, and the ``form``
attribute that tells the two apart."""

from __future__ import annotations

import json
from typing import Any

import numpy as np

FORMAT = "dlocli-dataset"
FORMAT_VERSION = 2  # 2: the ``form`` attribute ("rod", or "markers")
DATASET_FILE = "dataset.h5"
#: the forms of data (and of the models that learn from them): the rod's full state, or
#: tracked marker positions; a file without the attribute (version 1) holds the rod's
ROD = "rod"
MARKERS = "markers"


def write_header(f: Any, form: str, n_segments: int, attrs: dict[str, Any]) -> None:
    """The attributes every dataset file starts with, then ``attrs`` (JSON where not a plain
    number or string), into the open HDF5 file ``f``."""
    f.attrs["format"] = FORMAT
    f.attrs["format_version"] = FORMAT_VERSION
    f.attrs["form"] = form
    f.attrs["n_segments"] = n_segments
    for key, value in attrs.items():
        f.attrs[key] = value if isinstance(value, (int, float, str)) else json.dumps(value)


def decode_attr(value: Any) -> Any:
    """An HDF5 attribute as Python: text decoded, JSON parsed, numpy scalars unwrapped."""
    if isinstance(value, bytes):
        value = value.decode()
    if isinstance(value, str) and value[:1] in "[{":
        try:
            return json.loads(value)
        except ValueError:
            return value
    return value.item() if isinstance(value, np.generic) else value
