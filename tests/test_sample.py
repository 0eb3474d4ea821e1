"""`dlo sample`: simulated recordings in the forms real data come in, read by the commands
that read real data (`dlo import`, `dlo track`) through the command its summary names; the
same seed writes the same files; bad input is one line, exit 2, nothing written."""

from __future__ import annotations

import json
import shlex
from pathlib import Path

import numpy as np
import pytest

from dlocli.data import MarkerDataset, load_dataset
from dlocli.recorded_cables.deform import read_trajectory
from dlocli.runs.sample_spec import SampleSpec

from tiny import file_digests, run_dlo

SHORT = ["--train", "2", "--eval", "1", "--seconds", "0.4"]


def _sample(out: Path, *flags: str) -> dict:
    assert run_dlo(["sample", *flags, *SHORT, "--out", str(out), "--json"]) == 0
    return json.loads((out / "summary.json").read_text())


def _next(summary: dict, out: Path) -> int:
    """Run the command the summary says reads the folder, into ``out``."""
    words = shlex.split(summary["next"])
    assert words[-2:] == ["--out", "runs/NAME"]
    return run_dlo([*words[1:-1], str(out), "--json"])


def test_a_sampled_cable_is_a_deform_folder_that_dlo_import_reads(tmp_path: Path) -> None:
    summary = _sample(tmp_path / "cable")
    assert summary["markers"] == 12 and summary["frames_per_recording"] == 41
    files = sorted(p.relative_to(tmp_path / "cable").as_posix()
                   for p in (tmp_path / "cable").rglob("*.pkl"))  # fmt: skip
    assert files == ["eval/take_002.pkl", "train/take_000.pkl", "train/take_001.pkl"]
    markers = read_trajectory(tmp_path / "cable" / "train" / "take_000.pkl")  # the safe reader
    assert markers.shape == (41, 12, 3) and np.isfinite(markers).all()
    spacing = np.linalg.norm(np.diff(markers[:, 1:-1], axis=1), axis=-1)  # on the rod
    assert np.all(np.abs(spacing.sum(1) - 1.0) < 0.05)  # 1 m of rod between the end markers
    assert _next(summary, tmp_path / "imported") == 0
    data = load_dataset(tmp_path / "imported")
    assert isinstance(data, MarkerDataset) and data.n_markers == 12
    assert np.flatnonzero(data.held).tolist() == [0, 1, 10, 11] and data.rate_hz == 100.0
    spec = json.loads((tmp_path / "cable" / "spec.json").read_text())
    assert spec["rate_hz"] == 100.0 and spec["task"]["control_dt"] == 0.01


def test_a_motion_capture_csv_in_mm_imports_with_the_summarys_flags(tmp_path: Path) -> None:
    flags = ["--format", "csv", "--units", "mm", "--rate-hz", "120", "--gripper-markers", "0"]
    summary = _sample(tmp_path / "cable", *flags)
    assert "--units mm" in summary["next"] and "--held 0,-1" in summary["next"]
    header = (tmp_path / "cable" / "train" / "take_000.csv").read_text().splitlines()[:2]
    assert header[0].startswith("frame,time,m0_x,m0_y,m0_z") and header[1].startswith("0,0.0")
    assert _next(summary, tmp_path / "imported") == 0
    data = load_dataset(tmp_path / "imported")
    assert data.n_markers == 10 and np.flatnonzero(data.held).tolist() == [0, 9]
    assert data.rate_hz == pytest.approx(120.0)


def test_sampled_clouds_are_frames_that_dlo_track_reads(tmp_path: Path) -> None:
    summary = _sample(tmp_path / "clouds", "clouds")
    assert summary["kind"] == "clouds" and summary["frames_per_recording"] == 11
    assert len(list((tmp_path / "clouds").rglob("*.npz"))) == 3
    assert _next(summary, tmp_path / "tracked") == 0
    tracked = json.loads((tmp_path / "tracked" / "summary.json").read_text())
    assert tracked["train_episodes"] == 2 and tracked["eval_episodes"] == 1
    assert tracked["rate_hz"] == 25.0 and tracked["points_per_frame"] > 20


def test_the_same_seed_writes_the_same_recordings(tmp_path: Path) -> None:
    _sample(tmp_path / "a", "--seed", "3")
    _sample(tmp_path / "b", "--seed", "3")
    _sample(tmp_path / "c", "--seed", "4")

    def recordings(folder: str) -> dict[str, str]:
        digests = file_digests(tmp_path / folder)
        return {Path(k).name: v for k, v in digests.items() if k.endswith(".pkl")}

    assert recordings("a") == recordings("b") != recordings("c")


@pytest.mark.parametrize(
    ("argv", "says"),
    [
        (["fish"], "fish"),
        (["--seconds", "0"], "seconds"),
        (["--train", "0"], "train"),
        (["--format", "bag"], "format"),
        (["--rate-hz", "5000"], "rate"),
    ],
)
def test_bad_input_is_one_line_and_writes_nothing(tmp_path, capsys, argv, says) -> None:
    assert run_dlo(["sample", *argv, "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error:") and says in err[0], err
    assert not (tmp_path / "out").exists()


def test_a_full_folder_needs_overwrite_and_keeps_its_files(tmp_path, capsys) -> None:
    (tmp_path / "out").mkdir()
    (tmp_path / "out" / "mine.txt").write_text("keep")
    assert run_dlo(["sample", *SHORT, "--out", str(tmp_path / "out")]) == 2
    assert "--overwrite" in capsys.readouterr().err
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == ["mine.txt"]


def test_overwrite_leaves_only_the_new_runs_recordings(tmp_path: Path) -> None:
    """Fewer recordings, or another format, over an earlier sample: `dlo import` then reads
    the new ones alone."""
    out = tmp_path / "cable"
    _sample(out)
    flags = ["--train", "1", "--eval", "0", "--seconds", "0.2", "--format", "csv"]
    assert run_dlo(["sample", *flags, "--out", str(out), "--overwrite", "--json"]) == 0
    takes = sorted(p.relative_to(out).as_posix() for p in out.rglob("take_*"))
    assert takes == ["train/take_000.csv"]
    summary = json.loads((out / "summary.json").read_text())
    assert (summary["train_recordings"], summary["eval_recordings"]) == (1, 0)


def test_a_task_given_in_part_keeps_both_grippers_moving() -> None:
    """A calibrated.yaml names the task's control period and markers, not its name."""
    given = SampleSpec.model_validate({"task": {"control_dt": 0.01}})
    assert (given.task.name, given.task.goal) == ("bimanual", "random")
    named = SampleSpec.model_validate({"task": {"name": "single"}})
    assert named.task.name == "single"


def test_each_kind_has_its_own_folder_unless_given(tmp_path: Path, monkeypatch) -> None:
    monkeypatch.chdir(tmp_path)
    for kind in ("clouds", "cable"):
        assert run_dlo(["sample", kind, "--train", "1", "--eval", "0", "--seconds", "0.1"]) == 0
    assert sorted(p.name for p in (tmp_path / "samples").iterdir()) == ["cable", "clouds"]
    assert list((tmp_path / "samples" / "clouds" / "train").glob("*.npz"))
