"""What the tests share: tiny settings, so every agent learns and every bench job runs in
seconds (the defaults are the paper's sizes; budgets are 60 transitions of 20-step episodes),
a lock held by another process, and inputs built once per test session."""

from __future__ import annotations

import json
import os
import pickle
import shutil
import subprocess
import sys
import zipfile
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np

from dlocli.backend_spec import default_backend

#: the MuJoCo rod that the installed MuJoCo runs, for the tests that need a MuJoCo rod but not
#: a particular one: the composite cable ("mujoco") on MuJoCo 3, the flex rod on MuJoCo 4
MUJOCO_ROD = default_backend()

#: options of the learning agents: small networks and GP, short horizons
TINY_AGENTS: dict[str, dict[str, Any]] = {
    "sac": {"net_arch": [16, 16], "batch_size": 8, "learning_starts": 20},
    "td3": {"net_arch": [16, 16], "batch_size": 8, "learning_starts": 20},
    "pilco": {
        "action_repeat": 2,
        "horizon": 3,
        "n_basis": 4,
        "gp_iterations": 10,
        "policy_iterations": 2,
        "max_gp_points": 15,
    },
}

#: a bench spec: three evaluation points of one episode each, one seed, one evaluation episode
TINY_BENCH: dict[str, Any] = {
    "task": {"episode_steps": 20, "reset_motion_steps": 10, "reset_settle_steps": 10},
    "model": {"hidden": 16, "lstm_layers": 1, "edge_layers": 2, "node_layers": 2},
    "fit": {"epochs": 2, "batch_size": 32, "device": "cpu"},
    "budget": 60,
    "evals": 3,
    "eval_trials": 1,
    "seeds": 1,
    "workers": 1,
    "options": TINY_AGENTS,
}


_HOLD_LOCK = """
import fcntl, os, sys, time
fd = os.open(sys.argv[1], os.O_RDWR | os.O_CREAT)
fcntl.flock(fd, fcntl.LOCK_EX)
os.ftruncate(fd, 0); os.write(fd, str(os.getpid()).encode())
print("locked", flush=True)
time.sleep(600)
"""


@contextmanager
def lock_held_elsewhere(lock_file: Path) -> Iterator[subprocess.Popen]:
    """Another process holds ``lock_file`` (a run directory's ``.dlo.lock``) for the block."""
    lock_file.parent.mkdir(parents=True, exist_ok=True)
    holder = subprocess.Popen([sys.executable, "-c", _HOLD_LOCK, str(lock_file)],
                              stdout=subprocess.PIPE)  # fmt: skip
    try:
        assert holder.stdout is not None and holder.stdout.readline().strip() == b"locked"
        yield holder
    finally:
        holder.kill()
        holder.wait()


def run_dlo(argv: list[str]) -> int:
    """Run the `dlo` entry point itself (``dlocli.cli.main``) in this process; its exit code.

    The entry point sizes the process's thread pools through environment variables; they are
    put back after, so a later test's subprocesses get the threads they would have (floats
    differ with the thread count)."""
    from dlocli.cli import main

    old, environment = sys.argv, dict(os.environ)
    sys.argv = ["dlo", *argv]
    try:
        main()
    except SystemExit as exc:
        return exc.code if isinstance(exc.code, int) else 0
    finally:
        sys.argv = old
        os.environ.clear()
        os.environ.update(environment)
    return 0


def file_digests(*roots: Path) -> dict[str, str]:
    """sha256 of every file under ``roots`` (lock files excepted: taking a lock is fine)."""
    import hashlib

    found = {}
    for root in roots:
        for path in sorted(Path(root).rglob("*")):
            if path.is_file() and path.name != ".dlo.lock":
                found[str(path)] = hashlib.sha256(path.read_bytes()).hexdigest()
    return found


def crafted_policy(policy: Path, target: Path, edit: Any) -> Path:
    """A copy of ``policy`` whose model.zip is rewritten by ``edit(members)`` (name -> bytes)."""
    shutil.copytree(policy, target)
    with zipfile.ZipFile(policy / "model.zip") as archive:
        members = {name: archive.read(name) for name in archive.namelist()}
    edit(members)
    with zipfile.ZipFile(target / "model.zip", "w") as archive:
        for name, data in members.items():
            archive.writestr(name, data)
    return target


def edit_policy_data(members: dict[str, bytes], **entries: Any) -> None:
    """Set ``entries`` in the ``data`` JSON of a policy zip's ``members``."""
    data = json.loads(members["data"])
    data.update(entries)
    members["data"] = json.dumps(data).encode()


