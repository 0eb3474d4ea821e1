"""Process hygiene: SIGTERM ends a command like SIGINT (finished work saved), and worker
processes end when the process that started them dies, however it dies."""

from __future__ import annotations

import os
import signal
import sys
import threading
import time
from typing import Any

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


def exit_with_parent(parent: int, poll_seconds: float = 1.0) -> None:
    """Call in a worker process (a pool's ``initializer``, ``initargs=(os.getpid(),)``): it
    exits as soon as the process ``parent`` is gone. On Linux the kernel sends SIGKILL
    (``PR_SET_PDEATHSIG``); elsewhere, and as a second line, a daemon thread notices the
    worker was re-parented."""
    _ask_kernel_for_sigkill_on_parent_death()
    if os.getppid() != parent:  # the parent died before we asked
        os._exit(1)

    def watch() -> None:
        while os.getppid() == parent:
            time.sleep(poll_seconds)
        os._exit(1)

    threading.Thread(target=watch, name="exit-with-parent", daemon=True).start()


def pool_initializer() -> dict[str, Any]:
    """``initializer`` and ``initargs`` for a process pool whose workers end with this one."""
    return {"initializer": exit_with_parent, "initargs": (os.getpid(),)}


def _ask_kernel_for_sigkill_on_parent_death() -> None:
    if not sys.platform.startswith("linux"):
        return
    try:
        import ctypes

        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(1, signal.SIGKILL, 0, 0, 0)  # 1 = PR_SET_PDEATHSIG
    except (OSError, AttributeError):
        pass
