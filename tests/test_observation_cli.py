"""`dlo online` and `dlo control` with the markers observation and every tracker fault, and
the one-line refusals of bad observation settings."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from dlocli.data import load_dataset

from tiny import dlo_import, file_digests, run_dlo, write_cable

FAULTS = ["--noise-mm", "2", "--latency-steps", "1", "--dropout", "0.05"]
OCCLUSION = ["--occlusion-probability", "0.1"]
TINY_ONLINE = ["online", "--observation", "markers", "--markers", "6", "--iters", "2",
               "--trials", "2", "--steps", "15", "--initial-episodes", "2", "--hidden", "8",
               "--update-steps", "12", "--rollout-steps", "3", "--shapes", "near-rest",
               "--seed", "3"]  # fmt: skip


@pytest.fixture(scope="module")
def marker_run(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("online") / "run"
    assert run_dlo([*TINY_ONLINE, *FAULTS, "--out", str(out)]) == 0
    return out


def test_online_learns_the_marker_model_from_the_reports(marker_run):
    summary = json.loads((marker_run / "summary.json").read_text())
    assert summary["iterations_done"] == 2 and summary["transitions"] == 90
    spec = json.loads((marker_run / "spec.json").read_text())
    assert spec["task"]["observation"]["latency_steps"] == 1
    trial = load_dataset(marker_run / "data" / "iter_01" / "trial_001.h5")
    assert trial.markers.shape == (16, 8, 3) and trial.positions.shape == (16, 20, 3)
    import torch

    payload = torch.load(marker_run / "checkpoints" / "iter_02.pt", weights_only=True)
    assert payload["form"] == "markers" and payload["control_dt"] == 0.02


def test_control_plans_through_the_marker_model_under_faults(marker_run, near_rest_goal, tmp_path):
    out = tmp_path / "control"
    argv = ["control", "--goal", str(near_rest_goal), "--checkpoint",
            str(marker_run / "checkpoints" / "iter_02.pt"), "--observation", "markers",
            "--markers", "6", "--steps", "8", "--shapes", "near-rest", "--out", str(out),
            "--stop-after-lost-s", "0.1", *FAULTS, *OCCLUSION]  # fmt: skip
    assert run_dlo(argv) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["steps"] == 8 and summary["initial_error_mm"] > 0
    # a full-state run of the same marker model is refused in one line
    assert run_dlo([*argv[:7], "--steps", "8", "--out", str(tmp_path / "x")]) == 2


@pytest.mark.parametrize(
    ("flags", "says"),
    [
        (["--observation", "markers", "--noise-mm", "-1"], "--noise-mm"),
        (["--noise-mm", "2"], "--observation markers"),
        (["--observation", "markers", "--latency-steps", "15"], "shorter than the episode"),
        (["--observation", "markers", "--dropout", "1"], "dropout"),
        (["--observation", "markers", "--markers", "1"], "markers"),
        # a marker model's update counts steps: --epochs would be silently ignored
        (["--observation", "markers", "--epochs", "3"], "--schedule steps --update-steps"),
    ],
)
def test_bad_observation_settings_get_one_line(flags, says, tmp_path, capsys):
    out = tmp_path / "run"
    out.mkdir()
    (out / "keep.txt").write_text("mine")
    before = file_digests(out)
    argv = ["online", "--steps", "15", "--out", str(out), *flags]
    assert run_dlo(argv) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and says in err, err
    assert file_digests(out) == before


def test_markers_off_the_rod_get_one_line(tmp_path, capsys):
    spec = tmp_path / "spec.yaml"
    arcs = "    marker_arc_lengths: [0, 0.5, 1.7]\n"  # past half a rod length behind the end
    spec.write_text("task:\n  observation:\n    kind: markers\n" + arcs)
    assert run_dlo(["online", "--spec", str(spec), "--out", str(tmp_path / "run")]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "marker_arc_lengths" in err, err
    # a marker count the arc lengths contradict (a calibrated spec holds them): not ignored
    spec.write_text("task:\n  observation:\n    marker_arc_lengths: [0, 0.5, 1]\n")
    argv = ["online", "--spec", str(spec), "--observation", "markers", "--markers", "4"]
    assert run_dlo([*argv, "--out", str(tmp_path / "run")]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "drop --markers" in err, err


def test_control_observes_two_held_markers_per_end(near_rest_goal, tmp_path, capsys):
    """A model of a cable held by two markers at each end (DEFORM's layout, `dlo import`'s
    default) plans through `dlo control`'s flags: the outer held markers on the grippers."""
    write_cable(tmp_path / "cable", n_train=3, n_eval=1)  # 6 markers at 100 Hz
    assert dlo_import(tmp_path / "cable", tmp_path / "data") == 0
    assert load_dataset(tmp_path / "data").held.tolist() == [1, 1, 0, 0, 1, 1]
    assert run_dlo(["train", "--data", str(tmp_path / "data"), "--model", "mlp", "--hidden", "8",
                    "--update-steps", "2", "--rollout-steps", "2", "--eval-every", "2",
                    "--device", "cpu", "--out", str(tmp_path / "model")]) == 0  # fmt: skip
    argv = ["control", "--goal", str(near_rest_goal), "--checkpoint", str(tmp_path / "model"),
            "--observation", "markers", "--control-dt", "0.01", "--steps", "3",
            "--shapes", "near-rest"]  # fmt: skip
    out = tmp_path / "control"
    arcs = ["--marker-arc-lengths", "-0.1,0,0.4,0.6,1,1.1", "--gripper-markers", "0"]
    assert run_dlo([*argv, *arcs, "--out", str(out)]) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["steps"] == 3 and not summary["diverged"]
    observed = json.loads((out / "spec.json").read_text())["task"]["observation"]
    assert observed["marker_arc_lengths"] == [-0.1, 0, 0.4, 0.6, 1, 1.1]
    # one held marker at each end is another layout: refused in one line
    wrong = tmp_path / "wrong"
    assert run_dlo([*argv, "--markers", "6", "--gripper-markers", "0", "--out", str(wrong)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "4 held" in err and "2 held" in err, err
    assert not wrong.exists()
