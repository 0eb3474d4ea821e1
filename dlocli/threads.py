"""How many threads each process runs: torch, OpenMP and BLAS threads chosen from the CPUs
this process may use (its affinity mask and a cgroup CPU quota) and the number of processes
sharing them, so that N processes on C CPUs never run more than C busy threads between them.

Idle OpenMP threads wait passively (they sleep instead of spinning): where other processes
share the cores, a spinning thread burns the time slice its partner needs to reach the same
barrier, and a model update slows by tens of times instead of by the share of the CPU it
lost. The user's own ``OMP_*`` variables and an explicit ``--threads`` win over the choice;
an override that oversubscribes the CPUs is warned about once per run.
"""

from __future__ import annotations

import math
import os
import sys
from collections.abc import Iterator
from contextlib import contextmanager
from functools import cache
from pathlib import Path

#: the variables that size the thread pools of OpenMP (torch), MKL and OpenBLAS (numpy)
THREAD_VARIABLES = ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS")
#: idle OpenMP threads sleep at once: GNU OpenMP (torch's) and Intel OpenMP
PASSIVE_WAITING = {"OMP_WAIT_POLICY": "PASSIVE", "KMP_BLOCKTIME": "0"}
CGROUP_ROOT = Path("/sys/fs/cgroup")


# ----------------------------------------------------------------------------- the choice
def quota_cpus(cpu_max: str) -> float | None:
    """The CPUs a cgroup v2 ``cpu.max`` line ("QUOTA PERIOD", or "max PERIOD" for no limit)
    allows; None for no limit or an unreadable line."""
    parts = cpu_max.split()
    if len(parts) != 2 or parts[0] == "max":
        return None
    try:
        quota, period = int(parts[0]), int(parts[1])
    except ValueError:
        return None
    return quota / period if quota > 0 and period > 0 else None


def usable_cpus(affinity: int, quota: float | None = None) -> int:
    """Whole CPUs to plan threads for: the affinity mask's, fewer under a quota (rounded
    down: a thread beyond the quota is throttled), never less than one."""
    cpus = affinity if quota is None else min(affinity, math.floor(quota))
    return max(1, cpus)


def threads_per_process(cpus: int, processes: int = 1) -> int:
    """Threads each of ``processes`` busy processes may run on ``cpus`` CPUs (at least 1)."""
    return max(1, cpus // max(1, processes))


def oversubscribes(threads: int, processes: int, cpus: int) -> bool:
    """Whether ``processes`` x ``threads`` busy threads exceed ``cpus`` CPUs."""
    return threads * processes > cpus


def thread_environment(threads: int) -> dict[str, str]:
    """The variables that give a process ``threads`` threads and passive waiting."""
    return dict.fromkeys(THREAD_VARIABLES, str(threads)) | PASSIVE_WAITING


# ----------------------------------------------------------------------------- this machine
@cache
def machine_cpus() -> int:
    """The CPUs this process may use: its affinity mask, and its cgroup's CPU quota."""
    affinity = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else None
    return usable_cpus(affinity or os.cpu_count() or 1, _cgroup_quota())


def _cgroup_quota() -> float | None:
    """The tightest CPU quota of this process's cgroup v2 and its parents (None: none)."""
    try:
        lines = Path("/proc/self/cgroup").read_text().splitlines()
    except OSError:
        return None
    own = next((line[3:] for line in lines if line.startswith("0::")), None)
    if own is None:
        return None
    quotas = []
    directory = CGROUP_ROOT / own.lstrip("/")
    for folder in (directory, *directory.parents):
        try:
            quota = quota_cpus((folder / "cpu.max").read_text())
        except OSError:
            quota = None
        if quota is not None:
            quotas.append(quota)
        if folder == CGROUP_ROOT:
            break
    return min(quotas) if quotas else None


def fit_this_process() -> dict[str, str]:
    """Before torch or numpy is imported (the `dlo` entry point): size this process's thread
    pools to the CPUs it may use, with passive waiting; variables the user set are kept
    (one thread count set is the user's choice for every pool: torch reads MKL's too).
    Returns what was set."""
    wanted = thread_environment(machine_cpus())
    if any(name in os.environ for name in THREAD_VARIABLES):
        wanted = PASSIVE_WAITING
    added = {name: value for name, value in wanted.items() if name not in os.environ}
    os.environ.update(added)
    return added


def set_worker_threads(threads: int) -> None:
    """In a worker process: ``threads`` threads and passive waiting, before torch or numpy
    start their pools (later imports read the variables), and for torch if already started."""
    os.environ.update(thread_environment(threads))
    torch = sys.modules.get("torch")
    if torch is not None:
        torch.set_num_threads(threads)


@contextmanager
def torch_threads(threads: int) -> Iterator[None]:
    """Run the block with ``threads`` torch CPU threads, then restore the previous number."""
    import torch

    before = torch.get_num_threads()
    torch.set_num_threads(threads)
    try:
        yield
    finally:
        torch.set_num_threads(before)


# ----------------------------------------------------------------------------- overrides
_warned = False


def warn_if_oversubscribed(threads: int, processes: int, flag: str = "--threads") -> bool:
    """One line on stderr, once per process, when ``processes`` x ``threads`` (an override)
    exceed this machine's CPUs; True if it warned."""
    global _warned
    cpus = machine_cpus()
    if _warned or not oversubscribes(threads, processes, cpus):
        return False
    _warned = True
    sys.stderr.write(
        f"warning: {flag} {threads} x {processes} process(es) = {threads * processes} busy "
        f"threads on {cpus} CPU(s): they will wait on each other; lower {flag} (or the "
        "workers) to fit\n"
    )
    return True
