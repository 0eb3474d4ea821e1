"""`dlo serve`: a simulator served as a cell over the dlocli-cell protocol."""

from __future__ import annotations

from dlocli.bridge.cell import serve as serve_cell
from dlocli.bridge.server import Listening, Logged
from dlocli.bridge.spec import ServeSpec
from dlocli.camera_spec import CameraSpec
from dlocli.cli.common import handle_errors
from dlocli.cli.flags import RunFlags, spec_flags
from dlocli.events import Event
from dlocli.extras import require
from dlocli.processes import signal_token, stop_handled


def banner(spec: ServeSpec, address: str) -> str:
    """The line `dlo serve` says once it listens: the rod, the clock, the address, and who
    may come in and what they get (keys, camera, a session's idle time)."""
    mode = "real time" if spec.realtime else "lockstep"
    keys = f"keys on ({spec.keys})" if spec.keys is not None else "keys off (loopback only)"
    camera = spec.task.observation.camera or CameraSpec()
    seen = f"camera on ({camera.width} x {camera.height} px)" if spec.camera else "camera off"
    return (
        f"serving {spec.backend.name} ({spec.backend.rod.n_segments} segments, "
        f"{spec.control_dt:g} s period, {mode}) at {address}; {keys}; {seen}; a session ends "
        f"after {spec.session_idle_s:g} s without a request; Ctrl-C stops"
    )


@handle_errors
@spec_flags(ServeSpec)
def serve(
    run: RunFlags,
) -> None:
    """Serve a simulator as a cell at --address until stopped (Ctrl-C, SIGTERM: exit 0):
    controllers step it with `dlo control --cell ADDRESS`, as they would a robot. One
    controller at a time owns it (from its hello to its bye, or --session-idle-s without a
    request); off loopback it needs --keys (`dlo keys --out DIR`)."""
    import typer

    spec = run.spec()
    require("bridge", "dlo serve")

    bound = [spec.address]

    def report(event: Event) -> None:
        if isinstance(event, Listening):
            bound[0] = event.address  # tcp://HOST:* names its port only once bound
            typer.echo(banner(spec, event.address), err=True)
        elif isinstance(event, Logged):
            typer.echo(f"dlo serve: {event.line}", err=True)

    try:
        serve_cell(spec, report, signal_token())
    except KeyboardInterrupt:  # Ctrl-C or SIGTERM: how a server is meant to end
        stop_handled()
        typer.echo(f"dlo serve: stopped serving at {bound[0]}", err=True)
