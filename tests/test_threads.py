"""Threads that fit the machine: the choice from CPUs, quota and processes, what worker
processes start with, and one warning for an override that oversubscribes."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

from dlocli import threads
from dlocli.threads import (
    oversubscribes,
    quota_cpus,
    thread_environment,
    threads_per_process,
    usable_cpus,
)


@pytest.mark.parametrize(
    ("line", "cpus"),
    [("max 100000\n", None), ("200000 100000\n", 2.0), ("150000 100000", 1.5),
     ("50000 100000", 0.5), ("", None), ("garbage", None), ("-1 100000", None)],
)  # fmt: skip
def test_cgroup_quota_is_read_from_cpu_max(line, cpus):
    assert quota_cpus(line) == cpus


@pytest.mark.parametrize(
    ("affinity", "quota", "cpus"),
    [(8, None, 8), (8, 2.0, 2), (8, 1.5, 1), (8, 0.5, 1), (2, 16.0, 2), (1, None, 1)],
)
def test_usable_cpus_take_the_tighter_of_affinity_and_quota(affinity, quota, cpus):
    assert usable_cpus(affinity, quota) == cpus


@pytest.mark.parametrize("cpus", [1, 2, 3, 8, 64])
@pytest.mark.parametrize("processes", [1, 2, 3, 5, 8])
def test_processes_never_run_more_busy_threads_than_cpus(cpus, processes):
    each = threads_per_process(cpus, processes)
    assert each >= 1
    # more processes than CPUs: one thread each is the least; otherwise they fit
    assert each * processes <= cpus or each == 1
    assert not oversubscribes(each, processes, cpus) or processes > cpus


def test_thread_environment_sizes_every_pool_and_waits_passively():
    env = thread_environment(3)
    assert env["OMP_NUM_THREADS"] == env["MKL_NUM_THREADS"] == env["OPENBLAS_NUM_THREADS"] == "3"
    assert env["OMP_WAIT_POLICY"] == "PASSIVE" and env["KMP_BLOCKTIME"] == "0"


def test_machine_cpus_is_within_the_affinity_mask():
    assert 1 <= threads.machine_cpus() <= len(os.sched_getaffinity(0))


_CHILD = """
import os, sys
from dlocli.processes import start_worker
start_worker(os.getppid(), 1)
import torch
print(torch.get_num_threads(), os.environ["OMP_WAIT_POLICY"])
"""


def test_a_worker_starts_with_its_threads_before_torch():
    """A pool worker gets its threads and passive waiting before it imports torch, whatever
    the process that started it had (here: 4 threads, active waiting)."""
    env = {**os.environ, "OMP_NUM_THREADS": "4", "OMP_WAIT_POLICY": "ACTIVE"}
    out = subprocess.run([sys.executable, "-c", _CHILD], env=env, capture_output=True,
                         text=True, check=True, timeout=120).stdout.split()  # fmt: skip
    assert out == ["1", "PASSIVE"]


_DRIVER = """
import os
from dlocli.threads import fit_this_process, machine_cpus
fit_this_process()
import torch
print(torch.get_num_threads(), machine_cpus(), os.environ["OMP_WAIT_POLICY"])
"""


def test_the_driver_fits_the_machine_and_keeps_the_users_choice():
    env = {k: v for k, v in os.environ.items() if not k.startswith(("OMP_", "MKL_", "KMP_"))}
    run = [sys.executable, "-c", _DRIVER]
    fitted = subprocess.run(run, env=env, capture_output=True, text=True, check=True,
                            timeout=120).stdout.split()  # fmt: skip
    assert fitted[0] == fitted[1] and fitted[2] == "PASSIVE"
    env |= {"OMP_NUM_THREADS": "1", "OMP_WAIT_POLICY": "ACTIVE"}
    kept = subprocess.run(run, env=env, capture_output=True, text=True, check=True,
                          timeout=120).stdout.split()  # fmt: skip
    assert kept[0] == "1" and kept[2] == "ACTIVE"


def test_an_oversubscribing_override_is_warned_about_once(monkeypatch, capsys):
    monkeypatch.setattr(threads, "_warned", False)
    monkeypatch.setattr(threads, "machine_cpus", lambda: 2)
    assert not threads.warn_if_oversubscribed(1, processes=2)
    assert threads.warn_if_oversubscribed(2, processes=2)
    assert not threads.warn_if_oversubscribed(4, processes=2)
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "--threads 2 x 2 process(es) = 4 busy threads on 2" in err


def test_torch_threads_are_restored_after_the_block():
    import torch

    before = torch.get_num_threads()
    with threads.torch_threads(1):
        assert torch.get_num_threads() == 1
    assert torch.get_num_threads() == before
