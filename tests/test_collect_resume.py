"""`dlo collect` saves each finished episode at once and resumes: a killed or interrupted run
resumed gives the same dataset.h5, bit for bit, as an uninterrupted run with the same spec."""

from __future__ import annotations

import json
import random
import signal
import subprocess
import sys
import time

import h5py
import numpy as np
import pytest
from typer.testing import CliRunner

from dlocli.cli import app
from dlocli.io import written_by_dlo
from dlocli.runs.collect import PARTS_DIR, collect_random, part_path
from dlocli.specs import CollectSpec

runner = CliRunner()
EPISODES = 20
# tiny episodes, short settling: a whole run takes a few seconds
SPEC = f"episodes: {EPISODES}\nseed: 3\ntask: {{episode_steps: 3, reset_settle_steps: 10}}\n"


def run(*args: str):
    return runner.invoke(app, list(args))


def arrays(path) -> dict[str, np.ndarray]:
    with h5py.File(path / "dataset.h5", "r") as f:
        return {name: f[name][()] for name in f}


def assert_same_data(a, b) -> None:
    got, want = arrays(a), arrays(b)
    assert got.keys() == want.keys() and "episode_lengths" in got
    for name in want:
        assert got[name].dtype == want[name].dtype, name
        assert np.array_equal(got[name], want[name]), name


@pytest.fixture(scope="module")
def spec_file(tmp_path_factory):
    path = tmp_path_factory.mktemp("spec") / "collect.yaml"
    path.write_text(SPEC)
    return path


@pytest.fixture(scope="module")
def reference(tmp_path_factory, spec_file):
    """An uninterrupted run of the spec."""
    out = tmp_path_factory.mktemp("reference") / "run"
    res = run("collect", "--spec", str(spec_file), "--out", str(out), "--json")
    assert res.exit_code == 0, res.output
    assert not (out / PARTS_DIR).exists(), "the parts are removed once dataset.h5 is written"
    return out


def test_sigkill_then_resume_is_bit_identical(tmp_path, spec_file, reference):
    out = tmp_path / "killed"
    cmd = [sys.executable, "-m", "dlocli", "collect", "--spec", str(spec_file), "--out", str(out)]
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    deadline = time.time() + 120
    while not part_path(out, 0).exists():
        assert proc.poll() is None, proc.stderr.read().decode()
        assert time.time() < deadline
        time.sleep(0.01)
    time.sleep(random.uniform(0.0, 0.2))
    proc.kill()
    proc.wait(timeout=30)
    proc.stderr.close()
    assert proc.returncode == -signal.SIGKILL
    kept = sorted(out.glob(f"{PARTS_DIR}/episode_*.h5"))
    assert 1 <= len(kept) < EPISODES and not (out / "dataset.h5").exists(), "killed mid-run"
    assert kept == [part_path(out, e) for e in range(len(kept))], "parts are a prefix"
    # a crash mid-write may leave a temporary file; it is not an episode
    (out / PARTS_DIR / f".episode_{len(kept):06d}.h5.abc123.tmp").write_bytes(b"half")

    res = run("collect", "--resume", str(out), "--workers", "2", "--json")
    assert res.exit_code == 0, res.output
    summary = json.loads(res.stdout.strip().splitlines()[-1])
    assert summary["episodes"] == EPISODES and summary["transitions"] == 3 * EPISODES
    assert summary["workers"] == 2 and summary["seconds"] > 0
    assert not (out / PARTS_DIR).exists()
    assert_same_data(out, reference)
    assert json.loads((out / "summary.json").read_text()) == summary
    assert {"spec.json", "dataset.h5", "summary.json"} <= written_by_dlo(out)  # adopted


def test_interrupt_keeps_parts_and_resume_reassembles(tmp_path, reference, monkeypatch):
    out = tmp_path / "interrupted"
    spec = CollectSpec(episodes=EPISODES, steps=3, seed=3, out=out, task={"reset_settle_steps": 10})

    def stop(event):
        if event.done == 3:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        collect_random(spec, progress=stop)
    assert arrays(out)["episode_lengths"].tolist() == [3, 3, 3], "finished episodes saved"
    assert not (out / "summary.json").exists() and (out / PARTS_DIR).is_dir()
    first = json.loads((out / PARTS_DIR / "progress.json").read_text())["seconds"]
    # an unreadable part and a missing one in the middle are collected (again)
    part_path(out, 1).write_bytes(b"not hdf5")
    part_path(out, 2).unlink()

    seen = []

    def crash_before_cleanup(path, *args, **kwargs):
        raise OSError("killed before the parts were removed")

    monkeypatch.setattr("dlocli.runs.collect.shutil.rmtree", crash_before_cleanup)
    with pytest.raises(OSError):
        collect_random(spec, progress=lambda e: seen.append(e.done), resume=True)
    monkeypatch.undo()
    assert seen[0] == 1 and seen[-1] == EPISODES, "progress starts at the episodes kept"
    assert (out / "summary.json").exists() and (out / PARTS_DIR).is_dir()
    assert_same_data(out, reference)

    # dataset and summary written but the parts still there: resuming assembles again
    seen.clear()
    summary = collect_random(spec, progress=lambda e: seen.append(e.done), resume=True)
    assert seen == [EPISODES], "nothing recollected"
    assert summary["episodes"] == EPISODES and summary["seconds"] >= first
    assert not (out / PARTS_DIR).exists()
    assert_same_data(out, reference)


def test_resume_of_finished_run_does_not_recollect(reference):
    before = (reference / "dataset.h5").stat().st_mtime_ns
    saved = json.loads((reference / "summary.json").read_text())
    res = run("collect", "--resume", str(reference), "--json")
    assert res.exit_code == 0, res.output
    assert json.loads(res.stdout.strip().splitlines()[-1]) == saved
    assert (reference / "dataset.h5").stat().st_mtime_ns == before


def test_resume_of_non_collect_dir_exits_2(tmp_path):
    res = run("collect", "--resume", str(tmp_path))
    assert res.exit_code == 2
    lines = res.output.strip().splitlines()
    assert len(lines) == 1 and "not a collect run" in lines[0], res.output
    (tmp_path / "spec.json").write_text(json.dumps({"data": "d.h5", "epochs": 3}))
    res = run("collect", "--resume", str(tmp_path))
    assert res.exit_code == 2 and len(res.output.strip().splitlines()) == 1, res.output
    assert "Traceback" not in res.output


def test_resume_with_conflicting_flag_exits_2(tmp_path):
    out = tmp_path / "run"
    spec = CollectSpec(episodes=2, steps=3, seed=3, out=out)
    out.mkdir()
    (out / "spec.json").write_text(spec.model_dump_json())
    res = run("collect", "--resume", str(out), "--seed", "5")
    assert res.exit_code == 2 and "seed" in res.output and "Traceback" not in res.output
    assert sorted(p.name for p in out.iterdir()) == ["spec.json"], "nothing written"
