"""The cell's side of the dlocli-cell protocol, for every cell: `dlo serve`'s simulator and a
robot of your own (:class:`dlocli.bridge.robot.Robot`) are served by the same loop, so both
refuse the same bad requests.

What a request passes before it reaches the rod: ZeroMQ's size limit (a longer message is
dropped unread), one frame, a JSON object of one of the protocol's types whose every field has
its type, range and shape (:mod:`dlocli.bridge.messages`), and the session: a cell belongs to
the controller that said ``hello`` until its ``bye`` or until it stayed silent for
``session_idle_s`` (the grippers are then stopped). A refused request gets ``error`` and
changes nothing; the cell serves on, whatever it was sent. The serving reports to one
``progress`` (:data:`dlocli.events.Callback`): :class:`Listening` once the socket is bound, then
a :class:`Logged` line for each session opened and ended, each request refused as ``busy``,
each fault of the cell and each failed handshake (a client without the cell's keys, or of
another protocol).
"""

from __future__ import annotations

import secrets
import time
from abc import ABC, abstractmethod
from pathlib import Path
from typing import Any

from dlocli.bridge import messages, protocol
from dlocli.bridge.keys import require_keys_off_loopback, secure_cell
from dlocli.cancel import CancelToken
from dlocli.errors import BadInput
from dlocli.events import Began, Callback, Event, ignore

#: how often the loop looks for a stop signal and an idle session while no request comes (ms)
POLL_MS = 100
#: a session without a request for this long ends (s), unless the cell says otherwise
SESSION_IDLE_S = 30.0

Reply = dict[str, Any]


class Listening(Began):
    """The cell's socket is bound: serving (unit "request") begins at ``address``, which
    names the port a ``tcp://HOST:*`` address was given only now."""

    @property
    def address(self) -> str:
        return self.values["address"]


class Logged(Event):
    """A line for the cell's log (a session opened or ended, a request refused as busy, a
    fault of the cell, a failed handshake), ``done`` requests received so far."""

    @property
    def line(self) -> str:
        return self.values["line"]


class Refused(BadInput):
    """A well-formed request this cell cannot carry out (``set_state`` on a robot)."""


class CellHandler(ABC):
    """What a cell does with requests that passed every check; each returns its reply's
    fields (``type`` included) or raises BadInput (the request changes nothing)."""

    @abstractmethod
    def info(self) -> dict[str, Any]:
        """The welcome's ``cell``: name, backend (a rod spec or None), control_dt, realtime,
        n_segments, reset_timeout_s."""

    def on_hello(self, hello: messages.Hello) -> None:
        """Refuse a controller of another rod or control period."""
        info = self.info()
        ours = info.get("backend")
        if ours is not None and hello.backend != ours:
            raise BadInput(
                f"the controller's rod is not this cell's: give the controller this cell's "
                f"backend spec ({ours.get('name')}, {info['n_segments']} segments)"
            )
        if hello.control_dt != info["control_dt"]:
            raise BadInput(
                f"control period {hello.control_dt:g} s asked, this cell steps "
                f"{info['control_dt']:g} s: control it at the cell's period"
            )

    @abstractmethod
    def on_reset(self, request: messages.Reset) -> Reply: ...

    @abstractmethod
    def on_step(self, request: messages.Step) -> Reply: ...

    @abstractmethod
    def on_stop(self) -> Reply: ...

    def on_get_state(self) -> Reply:
        raise Refused("this cell cannot save its state (a real rod): get_state is for simulators")

    def on_set_state(self, request: messages.SetState) -> Reply:
        raise Refused("this cell cannot restore a state (a real rod): set_state is for simulators")

    def on_capture(self, request: messages.Capture) -> Reply:
        raise Refused("this cell has no camera: serve it with `dlo serve --camera`")

    def on_release(self) -> None:
        """The session ended (``bye``, or idle): leave the grippers stopped."""
        self.on_stop()


