"""Sizes that would exhaust the machine and physics that cannot work (issue 33): each is
refused before work starts, in one line naming the limit, exit 2, within seconds, leaving
every existing file as it was. The memory cases run in a subprocess under an address-space
limit, so a regression fails fast instead of swapping."""

from __future__ import annotations

import json
import os
import pickle
import struct
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from tiny import MUJOCO_ROD, file_digests, run_dlo, write_cable

HUGE = str(10**12)
LIMIT = "less than or equal to"

# (id, argv with {out}/{spec}, words the one line must hold)
SIZES: list[tuple[str, str, str]] = [
    ("collect-episodes", f"collect --episodes {HUGE} --out {{out}}", LIMIT),
    ("collect-steps", f"collect --steps {HUGE} --out {{out}}", LIMIT),
    ("collect-workers", "collect --workers 1000 --out {out}", LIMIT),
    ("bench-seeds", f"bench --seeds {HUGE} --out {{out}}", LIMIT),
    ("train-epochs", f"train --data {{out}} --epochs {HUGE} --out {{out}}", LIMIT),
    ("train-seed", f"train --data {{out}} --seed {2**70} --out {{out}}", LIMIT),
    ("online-iters", f"online --iters {HUGE} --out {{out}}", LIMIT),
    ("online-trials", f"online --trials {HUGE} --out {{out}}", LIMIT),
    ("online-workers", f"online --workers {HUGE} --out {{out}}", LIMIT),
    ("control-threads", f"control --threads {HUGE} --out {{out}}", LIMIT),
]

# (id, spec file text, words the one line must hold) for `dlo goal --spec`
PHYSICS: list[tuple[str, str, str]] = [
    ("control-dt", "task: {control_dt: 1.0e+6}", "control_dt"),
    ("physics-dt", "backend: {physics_dt: 1.0e-9}", "physics_dt"),
    ("settle-steps", "task: {reset_settle_steps: 1000000000}", "reset_settle_steps"),
    ("young-huge", "backend: {rod: {young_tension: 1.0e+30}}", "young_tension"),
    ("young-tiny", "backend: {rod: {young_bending: 1.0e-30}}", "young_bending"),
    ("density-huge", "backend: {rod: {density: 1.0e+30}}", "density"),
    ("density-tiny", "backend: {rod: {density: 1.0e-30}}", "density"),
    ("radius-tiny", "backend: {rod: {radius: 1.0e-9}}", "radius"),
    ("length-tiny", "backend: {rod: {length: 1.0e-6}}", "length"),
    ("length-huge", "backend: {rod: {length: 1000}}", "length"),
    ("poisson", "backend: {rod: {poisson: -0.999}}", "poisson"),
    ("velocity", "task: {max_linear_velocity: 1.0e+9}", "max_linear_velocity"),
    ("workspace-inverted", "task: {workspace_low: [1, 1, 1], workspace_high: [0, 0, 0]}",
     "workspace_low"),
    ("separation-inverted", "task: {min_separation: 0.9, max_separation: 0.1}",
     "min_separation"),
    # a box without the grippers' rest: the first step pulled them in (a "near-rest" goal
    # 653 mm from rest)
    ("workspace-excludes-rest", "task: {workspace_low: [0.6, 0.4, 1.2], "
     "workspace_high: [0.8, 0.6, 1.4], shapes: near-rest}", "excludes the grippers' rest"),
    ("workspace-excludes-rest-pose", "task: {workspace_low: [0.6, 0.4, 1.2], "
     "workspace_high: [0.8, 0.6, 1.4]}", "widen the workspace"),
    ("workspace-excludes-rest-pybullet", "backend: {name: pybullet}\ntask: {workspace_low: "
     "[0.6, 0.4, 1.2], workspace_high: [0.8, 0.6, 1.4], shapes: near-rest}",
     "excludes the grippers' rest"),
    ("rest-state-mujoco", f"backend: {{name: {MUJOCO_ROD}, rod: {{radius: 1.0e-4, density: 10}}}}",
     "cannot build this rod"),
]  # fmt: skip


def _refused_in_one_line(argv: list[str], words: str, capsys, roots: list[Path]) -> None:
    before = file_digests(*roots)
    start = time.monotonic()
    code = run_dlo(argv)
    seconds = time.monotonic() - start
    err = capsys.readouterr().err
    lines = [line for line in err.splitlines() if line.strip()]
    assert code == 2, err
    assert len(lines) == 1 and lines[0].startswith("error: ") and words in lines[0], err
    assert seconds < 10, seconds
    assert file_digests(*roots) == before


@pytest.mark.parametrize(("case", "argv", "words"), SIZES, ids=[c[0] for c in SIZES])
def test_a_count_beyond_its_limit_is_refused(case, argv, words, tmp_path, capsys):
    (tmp_path / "kept.txt").write_text("mine\n")
    args = argv.format(out=tmp_path).split()
    _refused_in_one_line(args, words, capsys, [tmp_path])


