"""The dlocli-cell protocol's messages as types: every request a cell takes and every reply a
controller takes is checked here, field by field, before anything acts on it.

One parse (pydantic's JSON parser: strict JSON, nesting bounded) turns a message's bytes into
one of these models or a one-line refusal. Both sides use it: a cell (``dlo serve``, a robot
cell built on :mod:`dlocli.bridge.server`) for requests, a controller
(:mod:`dlocli.bridge.remote`) for replies, so neither trusts the other's numbers.
"""

from __future__ import annotations

from typing import Annotated, Any, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, TypeAdapter, ValidationError, model_validator

from dlocli.bridge.protocol import VERSION
from dlocli.errors import BadInput
from dlocli.spec_base import bounded_repr

#: a float that is a number (JSON's 1e999 reads as infinity: refused)
Finite = Annotated[float, Field(allow_inf_nan=False)]
#: a length or a position coordinate (m): finite, within 1 km of the origin
Metres = Annotated[float, Field(allow_inf_nan=False, ge=-1000.0, le=1000.0)]
Vector3 = tuple[Metres, Metres, Metres]
Twist = tuple[Finite, Finite, Finite, Finite, Finite, Finite]
Pose = tuple[Metres, Metres, Metres, Finite, Finite, Finite, Finite]
Quaternion = tuple[Finite, Finite, Finite, Finite]
Row3, Row4 = tuple[Finite, Finite, Finite], tuple[Finite, Finite, Finite, Finite]
#: a session token: what `hello` hands out, what every later request carries
Token = Annotated[str, Field(min_length=1, max_length=64)]
#: how many numbers a simulator state may hold (a 200-segment rod needs a few thousand)
MAX_STATE_NUMBERS = 200_000
#: seeds a cell takes (numpy's and the simulators' range)
MAX_SEED = 2**32
#: the most points a cloud may hold (a 640 x 480 camera full of cable: 300k; ours 100s)
MAX_CLOUD_POINTS = 200_000


class Message(BaseModel):
    """A request: strict types (``true`` is no number, ``"1"`` no integer), no unknown field."""

    model_config = ConfigDict(strict=True, extra="forbid", frozen=True)


class Hello(Message):
    type: Literal["hello"]
    protocol: Annotated[str, Field(max_length=64)]
    version: int
    #: the controller's rod spec (a simulated cell refuses another one)
    backend: dict[str, Any] | None = None
    control_dt: Annotated[float, Field(allow_inf_nan=False, gt=0.0, le=10.0)]


class Limits(Message):
    """The grippers' envelope: a box (m) and the range of their separation (m)."""

    workspace_low: Vector3
    workspace_high: Vector3
    min_separation: Annotated[float, Field(allow_inf_nan=False, ge=0.0, le=1000.0)]
    max_separation: Annotated[float, Field(allow_inf_nan=False, gt=0.0, le=1000.0)]

    @model_validator(mode="after")
    def _ordered(self) -> Limits:
        if not all(lo < hi for lo, hi in zip(self.workspace_low, self.workspace_high, strict=True)):
            raise ValueError("workspace_low must lie below workspace_high on every axis")
        if not self.min_separation < self.max_separation:
            raise ValueError("min_separation must be less than max_separation")
        return self


class Reset(Message):
    type: Literal["reset"]
    session: Token
    seed: Annotated[int, Field(ge=0, lt=MAX_SEED)] | None = None
    limits: Limits | None = None


class Step(Message):
    type: Literal["step"]
    session: Token
    #: the controller's count of its steps since the reset (the cell's reply says its own)
    step: Annotated[int, Field(ge=0)] | None = None
    velocities: tuple[Twist, Twist]


class Stop(Message):
    type: Literal["stop"]
    session: Token


class GetState(Message):
    type: Literal["get_state"]
    session: Token


class SetState(Message):
    type: Literal["set_state"]
    session: Token
    state: Annotated[list[Finite], Field(min_length=1, max_length=MAX_STATE_NUMBERS)]


class Capture(Message):
    """A depth camera's frame of the cable now (a cell with a camera)."""

    type: Literal["capture"]
    session: Token
    #: the episode's seed of a simulated camera's noise (a real camera ignores it)
    seed: Annotated[int, Field(ge=0, lt=2**63)] = 0
    #: the controller's time of the frame (s since the episode began)
    time: Annotated[float, Field(allow_inf_nan=False, ge=0.0)] = 0.0


class Bye(Message):
    type: Literal["bye"]
    session: Token


Request = Hello | Reset | Step | Stop | GetState | SetState | Capture | Bye
REQUEST_TYPES = ("hello", "reset", "step", "stop", "get_state", "set_state", "capture", "bye")
_requests: TypeAdapter[Request] = TypeAdapter(
    Annotated[Request, Field(discriminator="type")]  # type: ignore[arg-type]
)


def parse_request(message: bytes) -> Request:
    """A request's bytes as its typed message; BadInput (one line) for anything else."""
    return _parse(_requests, message, "request", REQUEST_TYPES)


# --------------------------------------------------------------------------- replies
class Reply(BaseModel):
    """A cell's reply: strict types; fields a newer cell adds are ignored."""

    model_config = ConfigDict(strict=True, extra="ignore", frozen=True)