class CellServer:
    """Requests in, replies out, for one :class:`CellHandler`: the checks and the session."""

    def __init__(
        self,
        handler: CellHandler,
        idle_s: float = SESSION_IDLE_S,
        progress: Callback | None = None,
    ) -> None:
        self.handler, self.idle_s, self.progress = handler, idle_s, progress or ignore
        self.session: str | None = None
        self.last_request = 0.0
        self.received = 0  # requests, each log line's ``done``

    def log(self, line: str) -> None:
        """Report ``line`` for the cell's log."""
        self.progress(Logged("request", self.received, values={"line": line}))

    def answer(self, frames: list[bytes]) -> bytes:
        """The reply to one received message (its ZeroMQ frames)."""
        self.expire_idle()
        self.received += 1
        if len(frames) != 1:
            return _error("bad_request", f"a request is one ZeroMQ frame, not {len(frames)}")
        request: messages.Request | None = None
        try:
            request = messages.parse_request(frames[0])
            if isinstance(request, messages.Hello):
                return self._hello(request)
            self._check_session(request.session)
            reply = self._dispatch(request)
        except _Denied as denied:
            return _error(denied.code, str(denied))
        except Refused as exc:
            return _error("refused", str(exc))
        except BadInput as exc:
            return _error("bad_request", str(exc))
        except Exception as exc:  # a fault of the rod or the robot's code: say it, serve on
            self.log(f"the cell failed on a {type(request).__name__} request: {exc!r}")
            return _error("cell_fault", f"the cell failed: {type(exc).__name__}: {exc}")
        if isinstance(request, messages.Bye):
            self._end("the controller said bye")
        kind = reply.pop("type")
        return protocol.encode(kind, **reply)

    def expire_idle(self) -> None:
        """End a session that stayed silent for ``idle_s`` (its grippers are stopped)."""
        if self.session is not None and time.monotonic() - self.last_request > self.idle_s:
            self._end(f"no request for {self.idle_s:g} s")

    # ------------------------------------------------------------------ sessions
    def _hello(self, hello: messages.Hello) -> bytes:
        if self.session is not None:
            self.log("refused a hello: busy (a controller owns the cell)")
            raise _Denied("busy", self._busy())
        spoken = (hello.protocol, hello.version)
        if spoken != (protocol.PROTOCOL, protocol.VERSION):
            raise BadInput(
                f"this cell speaks {protocol.PROTOCOL} version {protocol.VERSION}, not "
                f"{hello.protocol} {hello.version}: use a controller of the same protocol"
            )
        self.handler.on_hello(hello)
        self.session, self.last_request = secrets.token_hex(16), time.monotonic()
        self.log("a controller opened a session")
        return protocol.encode(
            "welcome",
            protocol=protocol.PROTOCOL,
            version=protocol.VERSION,
            session=self.session,
            session_idle_s=self.idle_s,
            cell=self.handler.info(),
        )

    def _check_session(self, token: str) -> None:
        if self.session is None:
            raise _Denied(
                "no_session",
                f"no session: send hello first (a session ends with bye or after "
                f"{self.idle_s:g} s without a request)",
            )
        # bytes: compare_digest refuses str holding anything but ASCII
        if not secrets.compare_digest(token.encode("utf-8", "surrogatepass"),
                                      self.session.encode()):  # fmt: skip
            self.log("refused a request: busy (not the session's token)")
            raise _Denied("busy", self._busy())
        self.last_request = time.monotonic()

    def _busy(self) -> str:
        return (
            f"busy: another controller owns this cell until its bye or {self.idle_s:g} s "
            "without a request; nothing was done"
        )

    def _end(self, why: str) -> None:
        self.session = None
        try:
            self.handler.on_release()
        except Exception as exc:  # noqa: BLE001 - the session ends whatever the rod says
            self.log(f"stopping the grippers failed: {exc!r}")
        self.log(f"session ended: {why}")

    def _dispatch(self, request: messages.Request) -> Reply:
        handler = self.handler
        if isinstance(request, messages.Reset):
            return handler.on_reset(request)
        if isinstance(request, messages.Step):
            return handler.on_step(request)
        if isinstance(request, messages.Stop):
            return handler.on_stop()
        if isinstance(request, messages.GetState):
            return handler.on_get_state()
        if isinstance(request, messages.SetState):
            return handler.on_set_state(request)
        if isinstance(request, messages.Capture):
            return handler.on_capture(request)
        return {"type": "bye"}