@pytest.mark.parametrize(("case", "text", "words"), PHYSICS, ids=[c[0] for c in PHYSICS])
def test_physics_that_cannot_work_is_refused(case, text, words, tmp_path, capsys):
    spec = tmp_path / "spec.yaml"
    spec.write_text(text + "\n")
    args = ["goal", "--spec", str(spec), "--out", str(tmp_path / "goal.npy")]
    _refused_in_one_line(args, words, capsys, [tmp_path])
    assert not (tmp_path / "goal.npy").exists()


# (id, command, spec file text, words): tracker and camera settings that would size arrays
# past the machine (a spacing of 1e-7 asked for 728 TiB; 4096 x 4096 pixels took 2.5 GB)
TRACKING: list[tuple[str, str, str, str]] = [
    ("control-spacing", "control --goal {goal} --controller zero",
     "task: {observation: {kind: pointcloud, tracker: {spacing: 1.0e-7}}}",
     "tracker.spacing': Input should be greater than or equal to 0.001"),
    ("control-pixels", "control --goal {goal} --controller zero",
     "task: {observation: {kind: pointcloud, camera: {width: 4096, height: 4096}}}",
     "lower camera.width or camera.height"),
    ("track-spacing", "track --source {source}", "tracker: {spacing: 1.0e-7}",
     "tracker.spacing': Input should be greater than or equal to 0.001"),
]  # fmt: skip


@pytest.mark.parametrize(("case", "command", "text", "words"), TRACKING,
                         ids=[c[0] for c in TRACKING])  # fmt: skip
def test_a_tracker_or_camera_past_its_size_is_refused(
    case, command, text, words, near_rest_goal, tmp_path, capsys
):
    spec, source, out = tmp_path / "spec.yaml", tmp_path / "source", tmp_path / "out"
    spec.write_text(text + "\n")
    source.mkdir()
    (source / "kept.txt").write_text("mine\n")
    args = command.format(goal=near_rest_goal, source=source).split()
    _refused_in_one_line([*args, "--spec", str(spec), "--out", str(out)], words, capsys,
                         [tmp_path])  # fmt: skip
    assert not out.exists()


def test_the_documented_cameras_and_the_finest_tracker_are_allowed():
    from dlocli.camera_spec import CameraSpec, TrackerSpec

    for width, height in ((160, 120), (640, 480), (800, 600), (1920, 1080), (4096, 1)):
        CameraSpec(width=width, height=height)
    TrackerSpec(spacing=0.001)


def test_too_many_mppi_samples_are_refused():
    from pydantic import ValidationError

    from dlocli.controllers.mppi import MPPISpec

    with pytest.raises(ValidationError, match="less than or equal to 4096"):
        MPPISpec(samples=100_000)


# ----------------------------------------------------------------------------- memory
#: address-space limit of the memory cases: enough for Python, torch and the simulators
ADDRESS_SPACE = 3 * 2**30

MEMORY: list[tuple[str, str, str]] = [
    ("model-hidden", "online --hidden 8192 --out {out}", "hidden 8192"),
    ("mlp-hidden", "online --model mlp --spec {spec} --out {out}", "mlp (hidden 65536"),
    ("sac-net-arch", "bench --agents sac -o sac.net_arch=[65536,65536] --out {out}",
     "net_arch [65536, 65536]"),
    ("collect-dataset", "collect --episodes 1000000 --out {out}", "dataset of 1,000,000"),
]  # fmt: skip


def _under_memory_limit(args: list[str]) -> subprocess.CompletedProcess:
    """`dlo ARGS` in a subprocess limited to ADDRESS_SPACE bytes of memory."""
    program = (
        "import resource, sys\n"
        f"resource.setrlimit(resource.RLIMIT_AS, ({ADDRESS_SPACE}, {ADDRESS_SPACE}))\n"
        "from dlocli.cli import main\n"
        f"sys.argv = ['dlo', *{args!r}]\n"
        "main()\n"
    )
    env = {**os.environ, "PYTHONPATH": str(Path(__file__).parents[1])}
    return subprocess.run(
        [sys.executable, "-c", program], capture_output=True, text=True, timeout=60, env=env
    )


@pytest.mark.parametrize(("case", "argv", "words"), MEMORY, ids=[c[0] for c in MEMORY])
def test_a_size_beyond_memory_is_refused_under_a_memory_limit(case, argv, words, tmp_path):
    spec = tmp_path / "spec.yaml"
    spec.write_text("model: {hidden: 65536}\n")
    start = time.monotonic()
    done = _under_memory_limit(argv.format(out=tmp_path / "out", spec=spec).split())
    seconds = time.monotonic() - start
    lines = [line for line in done.stderr.splitlines() if line.strip()]
    assert done.returncode == 2, done.stderr[-2000:]
    assert len(lines) == 1 and words in lines[0] and "memory" in lines[0], done.stderr[-2000:]
    assert seconds < 20, seconds  # Python, torch and the simulators start in the subprocess
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("argv", ["goal --out {out}/goal.npy",
                                  "collect --episodes 2 --steps 20 --out {out}/run"])  # fmt: skip
