"""dlo deletes and replaces only what it made (issue 33): --overwrite removes only what a
run directory's manifest says dlo wrote, outputs never land in an input run, existing video
and plot files need --overwrite, a linked lock file is refused, and a full disk leaves no
truncated file. Each refusal is one line, exit 2, every existing file byte-identical."""

from __future__ import annotations

import errno
import os
from pathlib import Path

import pytest

from tiny import file_digests, run_dlo

COLLECT = ["collect", "--episodes", "2", "--steps", "3", "--shapes", "near-rest", "--json"]


@pytest.fixture(scope="module")
def world(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """A collect run, a model trained on it and a goal, all real."""
    root = tmp_path_factory.mktemp("ownership")
    paths = {"root": root, "data": root / "data", "train": root / "train"}
    paths["goal"] = root / "g.npy"
    assert run_dlo([*COLLECT, "--out", str(paths["data"])]) == 0
    train = ["train", "--data", str(paths["data"]), "--epochs", "1", "--hidden", "8",
             "--val-fraction", "0", "--out", str(paths["train"]), "--json"]  # fmt: skip
    assert run_dlo(train) == 0
    assert run_dlo(["goal", "--out", str(paths["goal"]), "--shapes", "near-rest"]) == 0
    return paths


def _refused(argv: list[str], roots: list[Path], capsys: pytest.CaptureFixture[str]) -> str:
    """Run ``argv``; assert exit 2, one line and every file under ``roots`` unchanged."""
    before = file_digests(*roots)
    capsys.readouterr()
    assert run_dlo(argv) == 2
    err = capsys.readouterr().err
    lines = [line for line in err.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith("error: ") and "Traceback" not in err, err
    assert file_digests(*roots) == before
    return lines[0]


@pytest.mark.parametrize("user_file", ["episodes/thesis.tex", "notes.txt", "empty-folder/"])
def test_overwrite_refuses_a_run_holding_a_file_dlo_did_not_write(
    user_file: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
):
    run = tmp_path / "run"
    assert run_dlo([*COLLECT, "--out", str(run)]) == 0
    if user_file.endswith("/"):
        (run / user_file).mkdir()
    else:
        (run / user_file).parent.mkdir(exist_ok=True)
        (run / user_file).write_text("mine\n")
    line = _refused([*COLLECT, "--out", str(run), "--overwrite"], [run], capsys)
    assert user_file.rstrip("/") in line and "--overwrite" in line
    assert (run / user_file).exists()


def test_overwrite_replaces_a_run_dlo_wrote(tmp_path: Path):
    run = tmp_path / "run"
    assert run_dlo([*COLLECT, "--out", str(run)]) == 0
    assert run_dlo([*COLLECT, "--out", str(run), "--overwrite", "--seed", "1"]) == 0


def test_online_overwrite_keeps_a_users_data_folder(tmp_path: Path, capsys):
    # the case: `online --overwrite` removed DIR/data/ whatever it held
    run = tmp_path / "run"
    (run / "data").mkdir(parents=True)
    (run / "data" / "thesis.tex").write_text("mine\n")
    argv = ["online", "--iters", "1", "--shapes", "near-rest", "--out", str(run), "--overwrite"]
    assert "data/thesis.tex" in _refused(argv, [run], capsys)


@pytest.mark.parametrize(
    "argv",
    [
        "train --data {data} --out {data} --overwrite",
        "train --data {data} --out {data}/model",
        "train --data {data}/dataset.h5 --out {data}/model",
        "eval --checkpoint {train} --data {data} --out {train} --overwrite",
        "eval --checkpoint {train} --data {data} --out {root}/e --plot {train}/p.png",
        "control --checkpoint {train}/checkpoints/final.pt --goal {goal} --out {train}/control",
    ],
)
def test_outputs_never_land_in_an_input_run(argv: str, world, tmp_path, capsys):
    args = [part.format(**{k: str(v) for k, v in world.items()}) for part in argv.split()]
    assert "inside" in _refused(args, [world["root"]], capsys)


@pytest.mark.parametrize(
    "argv",
    [
        "control --goal {goal} --controller zero --steps 2 --video {root}/v.gif --out {root}/c",
        "eval --checkpoint {train} --data {data} --plot {root}/p.png --out {root}/e",
    ],
)
def test_an_existing_video_or_plot_needs_overwrite(argv: str, world, capsys):
    args = [part.format(**{k: str(v) for k, v in world.items()}) for part in argv.split()]
    target = Path(args[args.index("--video" if "--video" in args else "--plot") + 1])
    target.write_bytes(b"a user's file\n")
    try:
        assert "--overwrite" in _refused(args, [world["root"]], capsys)
    finally:
        target.unlink()


@pytest.mark.parametrize("link", ["symlink", "hardlink"])
def test_a_linked_lock_file_is_refused_and_its_target_untouched(
    link: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
):
    target, run = tmp_path / "precious.txt", tmp_path / "run"
    target.write_text("precious\n")
    run.mkdir()
    (os.symlink if link == "symlink" else os.link)(target, run / ".dlo.lock")
    assert "lock" in _refused([*COLLECT, "--out", str(run)], [tmp_path], capsys)
    assert target.read_text() == "precious\n"


def test_a_full_disk_leaves_no_truncated_goal(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
):
    """The disk fills as the written file reaches it (delayed allocation): fsync says so."""

    def full(fd: int) -> None:
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr(os, "fsync", full)
    goal = tmp_path / "goal.npy"
    assert run_dlo(["goal", "--out", str(goal), "--shapes", "near-rest"]) == 1
    err = capsys.readouterr().err
    assert str(goal) in err and "Traceback" not in err
    assert list(tmp_path.iterdir()) == []  # neither the goal nor a temporary file
