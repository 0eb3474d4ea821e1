"""`dlo adapt`: a coded model trained here on two cables picks a third cable's code from its
first recordings (each candidate's score on them, the pick the lowest), learns it or
fine-tunes within a budget, and writes a checkpoint `dlo eval` and `dlo control --cable` give
the new cable its code from; bad input is one line, exit 2, nothing written."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch

from dlocli.data import MarkerDataset, load_dataset
from dlocli.models.cable_codes import cable_key
from dlocli.models.checkpoints import load_marker_model, save_checkpoint
from dlocli.models.code_pick import MEAN_CODE, best, score_candidates
from dlocli.models.marker_training import Cable, scores_cm
from dlocli.recorded_cables.deform import held_markers

from tiny import run_dlo, swinging_cable

FAST = ["--update-steps", "40", "--rollout-steps", "4", "--eval-every", "20", "--lr", "3e-3",
        "--device", "cpu"]  # fmt: skip
TINY = ["--hidden", "16", "--cable-code", "3", "--length-projection", "2", *FAST]


def cable(root: Path, name: str, seed: int, markers: int = 8, train: int = 4) -> Path:
    """A marker dataset of a swinging cable (``train`` train and 2 eval recordings of 40
    frames), its motion scaled by its seed so that each cable moves its own way."""
    scale = 1.0 + 0.1 * (seed % 7)

    def recording(i: int) -> np.ndarray:
        frames = swinging_cable(seed * 1000 + i, 40, markers).transpose(0, 2, 1)
        return frames[:1] + (frames - frames[:1]) * scale

    data = MarkerDataset.from_trajectories(
        {"train": [(str(i), recording(i)) for i in range(train)],
         "eval": [(str(i), recording(100 + i)) for i in range(2)]},
        held_markers(markers), {"rate_hz": 100.0},
    )  # fmt: skip
    return data.save(root / f"{name}.h5")


@pytest.fixture(scope="module")
def runs(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """Two training cables, a new one, one of another marker count, one without train
    recordings; a coded arc-mlp and a coded mlp trained on the two, an mlp without codes."""
    root = tmp_path_factory.mktemp("adapt")
    paths = {name: cable(root, name, seed) for name, seed in (("cableA", 1), ("cableB", 4),
                                                              ("new", 6))}  # fmt: skip
    paths["ten"] = cable(root, "ten", 9, markers=10)
    eval_only = MarkerDataset.from_trajectories(
        {"eval": [("0", swinging_cable(5, 40, 8).transpose(0, 2, 1))]}, held_markers(8),
        {"rate_hz": 100.0},
    )  # fmt: skip
    paths["eval_only"] = eval_only.save(root / "eval_only.h5")
    torch.set_num_threads(1)
    both = ["--data", str(paths["cableA"]), "--data", str(paths["cableB"])]
    for name, argv in (
        ("coded", ["--model", "arc-mlp", "--points", "8", *TINY, *both]),
        ("coded_mlp", ["--model", "mlp", *TINY, *both]),
        ("plain", ["--model", "mlp", "--hidden", "16", *FAST, "--data", str(paths["cableA"])]),
    ):
        paths[name] = root / name
        assert run_dlo(["train", *argv, "--out", str(paths[name]), "--json"]) == 0, name
    return paths


def adapt(runs: dict[str, Path], out: Path, *flags: str, checkpoint: str = "coded",
          data: str = "new") -> int:  # fmt: skip
    return run_dlo(["adapt", "--checkpoint", str(runs[checkpoint]), "--data", str(runs[data]),
                    "--out", str(out), "--json", *flags])  # fmt: skip


def summary(run: Path) -> dict:
    return json.loads((run / "summary.json").read_text())


def test_the_pick_is_the_code_that_predicts_the_recordings_read_best(runs, tmp_path, capsys):
    out = tmp_path / "picked"
    assert adapt(runs, out, "--recordings", "2") == 0
    result = json.loads(capsys.readouterr().out)
    assert result == summary(out)
    names = [r["name"] for r in result["scores"]]
    assert names == [MEAN_CODE, "cableA's code", "cableB's code", "freeze the free markers"]
    candidates = {r["name"]: r["score_cm"] for r in result["scores"] if r["role"] != "reference"}
    assert result["picked"] == min(candidates, key=candidates.get)
    assert result["picked_cm"] == candidates[result["picked"]] < result["freeze_cm"]
    assert result["fine_tune"] is None and result["update_steps"] == 0
    assert (out / "scores.csv").read_text().splitlines()[0] == "name,score_cm,role"
    assert json.loads((out / "spec.json").read_text())["recordings"] == 2

    # the library's scores of the same candidates, and the written code is the pick's
    before, after = load_marker_model(runs["coded"]), load_marker_model(out)
    new = load_dataset(runs["new"])
    read = new.episodes("train")[:2]
    scored = score_candidates(before, read, new.held, ["cableA's code", "cableB's code"])
    assert {c.name: round(c.mean_cm, 4) for c in scored} == candidates
    assert after.cable_keys == [*before.cable_keys, cable_key(new.held, new.episodes("train"))]
    pick = best(scored)
    expected = before.codes.mean(0) if pick.row is None else before.codes[pick.row]
    torch.testing.assert_close(after.codes[2], expected)
    torch.testing.assert_close(after.codes[:2], before.codes)
    for key, value in before.network.state_dict().items():
        torch.testing.assert_close(after.network.state_dict()[key], value, rtol=0, atol=0)

    # `dlo eval` gives the new cable its code; `dlo control --cable` plans with it
    assert run_dlo(["eval", "--checkpoint", str(out), "--data", str(runs["new"]), "--json"]) == 0
    scored_eval = json.loads(capsys.readouterr().out)
    assert scored_eval["cable_code"].startswith("its own")
    after.reference = True
    own = scores_cm(after, Cable(new.episodes("eval"), new.held))
    assert scored_eval["model_scores_cm"] == pytest.approx(own, rel=1e-3)


def test_control_plans_with_the_adapted_code(runs, tmp_path):
    from dlocli.runs.control import ControlSpec, load_control_model

    out = tmp_path / "picked"
    assert adapt(runs, out) == 0
    spec = ControlSpec(checkpoint=out, cable=runs["new"], task={"control_dt": 0.01})
    assert load_control_model(spec).cable == 2  # the new cable's row


def test_learning_the_code_alone_moves_nothing_else(runs, tmp_path, capsys):
    out = tmp_path / "code"
    assert adapt(runs, out, "--fine-tune", "code", "--update-steps", "20", "--eval-every",
                 "5", "--rollout-steps", "4") == 0  # fmt: skip
    result = json.loads(capsys.readouterr().out)
    assert result["update_steps"] == 20 and result["fine_tune"] == "code"
    assert result["adapted_cm"] <= result["picked_cm"]  # the pick stands unless bettered
    assert [r["role"] for r in result["scores"]][-2:] == ["adapted", "reference"]
    assert json.loads((out / "spec.json").read_text())["lr"] == 1e-2  # resolved
    rows = (out / "metrics.csv").read_text().splitlines()
    assert rows[1].startswith("0,0,nan,") and len(rows) == 6
    before, after = load_marker_model(runs["coded"]), load_marker_model(out)
    for key, value in before.network.state_dict().items():
        torch.testing.assert_close(after.network.state_dict()[key], value, rtol=0, atol=0)
    torch.testing.assert_close(after.codes[:2], before.codes, rtol=0, atol=0)
    assert run_dlo(["eval", "--checkpoint", str(out), "--data", str(runs["new"]), "--json"]) == 0


def test_a_fine_tune_stops_at_its_seconds_and_serves_any_marker_count(runs, tmp_path, capsys):
    """The whole model, on a cable of 10 markers (arc-mlp serves any count), stopped by
    --seconds long before --update-steps."""
    out = tmp_path / "all"
    assert adapt(runs, out, "--fine-tune", "all", "--update-steps", "100000", "--seconds",
                 "1", "--eval-every", "50", "--rollout-steps", "4", data="ten") == 0  # fmt: skip
    result = json.loads(capsys.readouterr().out)
    assert 0 < result["update_steps"] < 100000 and result["fit_seconds"] < 30
    assert result["adapted_cm"] <= result["picked_cm"]
    assert run_dlo(["eval", "--checkpoint", str(out), "--data", str(runs["ten"]), "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["cable_code"].startswith("its own")


def _rod_checkpoint(root: Path) -> Path:
    from dlocli.models.base import build_model

    return save_checkpoint(build_model({"name": "mlp", "hidden": 8}, 6), root / "rod.pt")


def _rod_dataset(root: Path) -> Path:
    """A rod dataset (the simulator's full state) of two still episodes of 6 segments."""
    from dlocli.data import Dataset, Episode

    line = np.stack([np.linspace(0, 1, 6), np.zeros(6), np.full(6, 0.5)], -1)
    still = Episode(positions=np.repeat(line[None], 4, 0), quaternions=np.tile([1.0, 0, 0, 0],
                    (4, 6, 1)), grippers=np.tile([0, 0, 0.5, 1, 0, 0, 0], (4, 2, 1)),
                    actions=np.zeros((3, 2, 6)), rewards=np.zeros(3), goal=line)  # fmt: skip
    return Dataset.from_episodes([still, still]).save(root / "rod.h5")


@pytest.mark.parametrize(
    "flags,needle",
    [
        ({"data": "rod"}, "simulated rod data"),
        ({"checkpoint": "rod_model"}, "is a rod model"),
        ({"checkpoint": "plain"}, "learned no cable codes"),
        ({"checkpoint": "coded_mlp", "data": "ten"}, "sized for 8 markers"),
        ({"argv": ["--recordings", "0"]}, "greater than or equal to 1"),
        ({"data": "eval_only"}, "no train"),
        ({"argv": ["--recordings", "5"]}, "pass --recordings 4 or fewer"),
        ({"argv": ["--fine-tune", "code", "--seconds", "nan"]}, "finite number"),
        ({"argv": ["--fine-tune", "all", "--seconds", "inf"]}, "finite number"),
        ({"argv": ["--fine-tune", "code", "--update-steps", "nan"]}, "valid integer"),
        ({"argv": ["--fine-tune", "code", "--lr", "nan"]}, "finite number"),
        ({"argv": ["--update-steps", "50"]}, "add --fine-tune"),
        ({"data": "cableA"}, "it has the cable's own code"),
        ({"argv": ["--fine-tune", "twice"]}, "--fine-tune"),
    ],
)  # fmt: skip
def test_bad_input_is_one_line_exit_2_and_writes_nothing(runs, tmp_path, capsys, flags, needle):
    paths = {**runs, "rod": _rod_dataset(tmp_path), "rod_model": _rod_checkpoint(tmp_path)}
    out = tmp_path / "refused"
    capsys.readouterr()
    code = adapt(paths, out, *flags.get("argv", []), checkpoint=flags.get("checkpoint", "coded"),
                 data=flags.get("data", "new"))  # fmt: skip
    said = capsys.readouterr()
    assert code == 2 and said.out == "", said
    lines = said.err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error:") and needle in lines[0], said.err
    assert not out.exists()


def test_an_out_inside_the_model_run_is_refused(runs, capsys):
    out = runs["coded"] / "adapted"
    assert adapt(runs, out) == 2
    assert "inside" in capsys.readouterr().err and not out.exists()
