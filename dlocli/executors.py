"""Where independent tasks run: local processes, or Ray tasks on a cluster (the jobs of
``dlo bench``, the trials and reference episodes of ``dlo online``, the replays of each
``dlo calibrate`` generation).

An executor is connected first and closed after (:func:`open_executor`). Its ``map(fn,
calls)`` runs ``fn(*args)`` for every ``args`` in ``calls`` and yields ``(index, result)`` as
calls finish, where ``result`` is what ``fn`` returned or the exception it raised (the caller
saves finished work and reports failures). ``share(value)`` makes a large argument that many
calls take travel once (a Ray object; the value itself locally). Results travel back to the
driver, which writes the files, so the nodes of a cluster need dlocli installed but no shared
file system. The functions reseed everything they use, so the same seeds give the same
results on either executor. ``calls_device(device)`` says on which torch device the calls
can run what the driver runs on ``device``. A new executor is one class with ``connect``,
``share``, ``map``, ``calls_device`` and ``close``, registered in :data:`EXECUTORS`.

Each call runs with ``threads`` threads (one CPU of Ray's scheduler per thread); the local
pool's workers start with them, and with passive waiting (:mod:`dlocli.threads`).

Ray is optional (``pip install 'dlocli[ray]'``) and imported only here, when used.
"""

from __future__ import annotations

import os
import subprocess
import sys
from collections.abc import Callable, Iterator
from concurrent.futures import ProcessPoolExecutor
from contextlib import contextmanager, suppress
from typing import Any, Literal

from pydantic import Field, ValidationInfo, field_validator

from dlocli.errors import BadInput, DloError
from dlocli.extras import require
from dlocli.limits import MAX_PROCESSES
from dlocli.processes import pool_initializer
from dlocli.specs import Spec
from dlocli.threads import machine_cpus, set_worker_threads

Outcome = tuple[int, Any]
#: Ray's connection window in seconds when joining a cluster (Ray's default: about 20 tries)
WINDOW_VARIABLE = "RAY_gcs_server_port_wait_time_s"


class ExecutorChoice(Spec):
    """The fields that say where a command's independent work runs (``--executor``,
    ``--ray-address``); every command with an executor has them, with these meanings."""

    executor: Literal["local", "ray"] = Field(
        "local", description="Where jobs run: local processes, or Ray tasks."
    )
    ray_address: str | None = Field(
        None,
        description="Ray cluster to join (host:port, ray://host:port or auto); None = "
        "start a local Ray instance.",
    )

    @field_validator("workers", check_fields=False)
    @classmethod
    def _workers_of_this_machine(cls, value: int | None, info: ValidationInfo) -> int | None:
        """Workers that run here (local processes, a local Ray instance) are at most this
        machine's CPUs; on a cluster joined at an address, its CPUs bound them once joined
        (:meth:`RayExecutor.connect`)."""
        on_cluster = info.data.get("executor") == "ray" and info.data.get("ray_address")
        if value is not None and value > MAX_PROCESSES and not on_cluster:
            raise ValueError(
                f"at most {MAX_PROCESSES} on this machine (its CPUs); a Ray cluster's own CPUs "
                "bound it with --executor ray --ray-address HEAD:PORT"
            )
        return value


class ClusterLost(DloError):
    """The executor stopped answering while work ran (a Ray cluster went down). Work that
    finished before is saved; :meth:`line` tells how to go on. Exit 1."""

    def __init__(self, where: str, cause: BaseException) -> None:
        self.where = where
        self.cause = cause
        super().__init__(self.line())

    def line(self, run_dir: Any = None) -> str:
        first = str(self.cause).strip().splitlines()[0] if str(self.cause).strip() else ""
        resume = f"--resume {run_dir}" if run_dir is not None else "--resume"
        return (
            f"{self.where} stopped answering ({type(self.cause).__name__}"
            f"{': ' + first if first else ''}); finished work is saved: restart the cluster "
            f"(`ray start --head`) or pass --executor local, and continue with {resume}"
        )


def _call(fn: Callable[..., Any], args: tuple) -> Any:
    try:
        return fn(*args)
    except Exception as exc:  # a failed call is reported; the others go on
        return exc


