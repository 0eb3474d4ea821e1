"""Cancellation handed to the library as a token: a long computation (a fit) is given a
:class:`CancelToken` and checks it at its safe points (each gradient step); whoever holds the
token cancels it. The commands hand it the process's stop signals
(:func:`dlocli.processes.signal_token`); Python callers make their own or pass none."""

from __future__ import annotations


class CancelToken:
    """A request to stop: :meth:`cancel` asks, :meth:`raise_if_cancelled` raises the
    request's exception once, where the computation can stop safely."""

    def __init__(self) -> None:
        self._reason: type[BaseException] | None = None

    def cancel(self, reason: type[BaseException] = KeyboardInterrupt) -> None:
        """Ask the computation to stop by raising ``reason`` at its next safe point."""
        self._reason = reason

    @property
    def reason(self) -> type[BaseException] | None:
        """The exception a cancellation raises (None: not cancelled)."""
        return self._reason

    def clear(self) -> None:
        """Forget the request (its stop was handled)."""
        self._reason = None

    def raise_if_cancelled(self) -> None:
        """Raise the requested stop, once; a no-op when none was asked. Cheap: call it at
        every safe point of a long loop."""
        reason = self.reason
        if reason is not None:
            self.clear()
            raise reason