def control_with_policy(goal: Path, policy: Path, out: Path) -> list[str]:
    """`dlo control` arguments: three steps of the SAC ``policy`` towards ``goal``."""
    return ["control", "--goal", str(goal), "--controller", "sac", "--policy", str(policy),
            "--steps", "3", "--shapes", "near-rest", "--out", str(out)]  # fmt: skip


class Payload:
    """Unpickled, it creates the file ``marker``: what a crafted file would run instead."""

    def __init__(self, marker: Path) -> None:
        self.marker = str(marker)

    def __reduce__(self) -> tuple[Any, ...]:
        return (open, (self.marker, "w"))


def built_once(factory: Any, name: str, build: Callable[[Path], None]) -> Path:
    """This test process's own copy of what ``build(directory)`` writes, built once per test
    session: under pytest-xdist the workers share their base temp directory's parent, and a
    file lock lets the first build there while the others wait (pytest-xdist's documented
    pattern). Each worker gets a copy, so no worker sees another's writes mid-test."""
    from filelock import FileLock

    own = factory.mktemp(name)
    if os.environ.get("PYTEST_XDIST_WORKER") is None:  # one process: build in place
        build(own)
        return own
    shared = factory.getbasetemp().parent / name
    built = shared / ".built"
    with FileLock(f"{shared}.lock"):
        if not built.is_file():
            shutil.rmtree(shared, ignore_errors=True)  # a build that failed part-way
            shared.mkdir()
            build(shared)
            built.touch()
    shutil.copytree(shared, own, dirs_exist_ok=True, ignore=shutil.ignore_patterns(".built"))
    return own


# ----------------------------------------------------------------------------- recordings
FRAMES, MARKERS = 40, 6


def swinging_cable(seed: int, frames: int = FRAMES, markers: int = MARKERS) -> np.ndarray:
    """(frames, 3, markers) like a DEFORM file: a sagging cable whose ends move."""
    rng = np.random.default_rng(seed)
    t = np.arange(frames)[:, None] / 100.0
    s = np.linspace(0, 1, markers)[None, :]
    phase, amp = rng.uniform(0, 6), rng.uniform(0.02, 0.08)
    x = 0.8 * s + amp * np.sin(2 * np.pi * t + phase)
    y = 0.05 * np.sin(np.pi * s) * np.cos(3 * t + phase)
    z = 0.5 - 0.2 * np.sin(np.pi * s) + amp * np.sin(5 * t) * s
    return np.stack([x, y, z], 1).astype(np.float64)


def write_cable(root: Path, n_train: int = 4, n_eval: int = 2, **kw) -> Path:
    """A cable folder in the DEFORM layout: train/ and eval/ of pickled recordings."""
    for split, n in (("train", n_train), ("eval", n_eval)):
        (root / split).mkdir(parents=True, exist_ok=True)
        for i in range(n):
            array = swinging_cable(i + (100 if split == "eval" else 0), **kw)
            (root / split / f"{i}.pkl").write_bytes(pickle.dumps(array.tolist()))
    return root


def dlo_import(source: Path, out: Path, *flags: str) -> int:
    """`dlo import --json` of ``source`` into ``out``; its exit code."""
    return run_dlo(["import", "--source", str(source), "--out", str(out), "--json", *flags])


def pair_and_singles(cli: Any, common: list[str], root: Path, seeds: tuple[int, int] = (3, 4)):
    """Train ``common`` (`dlo train` arguments) alone with each of ``seeds`` and as a
    two-member ensemble from the first: (the pair's run directory, the singles')."""
    for seed in seeds:
        alone = cli(*common, "--seed", str(seed), "--out", str(root / f"alone{seed}"))
        assert alone.exit_code == 0, alone.output
    pair = cli(*common, "--seed", str(seeds[0]), "--members", "2", "--out", str(root / "pair"))
    assert pair.exit_code == 0, pair.output
    return root / "pair", [root / f"alone{seed}" for seed in seeds]


def committed_bench(example: str, out: Path) -> Path:
    """examples/EXAMPLE's bench run as a run directory OUT, its job files rebuilt from the kept
    results.csv and jobs.json (examples/bench_jobs.py unpack)."""
    import runpy

    examples = Path(__file__).resolve().parents[1] / "examples"
    runpy.run_path(str(examples / "bench_jobs.py"))["unpack"](examples / example, out)
    return out
