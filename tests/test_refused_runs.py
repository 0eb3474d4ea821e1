"""A run refused before its first result leaves nothing behind (issue 51): no folder where
there was none, lock file and parents included, and a folder that was there as it was found.
The refusal here is a real one: an envelope box that excludes the gripper's start."""

from __future__ import annotations

import json
import os
from pathlib import Path

import pytest

from dlocli.errors import DloError
from dlocli.rundir import owned

from tiny import file_digests, run_dlo

CONTROL = ["control", "--controller", "zero", "--steps", "2", "--shapes", "near-rest"]
ONLINE = ["online", "--iters", "1", "--shapes", "near-rest"]
COLLECT = ["collect", "--episodes", "2", "--steps", "3", "--shapes", "near-rest"]


@pytest.fixture(scope="module")
def inputs(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """A goal, and a spec whose envelope box lies far from where the right gripper starts."""
    root = tmp_path_factory.mktemp("refused")
    assert run_dlo(["goal", "--out", str(root / "g.npy"), "--shapes", "near-rest"]) == 0
    box = {"right_low": [2.0, 2.0, 2.0], "right_high": [3.0, 3.0, 3.0]}
    (root / "far.json").write_text(json.dumps({"task": {"envelope": box}}))
    return {"goal": root / "g.npy", "far": root / "far.json"}


def _everything(root: Path) -> dict[str, str]:
    """Every path under ``root`` (folders and lock files too), files with their digests."""
    found = {str(p): "folder" for p in root.rglob("*") if p.is_dir()}
    found |= {str(p): "lock" for p in root.rglob(".dlo.lock")}
    return found | file_digests(root)


def _refused(argv: list[str], root: Path, capsys: pytest.CaptureFixture[str]) -> str:
    """Run ``argv``; assert exit 2 in one line and everything under ``root`` as it was."""
    before = _everything(root)
    capsys.readouterr()
    assert run_dlo(argv) == 2
    err = capsys.readouterr().err
    lines = [line for line in err.splitlines() if line.strip()]
    assert len(lines) == 1 and "Traceback" not in err, err
    assert _everything(root) == before
    return lines[0]


@pytest.mark.parametrize("command", ["control", "online", "collect"])
def test_a_run_refused_before_its_first_step_leaves_no_folder(
    command: str, inputs, tmp_path: Path, capsys
):
    argv = {"control": [*CONTROL, "--goal", str(inputs["goal"])], "online": ONLINE,
            "collect": COLLECT}[command]  # fmt: skip
    out = tmp_path / "runs" / "deep" / "run"  # the folders above it are new too
    line = _refused([*argv, "--spec", str(inputs["far"]), "--out", str(out)], tmp_path, capsys)
    assert "outside its envelope box" in line
    assert not (tmp_path / "runs").exists()


def test_a_refused_overwrite_leaves_the_earlier_run_as_it_was(inputs, tmp_path: Path, capsys):
    run = tmp_path / "run"
    control = [*CONTROL, "--goal", str(inputs["goal"]), "--out", str(run)]
    assert run_dlo([*control, "--seed", "3"]) == 0
    assert (run / "spec.json").is_file() and (run / "summary.json").is_file()
    line = _refused([*control, "--spec", str(inputs["far"]), "--overwrite"], tmp_path, capsys)
    assert "outside its envelope box" in line
    assert json.loads((run / "spec.json").read_text())["seed"] == 3  # the earlier run's spec
    assert run_dlo([*control, "--overwrite"]) == 0  # still dlo's to replace


def test_a_folder_refused_by_overwrite_gets_no_lock_file(inputs, tmp_path: Path, capsys):
    run = tmp_path / "run"
    run.mkdir()
    (run / "notes.txt").write_text("mine\n")
    argv = [*CONTROL, "--goal", str(inputs["goal"]), "--out", str(run), "--overwrite"]
    assert "notes.txt" in _refused(argv, tmp_path, capsys)
    assert sorted(os.listdir(run)) == ["notes.txt"]


def _start(run: Path) -> None:
    """What a run writes before its first step."""
    (run / "spec.json").write_text("{}\n")
    (run / "fingerprints.json").write_text("{}\n")
    (run / "plots" / "empty").mkdir(parents=True)


class Lost(DloError):
    """A run's own error after it started: a cell that never answers a step (exit 1)."""


def test_a_run_lost_before_its_first_result_is_undone(tmp_path: Path):
    run = tmp_path / "a" / "run"
    with pytest.raises(Lost), owned(run):
        _start(run)
        raise Lost("no reply")
    assert list(tmp_path.iterdir()) == []


def test_a_run_lost_after_a_result_keeps_it_and_its_spec(tmp_path: Path):
    run = tmp_path / "run"
    with pytest.raises(Lost), owned(run):
        _start(run)
        (run / "metrics.csv").write_text("step\n0\n")
        raise Lost("no reply")
    assert {"spec.json", "fingerprints.json", "metrics.csv"} <= set(os.listdir(run))
    assert "metrics.csv" in json.loads((run / ".dlo-written.json").read_text())


def test_an_interrupted_run_keeps_its_spec_to_resume(tmp_path: Path):
    run = tmp_path / "run"
    with pytest.raises(KeyboardInterrupt), owned(run):
        _start(run)
        raise KeyboardInterrupt
    assert (run / "spec.json").is_file()


def test_a_start_file_that_is_a_users_link_is_never_rewritten(tmp_path: Path):
    run, target = tmp_path / "run", tmp_path / "precious.json"
    run.mkdir()
    target.write_text('{"mine": 1}\n')
    (run / "spec.json").symlink_to(target)
    with pytest.raises(Lost), owned(run):
        (run / "spec.json").unlink()
        (run / "spec.json").write_text("{}\n")
        raise Lost("no reply")
    assert target.read_text() == '{"mine": 1}\n' and (run / "spec.json").is_file()
