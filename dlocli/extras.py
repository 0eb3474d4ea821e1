"""Optional features and the extra that installs each (``pip install -c constraints.txt
torch==2.13.0 -e '.[EXTRA]'`` in dlocli's folder, the form of every install line of the docs).

A command that needs a missing extra says which one in one line (exit 2) before it writes
anything, never a ``ModuleNotFoundError``. Every extra of the package but the test tools is
named here (a test holds this table to pyproject.toml).
"""

from __future__ import annotations

import importlib

from dlocli.errors import BadInput

#: extra -> the module it installs that dlocli imports
EXTRAS = {
    "ray": "ray",
    "minari": "minari",
    "tensorboard": "tensorboard",
    "calibrate": "cma",
    "bridge": "zmq",
    "ros": "rosbags",
    "view": "rerun",
}


def require(extra: str, feature: str, alternative: str = "") -> None:
    """Raise :class:`BadInput` naming ``extra`` unless its module imports; ``feature`` is
    what needs it (``"dlo calibrate"``), ``alternative`` a way to do without it."""
    try:
        importlib.import_module(EXTRAS[extra])
    except ImportError as exc:
        instead = f", or {alternative}" if alternative else ""
        raise BadInput(
            f"{feature} needs the '{extra}' extra, which is not installed: "
            f"pip install -c constraints.txt torch==2.13.0 -e '.[{extra}]' (in dlocli's "
            f"folder){instead}"
        ) from exc
