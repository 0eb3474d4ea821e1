"""One model for several recorded cables (`dlo train --data A --data B`), scored on a cable
it never saw (`dlo eval`) and fine-tuned on it (`--init-from`); and the one-line refusals:
rod data among the cables, a network of one marker count given cables of another, a
checkpoint of the other view."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from dlocli.data import MarkerDataset
from dlocli.recorded_cables.deform import held_markers

from tiny import FRAMES, run_dlo, swinging_cable

TINY_ATTENTION = ["--model", "attention", "--hidden", "8", "--heads", "2",
                  "--encoder-layers", "1"]  # fmt: skip
FAST = ["--update-steps", "30", "--rollout-steps", "4", "--eval-every", "15",
        "--device", "cpu", "--json"]  # fmt: skip


def cable(root: Path, markers: int, seed: int, rate_hz: float = 100.0) -> Path:
    """A marker dataset of a swinging cable with ``markers`` markers (4 train, 2 eval)."""

    def recording(i: int) -> np.ndarray:
        return swinging_cable(seed + i, FRAMES, markers).transpose(0, 2, 1)

    data = MarkerDataset.from_trajectories(
        {"train": [(str(i), recording(i)) for i in range(4)],
         "eval": [(str(i), recording(100 + i)) for i in range(2)]},
        held_markers(markers), {"rate_hz": rate_hz},
    )  # fmt: skip
    return data.save(root / f"cable{markers}-{rate_hz:g}hz.h5")


@pytest.fixture(scope="module")
def cables(tmp_path_factory: pytest.TempPathFactory) -> dict[int, Path]:
    root = tmp_path_factory.mktemp("cables")
    return {m: cable(root, m, seed=10 * m) for m in (8, 10, 12)}


def summary(run: Path) -> dict:
    return json.loads((run / "summary.json").read_text())


def test_one_model_learns_two_cables_then_meets_a_third(cables, tmp_path, capsys):
    shared = tmp_path / "shared"
    argv = ["train", "--data", str(cables[8]), "--data", str(cables[10]), *TINY_ATTENTION,
            *FAST, "--out", str(shared)]  # fmt: skip
    assert run_dlo(argv) == 0, capsys.readouterr().err
    trained = summary(shared)
    assert [c["markers"] for c in trained["cables"]] == [8, 10]
    assert all(c["val_episodes"] == 1 and c["val_score_cm"] > 0 for c in trained["cables"])
    assert trained["train_episodes"] == 6 and trained["val_episodes"] == 2
    saved = json.loads((shared / "spec.json").read_text())["data"]
    assert saved == [str(cables[8]), str(cables[10])]

    unseen = tmp_path / "unseen"  # zero-shot: a cable of another marker count
    assert run_dlo(["eval", "--checkpoint", str(shared), "--data", str(cables[12]),
                    "--out", str(unseen), "--json"]) == 0  # fmt: skip
    zero_shot = summary(unseen)
    assert zero_shot["episodes"] == 2 and np.isfinite(zero_shot["model_score_cm"])

    tuned = tmp_path / "tuned"  # fine-tuned on the new cable, with its own steps and rate
    assert run_dlo(["train", "--data", str(cables[12]), "--init-from", str(shared),
                    "--update-steps", "20", "--lr", "1e-4", "--rollout-steps", "4",
                    "--device", "cpu", "--out", str(tuned), "--json"]) == 0  # fmt: skip
    assert [c["markers"] for c in summary(tuned)["cables"]] == [12]
    assert run_dlo(["eval", "--checkpoint", str(tuned), "--data", str(cables[12]),
                    "--out", str(tmp_path / "tuned-eval"), "--json"]) == 0  # fmt: skip


def test_a_network_of_one_marker_count_is_refused_other_cables(cables, tmp_path, capsys):
    capsys.readouterr()
    out = tmp_path / "mlp"
    argv = ["train", "--data", str(cables[8]), "--data", str(cables[10]), "--model", "mlp",
            "--hidden", "8", *FAST, "--out", str(out)]  # fmt: skip
    assert run_dlo(argv) == 2
    line = capsys.readouterr().err.strip()
    assert "sized for 8 markers" in line and "any marker count" in line
    assert len(line.splitlines()) == 1 and not out.exists()

    single = tmp_path / "mlp8"
    assert run_dlo(["train", "--data", str(cables[8]), "--model", "mlp", "--hidden", "8",
                    *FAST, "--out", str(single)]) == 0  # fmt: skip
    capsys.readouterr()
    assert run_dlo(["eval", "--checkpoint", str(single), "--data", str(cables[10])]) == 2
    assert "for 8 segments" in capsys.readouterr().err


def test_rod_data_among_cables_and_a_rod_checkpoint_are_refused(
    cables, small_dataset_dir, tmp_path, capsys
):
    capsys.readouterr()
    out = tmp_path / "mixed"
    assert run_dlo(["train", "--data", str(cables[8]), "--data", str(small_dataset_dir),
                    *FAST, "--out", str(out)]) == 2  # fmt: skip
    line = capsys.readouterr().err.strip()
    assert "is simulated rod data" in line and len(line.splitlines()) == 1
    assert not out.exists()

    rod = tmp_path / "rod"
    assert run_dlo(["train", "--data", str(small_dataset_dir), "--model", "mlp", "--hidden",
                    "8", "--epochs", "1", "--device", "cpu", "--out", str(rod)]) == 0  # fmt: skip
    capsys.readouterr()
    assert run_dlo(["train", "--data", str(cables[8]), "--init-from", str(rod), *FAST,
                    "--out", str(tmp_path / "wrong")]) == 2  # fmt: skip
    line = capsys.readouterr().err.strip()
    assert "is a rod model" in line and len(line.splitlines()) == 1


def test_cables_at_other_rates_or_missing_are_refused_and_nothing_is_written(
    cables, tmp_path, capsys
):
    """A model step is one control period: cables recorded at different rates are refused,
    as is a --data that does not exist; either way no run directory is left."""
    slow = cable(tmp_path, 10, seed=3, rate_hz=50.0)
    for second, why in ((slow, "different rates"), (tmp_path / "absent.h5", "absent.h5")):
        capsys.readouterr()
        out = tmp_path / "refused"
        argv = ["train", "--data", str(cables[8]), "--data", str(second), *TINY_ATTENTION,
                *FAST, "--out", str(out)]  # fmt: skip
        assert run_dlo(argv) == 2
        line = capsys.readouterr().err.strip()
        assert why in line and len(line.splitlines()) == 1, line
        assert not out.exists()