class LocalExecutor:
    """A pool of ``workers`` processes (spawned once, kept until :meth:`close`), or this
    process for a single worker (or a single call)."""

    run_dir: Any = None  # unused: nothing outlives this process

    def __init__(self, workers: int | None = None, threads: int = 1) -> None:
        self.workers = workers or machine_cpus()
        self.threads = threads
        self._pool: ProcessPoolExecutor | None = None

    def connect(self) -> None:
        """Nothing to connect to: processes start with the first calls."""

    def close(self) -> None:
        """End the pool's processes (queued calls are dropped)."""
        if self._pool is not None:
            self._pool.shutdown(cancel_futures=True)
            self._pool = None

    def share(self, value: Any) -> Any:
        return value

    def calls_device(self, device: str) -> str:
        """The driver's device: the pool's processes see the same GPUs."""
        return device

    def map(self, fn: Callable[..., Any], calls: list[tuple]) -> Iterator[Outcome]:
        if min(self.workers, len(calls)) <= 1:
            for index, args in enumerate(calls):
                yield index, _call(fn, args)
            return
        from concurrent.futures import as_completed

        pool = self._get_pool()
        futures = {pool.submit(fn, *args): index for index, args in enumerate(calls)}
        try:
            for future in as_completed(futures):
                error = future.exception()
                yield futures[future], error if error is not None else future.result()
        finally:
            for future in futures:
                future.cancel()

    def _get_pool(self) -> ProcessPoolExecutor:
        if self._pool is None:
            import multiprocessing as mp

            # spawn: forking a process whose torch already started OpenMP threads can hang
            self._pool = ProcessPoolExecutor(
                self.workers, mp_context=mp.get_context("spawn"), **pool_initializer(self.threads)
            )
        return self._pool


def _in_ray_worker(fn: Callable[..., Any], threads: int, *args: Any) -> Any:
    """A Ray task: ``fn(*args)`` with ``threads`` threads and passive waiting."""
    set_worker_threads(threads)
    return fn(*args)


