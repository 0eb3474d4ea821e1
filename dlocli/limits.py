"""What one run may ask of the machine: counts, seeds, processes and memory.

Counts are bounded in the specs by pydantic constraints built from these constants, so the
limit is named in the error and refused before any work starts. Sizes whose memory depends
on several fields (a model's widths, a replay buffer) are estimated and checked with
:func:`refuse_unless_fits` against the memory this process may use.
"""

from __future__ import annotations

import os
import resource

from dlocli.errors import BadInput

#: most repetitions of anything (episodes, epochs, iterations, trials, steps): a million is
#: already weeks of simulation; more is a typo that would run forever
MAX_COUNT = 1_000_000
#: most transitions a budget or buffer may name
MAX_TRANSITIONS = 100_000_000
#: seeds are 32-bit in every generator the runs seed (numpy, torch, the simulators)
MAX_SEED = 2**32 - 1
#: most seeds of a bench (each is a job per agent)
MAX_SEEDS = 1000
#: the CPUs this process may run on
CPUS = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1
#: most worker processes or threads: one per CPU (two on a one-CPU machine, which only share
#: it: results do not depend on the number of workers)
MAX_PROCESSES = max(2, CPUS)
#: most workers a run may name on a Ray cluster it joins (``--ray-address``): the cluster's
#: CPUs bound them once it is joined (:meth:`dlocli.executors.RayExecutor.connect`), this
#: cap before (a typo of a million workers is refused at once)
MAX_CLUSTER_WORKERS = 10_000
#: most nodes of the tracker's chain (a spacing of 1/1000 of the cable): it solves a dense
#: nodes x nodes system and weighs every cloud point against every node each EM iteration
MAX_TRACKER_NODES = 1000
#: most pixels of the simulated depth camera (full HD): a camera holds about 150 bytes per
#: pixel (its rays and their hits; 4096 x 4096 took 2.5 GB)
MAX_CAMERA_PIXELS = 1920 * 1080
#: share of the usable memory one estimated allocation may take (the rest: the simulator,
#: torch itself, the data)
MEMORY_SHARE = 0.5


def usable_memory() -> int:
    """Bytes this process may use: the machine's physical memory, or less under a limit on
    the address space (``ulimit -v``)."""
    physical = os.sysconf("SC_PHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    soft, _ = resource.getrlimit(resource.RLIMIT_AS)
    return physical if soft == resource.RLIM_INFINITY else min(physical, soft)


def refuse_unless_fits(what: str, n_bytes: float, fix: str) -> None:
    """BadInput naming ``what``, its estimated size and the limit, if ``n_bytes`` exceeds the
    share of the usable memory one allocation may take."""
    limit = MEMORY_SHARE * usable_memory()
    if n_bytes > limit:
        raise BadInput(
            f"{what} needs about {_gigabytes(n_bytes)} of memory, more than the "
            f"{_gigabytes(limit)} this run may use ({MEMORY_SHARE:.0%} of this machine's "
            f"{_gigabytes(usable_memory())}); {fix}"
        )


def _gigabytes(n_bytes: float) -> str:
    return f"{n_bytes / 2**30:.3g} GiB"


def refuse_oversized_dataset(episodes: int, episode_steps: int, n_segments: int) -> None:
    """BadInput if a dataset of ``episodes`` episodes would not fit in memory. Its float32
    arrays (:mod:`dlocli.data.rod`) hold N x (3 + 4) + 2 x 7 numbers per state and 2 x 6 + 1 per
    transition, three times over while it is assembled and saved (the episodes, their
    concatenation, the file's image)."""
    per_episode = (episode_steps + 1) * (n_segments * 7 + 14) + episode_steps * 13
    refuse_unless_fits(
        f"a dataset of {episodes:,} episodes of {episode_steps} steps",
        3 * 4.0 * episodes * per_episode,
        "collect fewer or shorter episodes",
    )
