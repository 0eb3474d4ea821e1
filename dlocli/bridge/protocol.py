"""The dlocli-cell protocol, version 1: a controller and a cell (a served simulator, or a real
robot with a tracker) over ZeroMQ.

The controller holds a REQ socket, the cell a REP socket: every request gets one reply. Each
message is one JSON object (UTF-8); JSON's shortest round-trip float form keeps float64 values
exact, so a bridged run equals an in-process one. Units: metres, seconds, radians; world frame,
z up; quaternions (w, x, y, z); gripper 0 is the left one (the rod's start), gripper 1 the right.

Requests (``type``) and their replies:

- ``hello`` {protocol, version, backend, control_dt} -> ``welcome`` {protocol,
  version, cell: {name, backend, control_dt, realtime, n_segments}}. ``backend`` is the
  controller's rod spec: a simulated cell refuses another rod or control period.
- ``reset`` {seed, limits} -> ``state``: the rod at rest in its nominal configuration;
  ``limits`` is the grippers' envelope {workspace_low, workspace_high, min_separation,
  max_separation} in metres, which the cell keeps them inside.
- ``step`` {step, velocities: [[vx, vy, vz, wx, wy, wz] left, [...] right]} (m/s, rad/s about
  the gripper position) -> ``state`` after one control period.
- ``stop`` {} -> ``state``: zero velocity, grippers held where they are.
- ``get_state`` {} -> ``snapshot`` {state: [...]}; ``set_state`` {state} -> ``state``
  (simulated cells only; a real cell replies ``error``).
- ``bye`` {} -> ``bye``.

``state`` = {step, time, diverged, tracked, positions (N x 3), quaternions (N x 4), grippers
(2 x 7: x y z qw qx qy qz), late, dropped}: ``step`` counts the cell's control periods since
the reset, ``tracked`` is false when the tracker lost the cable (positions and quaternions are
then the last ones it saw), ``late`` counts the periods the cell stepped with the held command
because none had come in time, ``dropped`` the commands it lost. Any request may get
``error`` {message}.
"""

from __future__ import annotations

import json
from typing import Any

import numpy as np

from dlocli.errors import BadInput

PROTOCOL = "dlocli-cell"
VERSION = 1


def encode(kind: str, **fields: Any) -> bytes:
    """One message: ``type`` and ``fields`` (numpy arrays as nested lists)."""
    return json.dumps({"type": kind, **fields}, default=_plain, allow_nan=False).encode()


def decode(message: bytes) -> dict[str, Any]:
    """A message as a dict with a ``type``; BadInput for anything else."""
    try:
        value = json.loads(message.decode("utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise BadInput(f"not a {PROTOCOL} message (JSON expected): {exc}") from None
    if not isinstance(value, dict) or not isinstance(value.get("type"), str):
        raise BadInput(f"not a {PROTOCOL} message: a JSON object with a 'type' expected")
    return value


def _plain(value: Any) -> Any:
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, np.generic):
        return value.item()
    raise TypeError(f"cannot send {type(value).__name__}")


def array(message: dict[str, Any], key: str, shape: tuple[int, ...]) -> np.ndarray:
    """``message[key]`` as a finite float64 array of ``shape``; BadInput otherwise."""
    try:
        value = np.asarray(message[key], dtype=np.float64)
    except (KeyError, TypeError, ValueError):
        raise BadInput(f"{message.get('type')} message: '{key}' missing or not numbers") from None
    if value.shape != shape or not np.all(np.isfinite(value)):
        raise BadInput(
            f"{message.get('type')} message: '{key}' must be finite numbers of shape {shape}, "
            f"got shape {value.shape}"
        )
    return value
