"""Where the jobs of ``dlo bench`` run: local processes, or Ray tasks on a cluster.

An executor is connected first and closed after (:func:`open_executor`); its ``run`` takes the
resolved spec (JSON) and a list of :class:`dlocli.bench.jobs.Job` and yields ``(job, result)``
as jobs finish, where ``result`` is :func:`dlocli.bench.jobs.run_job`'s dict or the exception
the job raised (the caller saves finished jobs and reports failed ones). Both executors call
the same :func:`run_job`, which reseeds everything it uses, so the same seeds give the same
results on either. A new executor is one class with ``connect``, ``run`` and ``close``.

Ray is optional (``pip install 'dlocli[ray]'``) and imported only here, when used. Each job is
one Ray task with one CPU; its results travel back to the driver, which writes the files, so
the cluster's nodes need dlocli installed but no shared file system.
"""

from __future__ import annotations

import os
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

from dlocli.bench.jobs import Job, run_job
from dlocli.errors import BadInput
from dlocli.processes import pool_initializer

Outcome = tuple[Job, "dict[str, Any] | BaseException"]
#: Ray's connection window in seconds when joining a cluster (Ray's default: about 20 tries)
WINDOW_VARIABLE = "RAY_gcs_server_port_wait_time_s"


def _run_inline(spec_json: str, job: Job) -> dict[str, Any] | BaseException:
    try:
        return run_job(spec_json, job.agent, job.seed, job.scratch)
    except Exception as exc:  # a failed job is reported; the others go on
        return exc


class LocalExecutor:
    """A pool of ``workers`` processes (spawned), or this process for a single worker."""

    def __init__(self, workers: int | None = None) -> None:
        self.workers = workers or os.cpu_count() or 1

    def connect(self) -> None:
        """Nothing to connect to: processes start in :meth:`run`."""

    def close(self) -> None:
        """Nothing to release: the pool ends with :meth:`run`."""

    def run(self, spec_json: str, jobs: list[Job]) -> Iterator[Outcome]:
        workers = min(self.workers, len(jobs))
        if workers <= 1:
            for job in jobs:
                yield job, _run_inline(spec_json, job)
            return
        yield from self._pool(spec_json, jobs, workers)

    def _pool(self, spec_json: str, jobs: list[Job], workers: int) -> Iterator[Outcome]:
        import multiprocessing as mp
        from concurrent.futures import ProcessPoolExecutor, as_completed

        # spawn: forking a process whose torch already started OpenMP threads can hang
        pool = ProcessPoolExecutor(
            workers, mp_context=mp.get_context("spawn"), **pool_initializer()
        )
        try:
            futures = {
                pool.submit(run_job, spec_json, job.agent, job.seed, job.scratch): job
                for job in jobs
            }
            for future in as_completed(futures):
                error = future.exception()
                yield futures[future], error if error is not None else future.result()
        finally:
            pool.shutdown(cancel_futures=True)


class RayExecutor:
    """One Ray task per job on the cluster at ``address`` (None: a local Ray instance)."""

    #: seconds Ray may try to reach a cluster address before the address is refused
    CONNECT_WINDOW_S = "5"

    def __init__(self, workers: int | None = None, address: str | None = None) -> None:
        self.workers = workers
        self.address = address
        self._started = False

    def connect(self) -> None:
        """Join the cluster (or start a local instance); BadInput if the address fails."""
        import logging

        import ray

        if ray.is_initialized():
            return
        options: dict[str, Any] = {
            "include_dashboard": False,
            "log_to_driver": False,
            "logging_level": logging.ERROR,
        }
        if self.address is None:
            ray.init(num_cpus=self.workers or os.cpu_count() or 1, **options)
            self._started = True
            return
        preset = WINDOW_VARIABLE in os.environ  # the user's own window wins
        os.environ.setdefault(WINDOW_VARIABLE, self.CONNECT_WINDOW_S)
        try:
            with _stderr_silenced():  # Ray's core logs every failed attempt
                ray.init(address=self.address, **options)
        except ConnectionError as exc:
            raise BadInput(
                f"Ray address {self.address} does not answer as a Ray cluster "
                "(start it with `ray start --head`) or drop --ray-address"
            ) from exc
        finally:
            if not preset:
                os.environ.pop(WINDOW_VARIABLE, None)
        self._started = True

    def close(self) -> None:
        """Disconnect (and stop a local instance) if :meth:`connect` started Ray."""
        if self._started:
            import ray

            ray.shutdown()
            self._started = False

    def run(self, spec_json: str, jobs: list[Job]) -> Iterator[Outcome]:
        import ray

        self.connect()
        task = ray.remote(num_cpus=1, max_retries=0)(run_job)
        pending = {task.remote(spec_json, job.agent, job.seed, None): job for job in jobs}
        while pending:
            (ref,), _ = ray.wait(list(pending), num_returns=1)
            job = pending.pop(ref)
            yield job, self._result(ray, ref)

    @staticmethod
    def _result(ray: Any, ref: Any) -> dict[str, Any] | BaseException:
        try:
            return ray.get(ref)
        except ray.exceptions.RayError as exc:
            return exc


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
    try:
        import ray  # noqa: F401
    except ImportError as exc:
        raise BadInput(
            "--executor ray: Ray is not installed; pip install 'dlocli[ray]' "
            "or use --executor local"
        ) from exc
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
        socket.create_connection((host, int(port)), timeout=timeout).close()
    except OSError as exc:
        raise BadInput(
            f"Ray address {address} does not answer ({exc.strerror or exc}); start "
            "the cluster (`ray start --head`) or drop --ray-address"
        ) from exc


@contextmanager
def open_executor(spec: Any) -> Iterator[LocalExecutor | RayExecutor]:
    """The spec's executor, connected (Ray) before the caller writes anything; closed after."""
    executor = (
        RayExecutor(spec.workers, spec.ray_address)
        if spec.executor == "ray"
        else LocalExecutor(spec.workers)
    )
    executor.connect()
    try:
        yield executor
    finally:
        executor.close()