def test_a_file_size_limit_is_one_line_and_no_short_file(argv, tmp_path):
    """Under `ulimit -f` a write is cut without an error; the file is refused, not kept."""
    out = tmp_path / "out"
    out.mkdir()
    program = (
        "import resource, sys\n"
        "resource.setrlimit(resource.RLIMIT_FSIZE, (300, 300))\n"
        "from dlocli.cli import main\n"
        f"sys.argv = ['dlo', *{argv.format(out=out).split()!r}]\n"
        "main()\n"
    )
    env = {**os.environ, "PYTHONPATH": str(Path(__file__).parents[1])}
    done = subprocess.run(
        [sys.executable, "-c", program], capture_output=True, text=True, timeout=120, env=env
    )
    lines = [line for line in done.stderr.splitlines() if line.strip()]
    assert done.returncode == 1, done.stderr[-2000:]
    assert len(lines) == 1 and "file size limit" in lines[0], done.stderr[-2000:]
    assert not [p for p in out.rglob("*") if p.suffix in (".npy", ".h5")]


# ----------------------------------------------------------------------- recordings (issue 44)
def _memo_fan_out() -> bytes:
    """[[x] * 1000] * 1000, x a list of 300 floats, each list pickled once and reused through
    the memo: 7 kB that expand to 300 million numbers (2.4 GB before this was refused)."""
    floats = b"".join(b"G" + struct.pack(">d", 0.1) for _ in range(300))
    return (b"\x80\x04" + b"]\x94(" * 3 + floats + b"e" + b"h\x02" * 999 + b"e"
            + b"h\x01" * 999 + b"e.")  # fmt: skip


def _huge_declared_bytes() -> bytes:
    return b"\x80\x04\x8e" + struct.pack("<Q", 2**62) + b"xx."  # BINBYTES8 of 4 EiB


def _huge_declared_frame() -> bytes:
    return b"\x80\x04\x95" + struct.pack("<Q", 2**62) + b"]."  # a FRAME of 4 EiB


def _memo_index_far_out(index: int = 160_000_000) -> bytes:
    """A list of one float stored in the memo at ``index``: the unpickler sizes its memo to
    twice the highest index (2.4 GB here before this was refused)."""
    return b"\x80\x04]r" + struct.pack("<I", index) + b"(G" + struct.pack(">d", 0.1) + b"e."


def _over_the_budget() -> bytes:
    return pickle.dumps(np.zeros((4000, 3, 30)).tolist())  # 360,000 numbers: 21 MiB to read


BOMBS = [
    (_memo_fan_out, "memo reference"),
    (_memo_index_far_out, "memo index 160000000"),
    (_huge_declared_bytes, "not a readable pickle"),
    (_huge_declared_frame, "not a readable pickle"),
    (_over_the_budget, "over the budget"),
]


@pytest.mark.parametrize(("write", "words"), BOMBS, ids=[w.__name__[1:] for w, _ in BOMBS])
def test_a_recording_past_the_memory_budget_is_refused_before_it_is_built(write, words, tmp_path):
    root = write_cable(tmp_path / "CABLE", n_train=1, n_eval=0, frames=5)
    (root / "train" / "z.pkl").write_bytes(write())
    args = ["import", "--source", str(root), "--max-memory-mib", "16", "--out",
            str(tmp_path / "out")]  # fmt: skip
    done = _under_memory_limit(args)
    lines = [line for line in done.stderr.splitlines() if line.strip()]
    assert done.returncode == 2, done.stderr[-2000:]
    assert len(lines) == 1 and words in lines[0] and "z.pkl" in lines[0], done.stderr[-2000:]
    assert not (tmp_path / "out").exists()


_PEAK = """
import json, resource, sys, time
resource.setrlimit(resource.RLIMIT_AS, (2**30, 2**30))  # a regression fails, not swaps
from dlocli.errors import BadInput
from dlocli.recorded_cables.plain_pickle import load_plain
data = sys.stdin.buffer.read()
before, start = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss, time.perf_counter()
try:
    load_plain(data, "z.pkl", 2**40)
    refusal = None
except BadInput as exc:
    refusal = str(exc)
grown = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - before
print(json.dumps({"refusal": refusal, "seconds": time.perf_counter() - start, "grown_kib": grown}))
"""


def test_a_memo_index_far_out_is_refused_at_once_in_little_memory():
    """Even under a budget that would allow it: no plain pickle stores an object in the memo
    past the opcodes before it, and the memo is never read (a memo reference is refused)."""
    env = {**os.environ, "PYTHONPATH": str(Path(__file__).parents[1])}
    done = subprocess.run([sys.executable, "-c", _PEAK], input=_memo_index_far_out(),
                          capture_output=True, timeout=60, env=env)  # fmt: skip
    assert done.returncode == 0, done.stderr.decode()[-2000:]
    found = json.loads(done.stdout)
    assert "memo index 160000000" in found["refusal"] and "z.pkl" in found["refusal"]
    # 2.4 GB and 6 s before: within a megabyte and a millisecond now
    assert found["grown_kib"] < 64 * 1024 and found["seconds"] < 1.0, found