class CellInfo(Reply):
    """What a cell says of itself in its ``welcome``."""

    name: Annotated[str, Field(max_length=200)]
    backend: dict[str, Any] | None = None
    control_dt: Annotated[float, Field(allow_inf_nan=False, gt=0.0, le=10.0)]
    realtime: bool = False
    n_segments: Annotated[int, Field(ge=1, le=10_000)]
    #: the longest a ``reset`` may take to answer (s): a robot brings its grippers to the
    #: start and lets the cable settle
    reset_timeout_s: Annotated[float, Field(allow_inf_nan=False, gt=0.0, le=3600.0)] = 10.0
    #: the cell's depth camera (a camera spec), if it answers ``capture``
    camera: dict[str, Any] | None = None


class Welcome(Reply):
    type: Literal["welcome"]
    protocol: str
    version: int
    session: Token
    #: the cell ends a session idle for this long (s)
    session_idle_s: Annotated[float, Field(allow_inf_nan=False, gt=0.0)]
    cell: CellInfo


class State(Reply):
    type: Literal["state"]
    step: Annotated[int, Field(ge=0)]
    time: Annotated[float, Field(allow_inf_nan=False, ge=0.0)]
    diverged: bool
    tracked: bool = True
    positions: Annotated[list[Vector3], Field(max_length=10_000)]
    quaternions: Annotated[list[Quaternion], Field(max_length=10_000)]
    grippers: tuple[Pose, Pose]
    late: Annotated[int, Field(ge=0)] = 0
    dropped: Annotated[int, Field(ge=0)] = 0


class Snapshot(Reply):
    type: Literal["snapshot"]
    state: Annotated[list[Finite], Field(min_length=1, max_length=MAX_STATE_NUMBERS)]


class Cloud(Reply):
    """A depth camera's frame: the cable's points in the world frame (m), the camera's
    extrinsics (camera to world) and intrinsics (pixels)."""

    type: Literal["cloud"]
    points: Annotated[list[Vector3], Field(max_length=MAX_CLOUD_POINTS)]
    extrinsics: tuple[Row4, Row4, Row4, Row4]
    intrinsics: tuple[Row3, Row3, Row3]
    time: Annotated[float, Field(allow_inf_nan=False, ge=0.0)] = 0.0
    #: a simulator's segment behind each point (-1: stray), for measurements
    segments: Annotated[list[int], Field(max_length=MAX_CLOUD_POINTS)] | None = None


class Farewell(Reply):
    type: Literal["bye"]


class Error(Reply):
    type: Literal["error"]
    #: bad_request, busy (another controller owns the cell), no_session, refused
    code: Annotated[str, Field(max_length=64)] = "bad_request"
    message: Annotated[str, Field(max_length=2000)]


AnyReply = Welcome | State | Snapshot | Cloud | Farewell | Error
REPLY_TYPES = ("welcome", "state", "snapshot", "cloud", "bye", "error")
_replies: TypeAdapter[AnyReply] = TypeAdapter(
    Annotated[AnyReply, Field(discriminator="type")]  # type: ignore[arg-type]
)


def parse_reply(message: bytes) -> AnyReply:
    """A reply's bytes as its typed message; BadInput (one line) for anything else."""
    return _parse(_replies, message, "reply", REPLY_TYPES)


def state_arrays(state: State, n_segments: int) -> dict[str, np.ndarray]:
    """A state's positions (N, 3), quaternions (N, 4) and grippers (2, 7); BadInput unless
    it holds ``n_segments`` of each."""
    if len(state.positions) != n_segments or len(state.quaternions) != n_segments:
        raise BadInput(
            f"state reply: {len(state.positions)} positions and {len(state.quaternions)} "
            f"quaternions for a rod of {n_segments} segments"
        )
    return {
        "positions": np.array(state.positions, dtype=np.float64),
        "quaternions": np.array(state.quaternions, dtype=np.float64),
        "grippers": np.array(state.grippers, dtype=np.float64),
    }


def _parse(adapter: TypeAdapter, message: bytes, what: str, types: tuple[str, ...]) -> Any:
    try:
        return adapter.validate_json(message)
    except ValidationError as exc:
        raise BadInput(_refusal(exc, what, types)) from None


def _refusal(exc: ValidationError, what: str, types: tuple[str, ...]) -> str:
    error = exc.errors()[0]
    kind = error["type"]
    if kind == "json_invalid":
        return f"not a dlocli-cell {what}: {error['msg']}"
    if kind in ("union_tag_invalid", "union_tag_not_found", "model_attributes_type"):
        return f"not a dlocli-cell {what}: a JSON object whose 'type' is one of {', '.join(types)}"
    tag, *field = error["loc"]
    where = ".".join(str(part) for part in field) or "(the message)"
    if kind == "extra_forbidden":
        return f"{tag} {what}: unknown field '{where}' (protocol version {VERSION} has none)"
    if kind == "missing":
        return f"{tag} {what}: field '{where}' missing"
    return f"{tag} {what}: field '{where}': {error['msg']} (got {bounded_repr(error.get('input'))})"
