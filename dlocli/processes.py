"""Process hygiene: SIGTERM ends a command like SIGINT (finished work saved), and worker
processes end when the process that started them dies, however it dies."""

from __future__ import annotations

import os
import signal
import threading
import time

#: the PID of the `dlo` process; forked workers inherit the handler but not this role
_main_pid: int | None = None


class Terminated(KeyboardInterrupt):
    """SIGTERM arrived (from `timeout`, systemd, a cluster scheduler): handled like Ctrl-C,
    with exit code 143."""


def _on_sigterm(signum: int, frame: object) -> None:
    if os.getpid() != _main_pid:  # a forked worker: die as SIGTERM means
        signal.signal(signal.SIGTERM, signal.SIG_DFL)
        os.kill(os.getpid(), signal.SIGTERM)
        return
    raise Terminated


def handle_sigterm() -> None:
    """Make SIGTERM raise :class:`Terminated` in this (the main) process."""
    global _main_pid
    _main_pid = os.getpid()
    signal.signal(signal.SIGTERM, _on_sigterm)


def exit_with_parent(poll_seconds: float = 1.0) -> None:
    """Call in a worker process: it exits as soon as its parent is gone (then the worker is
    re-parented, so its parent PID changes). A daemon thread polls; the work is untouched."""
    parent = os.getppid()

    def watch() -> None:
        while os.getppid() == parent:
            time.sleep(poll_seconds)
        os._exit(1)

    threading.Thread(target=watch, name="exit-with-parent", daemon=True).start()