class _Denied(Exception):
    """A request outside the session (``busy``, ``no_session``)."""

    def __init__(self, code: str, message: str) -> None:
        super().__init__(message)
        self.code = code


def _error(code: str, message: str) -> bytes:
    return protocol.encode("error", code=code, message=message)


def serve(
    handler: CellHandler,
    address: str,
    keys: Path | None = None,
    idle_s: float = SESSION_IDLE_S,
    progress: Callback | None = None,
    cancel: CancelToken | None = None,
) -> None:
    """Serve ``handler`` at ``address`` until stopped (KeyboardInterrupt, or ``cancel``
    between requests: the command hands it Ctrl-C and SIGTERM); ``progress`` gets a
    :class:`Listening` once the socket listens, then a :class:`Logged` per line for the log.
    Off loopback ``keys`` (a `dlo keys` folder) are required."""
    import zmq

    require_keys_off_loopback(address, keys, "--address", "--keys")
    context = zmq.Context()
    socket = context.socket(zmq.REP)
    socket.setsockopt(zmq.LINGER, 0)
    socket.setsockopt(zmq.MAXMSGSIZE, protocol.MAX_MESSAGE_BYTES)
    progress = progress or ignore
    authenticator = monitor = None
    try:
        if keys is not None:
            authenticator = secure_cell(context, socket, keys)
        try:
            socket.bind(address)
        except zmq.ZMQError as exc:
            raise BadInput(f"--address {address}: cannot listen there ({exc})") from None
        monitor = socket.get_monitor_socket(HANDSHAKE_FAILURES)
        bound = socket.getsockopt_string(zmq.LAST_ENDPOINT)
        progress(Listening("request", 0, values={"address": bound}))
        _loop(CellServer(handler, idle_s, progress), socket, monitor, cancel or CancelToken())
    finally:
        if monitor is not None:
            socket.disable_monitor()
            monitor.close()
        socket.close()
        if authenticator is not None:
            authenticator.stop()
        context.term()


def _loop(server: CellServer, socket: Any, monitor: Any, cancel: CancelToken) -> None:
    import zmq

    poller = zmq.Poller()
    poller.register(socket, zmq.POLLIN)
    poller.register(monitor, zmq.POLLIN)
    handshakes = _HandshakeLog()
    while True:
        cancel.raise_if_cancelled()
        ready = dict(poller.poll(POLL_MS))
        if monitor in ready and (line := handshakes.failed(monitor)) is not None:
            server.log(line)
        if socket not in ready:
            server.expire_idle()
            continue
        socket.send(server.answer(socket.recv_multipart()))


#: the socket events of a client that failed to connect (ZeroMQ's monitor)
HANDSHAKE_FAILURES = 0x0800 | 0x2000 | 0x4000  # FAILED_NO_DETAIL, FAILED_PROTOCOL, FAILED_AUTH
#: a refused client retries every 100 ms: its repeats within this long are counted, not logged
REPEATS_QUIET_S = 10.0
_WHY_FAILED = {
    0x0800: "a client without this cell's keys, of another protocol, or one that hung up",
    0x2000: "a client without this cell's keys (or not speaking ZeroMQ's CURVE) was refused",
    0x4000: "a client whose key this cell's --keys folder does not hold was refused",
}


class _HandshakeLog:
    """One log line per failed handshake the monitor reports; the same failure again within
    :data:`REPEATS_QUIET_S` is counted, and the next line says how many."""

    def __init__(self) -> None:
        self.last, self.quiet_until, self.repeats = "", 0.0, 0

    def failed(self, monitor: Any) -> str | None:
        """The log line of the failure the monitor holds; None for a repeat kept quiet."""
        from zmq.utils.monitor import recv_monitor_message

        event = recv_monitor_message(monitor)
        why = _WHY_FAILED.get(event["event"], f"socket event {event['event']}")
        now = time.monotonic()
        if why == self.last and now < self.quiet_until:
            self.repeats += 1
            return None
        more = f" (the failure before repeated {self.repeats} times)" if self.repeats else ""
        self.last, self.quiet_until, self.repeats = why, now + REPEATS_QUIET_S, 0
        return f"a handshake failed: {why}{more}"