class RayExecutor:
    """One Ray task per call on the cluster at ``address`` (None: a local Ray instance of
    ``workers`` CPUs)."""

    #: seconds Ray may try to reach a cluster address before the address is refused
    CONNECT_WINDOW_S = "5"

    def __init__(
        self, workers: int | None = None, address: str | None = None, threads: int = 1
    ) -> None:
        self.workers = workers
        self.address = address
        self.threads = threads
        self._started = False
        #: the run directory a lost cluster's line names (set by :func:`open_executor`)
        self.run_dir: Any = None
        self._watch: subprocess.Popen | None = None
        self._cpus_checked = False

    @property
    def where(self) -> str:
        return f"the Ray cluster at {self.address}" if self.address else "the local Ray instance"

    def connect(self) -> None:
        """Join the cluster (or start a local instance); BadInput if the address fails or
        the cluster has fewer CPUs than ``workers`` calls need at once."""
        import logging

        import ray

        if ray.is_initialized():
            self._refuse_more_workers_than_cpus(ray)
            return
        options: dict[str, Any] = {
            "include_dashboard": False,
            "log_to_driver": False,
            "logging_level": logging.ERROR,
        }
        if self.address is None:
            # a task asks for `threads` CPUs: fewer in all and it could never start
            ray.init(num_cpus=max(self.workers or machine_cpus(), self.threads), **options)
            self._started = True
            return
        preset = WINDOW_VARIABLE in os.environ  # the user's own window wins
        os.environ.setdefault(WINDOW_VARIABLE, self.CONNECT_WINDOW_S)
        try:
            with _stderr_silenced():  # Ray's core logs every failed attempt
                ray.init(address=self.address, **options)
        except ConnectionError as exc:
            if _refused_for_token(exc):
                raise BadInput(
                    f"the Ray cluster at {self.address} wants its authentication token: set "
                    "RAY_AUTH_MODE=token here, with the head's ~/.ray/auth_token (or "
                    "RAY_AUTH_TOKEN) on this machine"
                ) from exc
            raise BadInput(
                f"Ray address {self.address} does not answer as a Ray cluster "
                "(start it with `ray start --head`) or drop --ray-address"
            ) from exc
        finally:
            if not preset:
                os.environ.pop(WINDOW_VARIABLE, None)
        self._started = True
        self._watch = _start_watch(self.address, self.run_dir)
        self._refuse_more_workers_than_cpus(ray)

    def _refuse_more_workers_than_cpus(self, ray: Any) -> None:
        """On a cluster joined at an address: BadInput (after closing) if its CPUs cannot run
        ``workers`` calls of ``threads`` CPUs each at once. A local instance has as many CPUs
        as it was started with."""
        if self.address is None or self.workers is None or self._cpus_checked:
            return
        self._cpus_checked = True
        cpus = int(ray.cluster_resources().get("CPU", 0))
        if self.workers * self.threads > cpus:
            self.close()
            room = max(1, cpus // self.threads)
            raise BadInput(
                f"--workers {self.workers}: {self.where} has {cpus} CPUs, room for {room} "
                f"calls of {self.threads} CPU(s) at once; give --workers {room} or fewer, or "
                "add nodes to the cluster"
            )

    def close(self) -> None:
        """Disconnect (and stop a local instance) if :meth:`connect` started Ray."""
        if self._started:
            import ray

            ray.shutdown()  # first: Ray may end this process here if the cluster is gone
            self._started = False
        if self._watch is not None:
            _end_watch(self._watch)
            self._watch = None

    def calls_device(self, device: str) -> str:
        """The CPU: Ray hides the GPUs from a task that asks for none (an empty
        CUDA_VISIBLE_DEVICES), and these tasks ask for CPUs."""
        return "cpu"

    def share(self, value: Any) -> Any:
        import ray

        self.connect()
        return ray.put(value)

    def map(self, fn: Callable[..., Any], calls: list[tuple]) -> Iterator[Outcome]:
        import ray

        self.connect()
        task = ray.remote(num_cpus=self.threads, max_retries=0)(_in_ray_worker)
        pending: dict[Any, int] = {}
        try:
            pending = {
                task.remote(fn, self.threads, *args): index for index, args in enumerate(calls)
            }
            while pending:
                (ref,), _ = ray.wait(list(pending), num_returns=1)
                index = pending.pop(ref)
                yield index, self._result(ray, ref)
        except (ray.exceptions.RayError, ConnectionError) as exc:
            raise ClusterLost(self.where, exc) from exc
        finally:  # stopped early: the calls left would hold the cluster's CPUs for nothing
            for ref in pending:
                _cancel(ray, ref)

    @staticmethod
    def _result(ray: Any, ref: Any) -> Any:
        try:
            return ray.get(ref)
        except ray.exceptions.RayTaskError as exc:  # the call's own error
            return exc


# ----------------------------------------------------------------------------- a lost head
# A driver on a cluster node shares that node's Ray processes; when they die, Ray's core ends
# the driver outright (C++ exit: no Python handler, no line). A small process beside the
# driver says the line instead when the driver ends without closing it and the address no
# longer answers (a driver killed by the user while the cluster runs ends silently).
_WATCH = "import sys; from dlocli.executors import watch_driver; watch_driver(*sys.argv[1:])"
_CLOSED = b"closed"


def _start_watch(address: str, run_dir: Any) -> subprocess.Popen:
    where = [str(run_dir)] if run_dir is not None else []
    return subprocess.Popen([sys.executable, "-c", _WATCH, address, *where],
                            stdin=subprocess.PIPE)  # fmt: skip


def _end_watch(watch: subprocess.Popen) -> None:
    with suppress(OSError, subprocess.TimeoutExpired):
        watch.communicate(_CLOSED, timeout=10)
    if watch.poll() is None:
        watch.kill()


def watch_driver(address: str, run_dir: str | None = None) -> None:
    """The watch's body: wait for the driver to close stdin; if it ended without saying
    so and ``address`` no longer answers, print the lost cluster's line on stderr."""
    import signal

    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is the driver's to handle
    if sys.stdin.buffer.read() == _CLOSED:
        return
    try:
        check_ray_address(address, timeout=2.0)
        return  # the cluster answers: the driver ended for another reason
    except BadInput:
        pass
    cause = ConnectionError("Ray ended the driver as the cluster went away")
    line = ClusterLost(f"the Ray cluster at {address}", cause).line(run_dir)
    sys.stderr.write(f"error: {line}\n")


def _refused_for_token(exc: BaseException) -> bool:
    """Whether Ray's failure to connect is a cluster refusing a driver without its token
    (recent Ray heads enable token authentication; a driver sends the token only when
    RAY_AUTH_MODE=token)."""
    causes = []
    while exc is not None and len(causes) < 8:
        causes.append(str(exc))
        exc = exc.__cause__ or exc.__context__
    return any("InvalidAuthToken" in text or "AuthenticationError" in text for text in causes)


def _cancel(ray: Any, ref: Any) -> None:
    # already finished, or the cluster is gone: nothing left to stop
    with suppress(Exception):
        ray.cancel(ref, force=True)


#: executors by name (``--executor``)
EXECUTORS: dict[str, Callable[..., LocalExecutor | RayExecutor]] = {
    "local": lambda workers, address, threads: LocalExecutor(workers, threads),
    "ray": lambda workers, address, threads: RayExecutor(workers, address, threads),
}


@contextmanager
def _stderr_silenced() -> Iterator[None]:
    """Send file descriptor 2 (C++ logs included) to /dev/null for the block."""
    saved = os.dup(2)
    with open(os.devnull, "w") as null:
        os.dup2(null.fileno(), 2)
        try:
            yield
        finally:
            os.dup2(saved, 2)
            os.close(saved)


# ----------------------------------------------------------------------------- checks
def check_executor(executor: str, ray_address: str | None) -> None:
    """Ray requested: installed, and its address (if any) answers (BadInput otherwise)."""
    if executor == "local":
        if ray_address is not None:
            raise BadInput("--ray-address needs --executor ray")
        return
    require("ray", "--executor ray", "use --executor local")
    if ray_address is not None:
        check_ray_address(ray_address)


def check_ray_address(address: str, timeout: float = 3.0) -> None:
    """Open a TCP connection to a host:port address (``auto`` is left to Ray)."""
    import socket

    if address == "auto":
        return
    host, sep, port = address.removeprefix("ray://").rpartition(":")
    if not sep or not host or not port.isdigit():
        raise BadInput(f"--ray-address {address!r} is not host:port, ray://host:port or auto")
    try:
        connection = socket.create_connection((host, int(port)), timeout=timeout)
    except OSError as exc:
        raise BadInput(
            f"Ray address {address} does not answer ({exc.strerror or exc}); start "
            "the cluster (`ray start --head`) or drop --ray-address"
        ) from exc
    with connection:
        speaks = _speaks_grpc(connection, timeout)
    if not speaks or not _answers_a_call(f"{host}:{port}", timeout):
        raise BadInput(
            f"Ray address {address} listens but does not answer as a Ray cluster within "
            f"{timeout:g} s (Ray speaks gRPC there); give the head's address or drop "
            "--ray-address"
        )


#: an HTTP/2 client's first bytes: the connection preface, then an empty SETTINGS frame
_HTTP2_HELLO = b"PRI * HTTP/2.0\r\n\r\nSM\r\n\r\n" + bytes([0, 0, 0, 4, 0, 0, 0, 0, 0])
_SETTINGS = 4


def _speaks_grpc(connection: Any, timeout: float) -> bool:
    """Whether the server answers an HTTP/2 preface with its SETTINGS frame, as every gRPC
    server (Ray's GCS, its client server) must first; anything else would make Ray wait."""
    connection.settimeout(timeout)
    try:
        connection.sendall(_HTTP2_HELLO)
        header = b""
        while len(header) < 9:
            chunk = connection.recv(9 - len(header))
            if not chunk:
                return False
            header += chunk
    except OSError:  # a timeout included
        return False
    return header[3] == _SETTINGS


def _answers_a_call(target: str, timeout: float) -> bool:
    """Whether a gRPC server at ``target`` answers a call within ``timeout`` seconds: every
    one answers a method it does not know (UNIMPLEMENTED); a server that greets and then
    stays silent would make ``ray.init`` wait forever."""
    import grpc

    channel = grpc.insecure_channel(target, options=[("grpc.enable_http_proxy", 0)])  # as Ray
    try:
        channel.unary_unary("/probe.NoSuchService/Answer")(b"", timeout=timeout)
    except grpc.RpcError as exc:
        return exc.code() not in (grpc.StatusCode.DEADLINE_EXCEEDED,
                                  grpc.StatusCode.UNAVAILABLE)  # fmt: skip
    finally:
        channel.close()
    return True


@contextmanager
def open_executor(spec: Any, threads: int = 1) -> Iterator[LocalExecutor | RayExecutor]:
    """The executor a spec names (its ``executor``, ``workers`` and ``ray_address``), each
    call with ``threads`` threads, connected (Ray) before the caller writes anything; closed
    after."""
    executor = EXECUTORS[spec.executor](spec.workers, spec.ray_address, threads)
    executor.run_dir = spec.out
    executor.connect()
    try:
        yield executor
    finally:
        executor.close()
