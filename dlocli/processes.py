"""Process hygiene: SIGTERM ends a command like SIGINT (finished work saved), a stop is never
lost, and worker processes end when the process that started them dies, however it dies.

A signal handler's exception is raised wherever the main thread happens to be; when that is a
destructor or a weakref callback, Python prints "Exception ignored" and carries on, and the
stop is lost (a collect then ran on for its 100,000 episodes). So the handlers also record the
stop in the process's :class:`~dlocli.cancel.CancelToken` (:func:`signal_token`, which the
commands hand to the library's long computations: fits, envs, replays; the library never reads
it itself), and the commands' own loops call :func:`raise_if_stopped` at their safe points
(each episode, each request) to raise it again."""

from __future__ import annotations

import os
import signal
import sys
import threading
import time
from typing import Any

from dlocli.cancel import CancelToken
from dlocli.threads import set_worker_threads

#: the PID of the `dlo` process; forked workers inherit the handler but not this role
_main_pid: int | None = None


class Terminated(KeyboardInterrupt):
    """SIGTERM arrived (from `timeout`, systemd, a cluster scheduler): handled like Ctrl-C,
    with exit code 143."""


class _SignalStops(CancelToken):
    """The stop that arrived in the main process and may have been swallowed; a forked worker
    that inherited it never raises it (its own signals end it)."""

    @property
    def reason(self) -> type[BaseException] | None:
        return self._reason if os.getpid() == _main_pid else None


_stops = _SignalStops()


def signal_token() -> CancelToken:
    """The token the process's stop signals (Ctrl-C, SIGTERM) cancel: what a command hands to
    the library's long computations."""
    return _stops


def _on_sigterm(signum: int, frame: object) -> None:
    if os.getpid() != _main_pid:  # a forked worker: die as SIGTERM means
        signal.signal(signal.SIGTERM, signal.SIG_DFL)
        os.kill(os.getpid(), signal.SIGTERM)
        return
    _stop(Terminated)


def _on_sigint(signum: int, frame: object) -> None:
    if os.getpid() != _main_pid:  # a forked worker: Python's own behaviour
        raise KeyboardInterrupt
    _stop(KeyboardInterrupt)


def _stop(kind: type[KeyboardInterrupt]) -> None:
    _stops.cancel(kind)
    raise kind


def raise_if_stopped() -> None:
    """Raise the stop (Ctrl-C, SIGTERM) that arrived but was swallowed where it landed; a
    no-op otherwise. Cheap: call it once per step of any long loop."""
    _stops.raise_if_cancelled()


def pending_stop() -> type[KeyboardInterrupt] | None:
    """The stop that arrived and was not yet handled (None if none): an error that follows
    a stop (a worker pool broken by Ctrl-C) is the stop, not a failure."""
    return _stops.reason  # type: ignore[return-value]  # only _stop cancels it, with one


def stop_handled() -> None:
    """The stop reached the command's handler: forget it (finishing work may still step)."""
    _stops.clear()


def handle_stop_signals() -> None:
    """In this (the main) process: SIGTERM raises :class:`Terminated`, SIGINT raises
    KeyboardInterrupt, and both are remembered for :func:`raise_if_stopped`."""
    global _main_pid
    _main_pid = os.getpid()
    signal.signal(signal.SIGTERM, _on_sigterm)
    signal.signal(signal.SIGINT, _on_sigint)


def exit_with_parent(parent: int, poll_seconds: float = 1.0) -> None:
    """Call in a worker process (a pool's ``initializer``, ``initargs=(os.getpid(),)``): it
    exits as soon as the process ``parent`` is gone. On Linux the kernel sends SIGKILL
    (``PR_SET_PDEATHSIG``); elsewhere, and as a second line, a daemon thread notices the
    worker was re-parented.

    A forked worker inherits :func:`_on_sigterm`, which runs only in the main thread, and only
    once that thread gets back to Python. When the kernel hands SIGTERM to another thread (the
    watcher below) while the main thread waits in C on a pool's queue lock, nothing handles it:
    ``Pool.terminate`` then joined such a worker forever (a CI run hung in ``dlo collect``). The
    worker therefore takes the kernel's default action, whichever thread receives it.

    Ctrl-C reaches every process of the terminal's group: a worker also ends at once on
    SIGINT, without Python's KeyboardInterrupt traceback; the main process reports the stop."""
    signal.signal(signal.SIGTERM, signal.SIG_DFL)
    signal.signal(signal.SIGINT, signal.SIG_DFL)
    _ask_kernel_for_sigkill_on_parent_death()
    if os.getppid() != parent:  # the parent died before we asked
        os._exit(1)

    def watch() -> None:
        while os.getppid() == parent:
            time.sleep(poll_seconds)
        os._exit(1)

    threading.Thread(target=watch, name="exit-with-parent", daemon=True).start()


def start_worker(parent: int, threads: int) -> None:
    """A pool worker's start: ``threads`` threads with passive waiting
    (:func:`dlocli.threads.set_worker_threads`, before the tasks import torch), and an end
    with the process ``parent`` (:func:`exit_with_parent`)."""
    set_worker_threads(threads)
    exit_with_parent(parent)


def pool_initializer(threads: int = 1) -> dict[str, Any]:
    """``initializer`` and ``initargs`` for a process pool whose workers run ``threads``
    threads each and end with this process."""
    return {"initializer": start_worker, "initargs": (os.getpid(), threads)}


def _ask_kernel_for_sigkill_on_parent_death() -> None:
    if not sys.platform.startswith("linux"):
        return
    try:
        import ctypes

        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(1, signal.SIGKILL, 0, 0, 0)  # 1 = PR_SET_PDEATHSIG
    except (OSError, AttributeError):
        pass
