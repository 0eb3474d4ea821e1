"""The dlocli-cell protocol, version 2: a controller and a cell (a served simulator, or a real
robot with a tracker) over ZeroMQ.

The controller holds a REQ socket, the cell a REP socket: every request gets one reply. Each
message is one JSON object (UTF-8, one ZeroMQ frame, at most :data:`MAX_MESSAGE_BYTES`);
JSON's shortest round-trip float form keeps float64 values exact, so a bridged run equals an
in-process one. Units: metres, seconds, radians; world frame, z up; quaternions (w, x, y, z);
gripper 0 is the left one (the rod's start), gripper 1 the right. Every field's type is in
:mod:`dlocli.bridge.messages`, where both sides check what they receive.

Requests (``type``) and their replies:

- ``hello`` {protocol, version, backend, control_dt} -> ``welcome`` {protocol, version,
  session, session_idle_s, cell: {name, backend, control_dt, realtime, n_segments,
  reset_timeout_s, camera}}. It opens a session: the cell belongs to this controller until ``bye``
  or until no request came for ``session_idle_s`` (the cell then stops its grippers). Every
  later request carries ``session``; another controller's requests get ``error`` with code
  ``busy`` and change nothing. ``backend`` is the controller's rod spec: a simulated cell
  refuses another rod or control period.
- ``reset`` {session, seed, limits} -> ``state``: the rod at rest in its nominal
  configuration; ``limits`` is the grippers' envelope {workspace_low, workspace_high,
  min_separation, max_separation} in metres, which the cell keeps them inside. A reset may
  take up to the welcome's ``reset_timeout_s`` to answer.
- ``step`` {session, step, velocities: [[vx, vy, vz, wx, wy, wz] left, [...] right]} (m/s,
  rad/s about the gripper position) -> ``state`` after one control period.
- ``stop`` {session} -> ``state``: zero velocity, grippers held where they are.
- ``get_state`` {session} -> ``snapshot`` {state: [...]}; ``set_state`` {session, state} ->
  ``state`` (simulated cells only; a real cell replies ``error``).
- ``capture`` {session, seed, time} -> ``cloud`` {points (P x 3, world frame), extrinsics
  (4 x 4, camera to world), intrinsics (3 x 3), time, segments}: a depth camera's frame of the
  cable (a cell whose welcome names a ``camera``; ``seed`` seeds a simulated camera's noise
  for the episode, so a bridged run draws what an in-process one draws).
- ``bye`` {session} -> ``bye``: the session ends.

``state`` = {step, time, diverged, tracked, positions (N x 3), quaternions (N x 4), grippers
(2 x 7: x y z qw qx qy qz), late, dropped}: ``step`` counts the cell's control periods since
the reset, ``tracked`` is false when the tracker lost the cable (positions and quaternions are
then the last ones it saw), ``late`` counts the commands that came after their period's tick
(a real-time cell; each once, however many periods it stepped with the held command
meanwhile; its clock starts at the first step after a reset), ``dropped`` the commands it
lost. Any request may get
``error`` {code, message}: ``bad_request`` (the request was refused and nothing changed),
``busy`` (another controller owns the cell), ``no_session`` (send ``hello`` first; a session
that idled out is gone), ``refused`` (the cell cannot do it, e.g. ``set_state`` on a robot).

Version 2 added sessions, the error codes, ``reset_timeout_s`` and ``capture``; a version-1
peer is refused at ``hello``.
"""

from __future__ import annotations

import json
from typing import Any

import numpy as np

PROTOCOL = "dlocli-cell"
VERSION = 2
#: the largest message a cell takes (ZeroMQ refuses longer ones on the socket, unread): a
#: 200-segment rod's full simulator state is a few hundred kB of JSON
MAX_MESSAGE_BYTES = 4 * 2**20
#: the largest reply a controller takes
MAX_REPLY_BYTES = 16 * 2**20


def encode(kind: str, **fields: Any) -> bytes:
    """One message: ``type`` and ``fields`` (numpy arrays as nested lists)."""
    return json.dumps({"type": kind, **fields}, default=_plain, allow_nan=False).encode()


def _plain(value: Any) -> Any:
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, np.generic):
        return value.item()
    raise TypeError(f"cannot send {type(value).__name__}")
