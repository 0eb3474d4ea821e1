"""Cable codes (`--cable-code D`): one learned code per training cable. The fused rollout
(the code folded into the first bias) computes what the plain one does; training learns a
code per cable and saves it with its key; `dlo eval` gives a trained cable its own code and
another the mean; `--init-from` on a new cable adds its code; where codes cannot go, one
line and exit 2."""

from __future__ import annotations

import copy
import csv
import json
from pathlib import Path

import numpy as np
import pytest
import torch
from typer.testing import CliRunner

from dlocli.data import MarkerDataset, load_dataset
from dlocli.errors import BadInput
from dlocli.models.cable_codes import cable_key
from dlocli.models.checkpoints import load_marker_model
from dlocli.models.marker_model import build_marker_model
from dlocli.models.marker_training import Cable, scores_cm
from dlocli.models.member_fits import joined
from dlocli.recorded_cables.deform import held_markers

from tiny import pair_and_singles, run_dlo

runner = CliRunner()
EXAMPLES = Path(__file__).resolve().parents[1] / "examples"


def cli(*args: str):
    from dlocli.cli import app

    return runner.invoke(app, list(args))


@pytest.mark.parametrize("members", [1, 2])
@pytest.mark.parametrize("name", ["mlp", "arc-mlp"])
def test_the_fused_rollout_with_a_folded_code_is_the_plain_one(name: str, members: int) -> None:
    """One network, or an ensemble whose members each fold their own code."""
    torch.manual_seed(0)
    held = held_markers(7)
    model = build_marker_model({"name": name, "hidden": 16, "cable_code": 3, "members": members,
                                "length_projection": 2}, 7, held)  # fmt: skip
    model.add_cables(["a", "b"])
    assert model.codes.shape == (2, 3) if members == 1 else (2, members, 3)
    torch.nn.init.normal_(model.codes)
    x = torch.randn(4, 7, 3) * 0.1
    future = x[:, None] + torch.randn(4, 5, 7, 3) * 0.01
    model.cable = 1
    fused = model.rollout(x, x, future)
    assert model._whole_rollout_layers(x, x, future) is not None
    model.reference = True  # plain PyTorch, the code appended to every marker's features
    plain = model.rollout(x, x, future)
    torch.testing.assert_close(fused, plain, rtol=1e-4, atol=1e-6)
    model.codes.data[1, -1] += 1.0  # the last member's code of the cable in use
    assert not torch.allclose(model.rollout(x, x, future), plain)
    model.cable = 0
    assert not torch.allclose(model.rollout(x, x, future), plain)  # the code matters


def test_the_fused_rollout_trains_the_code_of_the_cable_in_use() -> None:
    torch.manual_seed(0)
    model = build_marker_model({"name": "arc-mlp", "hidden": 16, "cable_code": 2}, 6,
                               held_markers(6))  # fmt: skip
    model.add_cables(["a", "b", "c"])
    x = torch.randn(3, 6, 3) * 0.1
    model.cable = 2
    model.rollout(x, x, x[:, None].expand(-1, 4, -1, -1)).square().sum().backward()
    assert model.codes.grad is not None
    moved = model.codes.grad.abs().sum(1)
    assert moved[2] > 0 and moved[0] == 0 and moved[1] == 0


def test_a_new_cable_starts_at_the_mean_code() -> None:
    model = build_marker_model({"name": "mlp", "hidden": 8, "cable_code": 2}, 6, held_markers(6))
    assert model.add_cables(["a", "b"]) == [0, 1]
    model.codes.data = torch.tensor([[1.0, 2.0], [3.0, 6.0]])
    assert model.add_cables(["c", "a"]) == [2, 0]
    torch.testing.assert_close(model.codes[2], torch.tensor([2.0, 4.0]))
    assert model.use_cable("unseen") is None
    torch.testing.assert_close(model.code(), model.codes.mean(0))


def _second_cable(root) -> str:
    """A second tiny cable: 7 markers, another stiffness (its recordings move more)."""
    rng = np.random.default_rng(1)
    line = np.stack([np.linspace(0, 0.9, 7), np.zeros(7), np.full(7, 0.5)], -1)
    split = {s: [(str(i), line + np.cumsum(rng.normal(0, 3e-3, (12, 7, 3)), 0))
                 for i in range(n)] for s, n in (("train", 4), ("eval", 2))}  # fmt: skip
    data = MarkerDataset.from_trajectories(split, held_markers(7), {"rate_hz": 100.0})
    return str(data.save(root / "second.h5"))


def _moved(source, path, scale: float = 1.0, shift: float = 0.0) -> str:
    """Another cable: the recordings of ``source`` scaled and shifted (new recordings, so a
    new key), saved to ``path``."""
    data = load_dataset(source)
    return str(MarkerDataset.from_trajectories(
        {s: [(str(i), e * scale + shift) for i, e in enumerate(data.episodes(s))]
         for s in ("train", "eval")},
        data.held, {"rate_hz": 100.0},
    ).save(path))  # fmt: skip


def test_training_on_two_cables_learns_a_code_each_and_eval_picks_it(
    marker_run, tmp_path, one_thread
) -> None:
    first = str(marker_run[0])
    second = _second_cable(tmp_path)
    res = cli("train", "--data", first, "--data", second, "--model", "arc-mlp", "--hidden",
              "16", "--cable-code", "3", "--update-steps", "20", "--rollout-steps", "4",
              "--eval-every", "10", "--length-projection", "2", "--out",
              str(tmp_path / "run"), "--json")  # fmt: skip
    assert res.exit_code == 0, res.output
    model = load_marker_model(tmp_path / "run")
    keys = [cable_key(d.held, d.episodes("train")) for d in map(load_dataset, (first, second))]
    assert model.cable_keys == keys and model.codes.shape == (2, 3)
    assert bool((model.codes[0] != model.codes[1]).any())  # each trained on its own batches

    scored = cli("eval", "--checkpoint", str(tmp_path / "run"), "--data", second, "--json")
    assert scored.exit_code == 0, scored.output
    result = json.loads(scored.output)
    assert result["cable_code"].startswith("its own")
    data = load_dataset(second)
    model.reference = True
    model.cable = 1
    expected = scores_cm(model, Cable(data.episodes("eval"), data.held, keys[1]))
    assert result["model_scores_cm"] == pytest.approx(expected, rel=1e-3)

    # a cable it did not train on: the mean code, then --init-from learns it a code of its own
    moved = _moved(_second_cable(tmp_path / ".."), tmp_path / "third.h5", scale=1.01)
    unseen = json.loads(cli("eval", "--checkpoint", str(tmp_path / "run"), "--data",
                            str(moved), "--json").output)  # fmt: skip
    assert unseen["cable_code"].startswith("the mean of 2")
    tuned = cli("train", "--init-from", str(tmp_path / "run"), "--data", str(moved),
                "--update-steps", "10", "--rollout-steps", "4", "--eval-every", "5",
                "--out", str(tmp_path / "tuned"), "--json")  # fmt: skip
    assert tuned.exit_code == 0, tuned.output
    grown = load_marker_model(tmp_path / "tuned")
    assert grown.codes.shape == (3, 3) and grown.cable_keys[:2] == keys
    own = json.loads(cli("eval", "--checkpoint", str(tmp_path / "tuned"), "--data",
                         str(moved), "--json").output)  # fmt: skip
    assert own["cable_code"].startswith("its own")


def test_codes_refuse_a_rod_model_in_one_line(small_dataset_dir, tmp_path) -> None:
    out = tmp_path / "run"
    rod = cli("train", "--data", str(small_dataset_dir), "--cable-code", "4", "--out", str(out))
    assert rod.exit_code == 2 and "drop --cable-code" in rod.output
    assert len(rod.output.strip().splitlines()) == 1 and not out.exists()


def test_each_coded_member_trains_as_the_coded_network_alone(
    marker_run, tmp_path, one_thread, capsys
) -> None:
    """`--members 2` with codes: member i is the network and codes `--seed S+i` gives alone,
    and `joined` (and join_members.py) makes the same ensemble of them trained apart;
    `--init-from` on a new cable learns each member a code for it; `dlo eval` picks them."""
    first, second = str(marker_run[0]), _second_cable(tmp_path)
    common = ["train", "--data", first, "--data", second, "--model", "arc-mlp", "--hidden",
              "16", "--cable-code", "3", "--update-steps", "20", "--rollout-steps", "4",
              "--eval-every", "10", "--length-projection", "2", "--json"]  # fmt: skip
    pair, singles = pair_and_singles(cli, common, tmp_path)
    ensemble = load_marker_model(pair)
    assert ensemble.codes.shape == (2, 2, 3)
    for i, alone in enumerate(singles):
        single = load_marker_model(alone)
        assert single.cable_keys == ensemble.cable_keys
        torch.testing.assert_close(ensemble.codes[:, i], single.codes)
        for key, value in ensemble.network.members[i].state_dict().items():
            torch.testing.assert_close(value, single.network.state_dict()[key])
    together = joined([load_marker_model(alone) for alone in singles])  # trained apart
    assert together.cable_keys == ensemble.cable_keys
    for key, value in ensemble.state_dict().items():
        torch.testing.assert_close(together.state_dict()[key], value)
    other = copy.deepcopy(single)
    other.cable_keys = other.cable_keys[::-1]
    with pytest.raises(BadInput, match="different cables"):
        joined([single, other])
    with pytest.raises(BadInput, match="different specs"):
        joined([single, load_marker_model(marker_run[1])])
    with pytest.raises(BadInput, match="different specs, or ensembles"):
        joined([ensemble, single])
    with pytest.raises(BadInput, match="two or more"):
        joined([single])
    _check_join_members_script(singles, ensemble, tmp_path, capsys)

    moved = _moved(second, tmp_path / "third.h5", scale=1.01)
    tuned = cli("train", "--init-from", str(pair), "--data", moved,
                "--update-steps", "10", "--rollout-steps", "4", "--eval-every", "5",
                "--out", str(tmp_path / "tuned"), "--json")  # fmt: skip
    assert tuned.exit_code == 0, tuned.output
    grown = load_marker_model(tmp_path / "tuned")
    assert grown.codes.shape == (3, 2, 3) and grown.cable_keys[:2] == ensemble.cable_keys
    assert bool((grown.codes[2, 0] != grown.codes[2, 1]).any())  # each member learned its own
    scored = json.loads(cli("eval", "--checkpoint", str(tmp_path / "tuned"), "--data", moved,
                            "--json").output)  # fmt: skip
    assert scored["cable_code"].startswith("its own")
    data = load_dataset(moved)
    grown.reference = True
    expected = scores_cm(grown, Cable(data.episodes("eval"), data.held, grown.cable_keys[2]))
    assert scored["model_scores_cm"] == pytest.approx(expected, rel=1e-3)


def _check_join_members_script(singles, ensemble, tmp_path, capsys) -> None:
    """examples/real_cables/join_members.py writes the joined run directory, and refuses a
    bad join, or a folder that holds a run, in one line with exit 2, writing nothing."""
    script = str(EXAMPLES / "real_cables" / "join_members.py")
    out = tmp_path / "joined"
    assert _run_script(script, out, *singles) == 0
    written = load_marker_model(out).state_dict()
    for key, value in ensemble.state_dict().items():
        torch.testing.assert_close(written[key], value)
    refused = tmp_path / "refused"
    capsys.readouterr()
    assert _run_script(script, refused, singles[0]) == 2
    assert capsys.readouterr().err == "error: an ensemble joins two or more networks, not 1\n"
    assert not refused.exists()
    before = (out / "checkpoints" / "final.pt").read_bytes()
    assert _run_script(script, out, singles[1], singles[0]) == 2  # the run there stays
    assert "already holds a run" in capsys.readouterr().err
    assert (out / "checkpoints" / "final.pt").read_bytes() == before


def _run_script(script: str, *args) -> int:
    import runpy
    import sys
    from unittest import mock

    with mock.patch.object(sys, "argv", [script, *map(str, args)]):
        try:
            runpy.run_path(script, run_name="__main__")
        except SystemExit as stop:
            return stop.code
    return 0


def test_fine_tuning_the_code_alone_moves_nothing_else(marker_run, tmp_path, one_thread) -> None:
    first = str(marker_run[0])
    res = cli("train", "--data", first, "--model", "mlp", "--hidden", "16", "--cable-code", "2",
              "--update-steps", "10", "--rollout-steps", "4", "--eval-every", "5",
              "--out", str(tmp_path / "run"), "--json")  # fmt: skip
    assert res.exit_code == 0, res.output
    new = _moved(first, tmp_path / "new.h5", shift=0.01)
    tuned = cli("train", "--init-from", str(tmp_path / "run"), "--data", str(new),
                "--fine-tune", "code", "--update-steps", "10", "--rollout-steps", "4",
                "--eval-every", "5", "--lr", "0.05", "--val-fraction", "0",
                "--out", str(tmp_path / "tuned"), "--json")  # fmt: skip
    assert tuned.exit_code == 0, tuned.output
    before, after = load_marker_model(tmp_path / "run"), load_marker_model(tmp_path / "tuned")
    for key, value in before.network.state_dict().items():
        torch.testing.assert_close(after.network.state_dict()[key], value, rtol=0, atol=0)
    torch.testing.assert_close(after.codes[0], before.codes[0], rtol=0, atol=0)
    assert after.codes.shape == (2, 2)  # the new cable's code learned (the last one stands)
    assert bool((after.codes[1] != before.codes.mean(0)).any())


@pytest.mark.parametrize("extra", [[], ["--init-from", "RUN_WITHOUT_CODES"]])
def test_fine_tuning_a_code_that_cannot_be_is_refused_in_one_line(
    marker_run, tmp_path, extra
) -> None:
    dataset, checkpoint = marker_run
    extra = [str(checkpoint) if a == "RUN_WITHOUT_CODES" else a for a in extra]
    out = tmp_path / "run"
    res = cli("train", "--data", str(dataset), *extra, "--fine-tune", "code", "--out", str(out))
    assert res.exit_code == 2 and "--fine-tune" in res.output, res.output
    assert len(res.output.strip().splitlines()) == 1 and not out.exists()


def test_the_library_refuses_to_fine_tune_the_code_of_a_model_without_codes() -> None:
    """``fit`` itself, not only ``dlo train``, names the problem (no AttributeError)."""
    from dlocli.errors import BadInput
    from dlocli.models.fit import fit
    from dlocli.models.marker_training import Cables
    from dlocli.models.spec import TrainSpec

    episodes = [np.random.default_rng(i).normal(size=(12, 6, 3)) * 0.01 for i in range(2)]
    model = build_marker_model({"name": "mlp", "hidden": 8}, 6, held_markers(6))
    cables = Cables([Cable(episodes, held_markers(6))], [])
    with pytest.raises(BadInput, match="cable codes"):
        fit(model, cables, TrainSpec(fine_tune="code", update_steps=2))


def test_a_fine_tune_keeps_its_start_when_no_step_validates_better(
    marker_run, tmp_path, one_thread
) -> None:
    """`--init-from` with validation: the starting weights are step 0 of the history and a
    candidate, so a fine-tune that only worsens validation returns the model it began from."""
    dataset = str(marker_run[0])
    base = cli("train", "--data", dataset, "--model", "mlp", "--hidden", "16", "--update-steps",
               "10", "--rollout-steps", "4", "--eval-every", "5", "--out", str(tmp_path / "run"),
               "--json")  # fmt: skip
    assert base.exit_code == 0, base.output
    wild = cli("train", "--init-from", str(tmp_path / "run"), "--data", dataset, "--lr", "5",
               "--update-steps", "4", "--rollout-steps", "4", "--eval-every", "2",
               "--out", str(tmp_path / "tuned"), "--json")  # fmt: skip
    assert wild.exit_code == 0, wild.output
    rows = (tmp_path / "tuned" / "metrics.csv").read_text().splitlines()[1:]
    start = float(rows[0].split(",")[3])
    assert rows[0].startswith("0,0,nan,") and len(rows) == 3
    assert not any(float(r.split(",")[3]) <= start for r in rows[1:])  # lr 5: worse (or NaN)
    before, after = load_marker_model(tmp_path / "run"), load_marker_model(tmp_path / "tuned")
    for key, value in before.state_dict().items():
        torch.testing.assert_close(after.state_dict()[key], value, rtol=0, atol=0)


@pytest.mark.parametrize(
    "width,needle",
    [("-1", "greater than or equal to 0"), ("65", "less than or equal to 64"),
     ("nan", "valid integer"), ("2.5", "valid integer")],
)  # fmt: skip
def test_a_bad_code_width_is_refused_in_one_line(marker_run, tmp_path, capsys, width, needle):
    """From the `dlo` entry point: one line, exit 2, before any run directory exists."""
    out = tmp_path / "run"
    args = ["train", "--data", str(marker_run[0]), "--cable-code", width, "--out", str(out)]
    assert run_dlo(args) == 2
    said = capsys.readouterr().err.strip()
    assert needle in said and "--cable-code" in said and len(said.splitlines()) == 1
    assert not out.exists()


@pytest.mark.parametrize("keys", [None, ["a"], ["a", "a"], "ab"])
def test_a_checkpoint_whose_codes_and_keys_disagree_is_refused(marker_run, tmp_path, keys):
    from dlocli.models.checkpoints import CABLE_KEYS, read_checkpoint, save_checkpoint

    model = build_marker_model({"name": "mlp", "hidden": 8, "cable_code": 2}, 6, held_markers(6))
    model.fit_normalization([(e, model.held.numpy()) for e in
                             load_dataset(marker_run[0]).episodes("train")])  # fmt: skip
    model.add_cables(["a", "b"])
    good = save_checkpoint(model, tmp_path / "good.pt", {CABLE_KEYS: model.cable_keys})
    assert load_marker_model(good).cable_keys == ["a", "b"]
    payload = read_checkpoint(good)
    if keys is None:
        payload.pop(CABLE_KEYS)
    else:
        payload[CABLE_KEYS] = keys
    torch.save(payload, tmp_path / "bad.pt")
    res = cli("eval", "--checkpoint", str(tmp_path / "bad.pt"), "--data", str(marker_run[0]))
    assert res.exit_code == 2 and "cable codes but not their keys" in res.output, res.output
    assert len(res.output.strip().splitlines()) == 1


def test_control_plans_with_the_code_of_the_cable_it_is_given(
    marker_run, near_rest_goal, small_dataset_dir, tmp_path, capsys, one_thread
) -> None:
    """`dlo control --cable DATA` plans with that cable's code; a cable the model never
    trained on, a rod dataset, a missing or garbled file, a model without codes or no model
    at all is refused in one line, exit 2, before any run directory exists."""
    from dlocli.runs.control import ControlSpec, load_control_model

    first = str(marker_run[0])
    second = _moved(first, tmp_path / "second.h5", scale=1.01)
    run = tmp_path / "run"
    train = ["train", "--data", first, "--data", str(second), "--model", "mlp", "--hidden", "16",
             "--cable-code", "2", "--update-steps", "4", "--rollout-steps", "4",
             "--eval-every", "2", "--out", str(run)]  # fmt: skip
    assert run_dlo(train) == 0
    task = {"control_dt": 0.01}
    assert load_control_model(ControlSpec(checkpoint=run, task=task)).cable is None  # the mean
    assert load_control_model(ControlSpec(checkpoint=run, cable=second, task=task)).cable == 1
    capsys.readouterr()

    control = ["control", "--goal", str(near_rest_goal), "--checkpoint", str(run),
               "--observation", "markers", "--markers", "4", "--steps", "2",
               "--control-dt", "0.01", "--out"]  # fmt: skip
    out = tmp_path / "control"
    assert run_dlo([*control, str(out), "--cable", str(second)]) == 0
    assert json.loads((out / "summary.json").read_text())["cable"] == str(second)
    third = _moved(first, tmp_path / "third.h5", scale=1.02)
    garbage = tmp_path / "garbage.h5"
    garbage.write_bytes(b"\x89HDF\r\n" + bytes(range(256)) * 8)
    refused = [
        ([str(run), "--cable", str(third)], "never trained on --cable"),
        ([str(run), "--cable", str(small_dataset_dir)], "not a marker dataset"),
        ([str(marker_run[1]), "--cable", first], "learned no cable codes"),
        ([str(run), "--cable", str(tmp_path / "missing.h5")], "does not exist"),
        ([str(run), "--cable", str(garbage)], "not a readable HDF5 file"),
    ]
    for (checkpoint, *rest), needle in refused:
        argv = [*control, str(tmp_path / "refused"), *rest]
        argv[argv.index("--checkpoint") + 1] = checkpoint
        capsys.readouterr()
        assert run_dlo(argv) == 2
        said = capsys.readouterr().err.strip()
        assert needle in said and len(said.splitlines()) == 1, said
        assert not (tmp_path / "refused").exists()
    no_model = [a for a in control if a not in ("--checkpoint", str(run))]
    assert run_dlo([*no_model, str(tmp_path / "refused"), "--cable", first]) == 2
    said = capsys.readouterr().err.strip()
    assert "pass --checkpoint" in said and len(said.splitlines()) == 1, said
    assert not (tmp_path / "refused").exists()


def test_control_infers_the_code_while_it_runs_and_records_each_pick(
    marker_run, near_rest_goal, small_dataset_dir, tmp_path, capsys, one_thread
) -> None:
    """`dlo control --adapt-code` starts from the mean code and re-picks every --adapt-every
    steps; metrics.csv says which code each step planned with, summary.json every pick. With
    --cable, without a model, with a rod model or a model without codes: one line, exit 2,
    no run directory."""
    from dlocli.models.base import build_model
    from dlocli.models.checkpoints import save_checkpoint

    first = str(marker_run[0])
    second = _moved(first, tmp_path / "second.h5", scale=1.01)
    run = tmp_path / "run"
    train = ["train", "--data", first, "--data", str(second), "--model", "mlp", "--hidden", "16",
             "--cable-code", "2", "--update-steps", "4", "--rollout-steps", "4",
             "--eval-every", "2", "--out", str(run)]  # fmt: skip
    assert run_dlo(train) == 0
    control = ["control", "--goal", str(near_rest_goal), "--checkpoint", str(run),
               "--observation", "markers", "--markers", "4", "--steps", "20",
               "--control-dt", "0.01", "-o", "iterations=2", "--out"]  # fmt: skip
    out = tmp_path / "control"
    capsys.readouterr()
    assert run_dlo([*control, str(out), "--adapt-code", "--adapt-every", "2",
                    "--adapt-window", "16"]) == 0  # fmt: skip
    summary = json.loads((out / "summary.json").read_text())
    names = {"mean code", f"{Path(first).parent.name}'s code", "second's code"}
    assert summary["adapt_code"] and summary["cable"] is None
    picks = summary["code_picks"]
    assert [p["step"] for p in picks] == [16, 18] and {p["code"] for p in picks} <= names
    assert all(set(p["scores_cm"]) == names and p["frames"] == 16 for p in picks)
    assert summary["code_final"] == picks[-1]["code"]
    printed = capsys.readouterr().out  # the table: each re-pick's step and code
    assert "code_picks" in printed and "16:" in printed and "scores_cm" not in printed
    with open(out / "metrics.csv") as f:
        codes = [row["code"] for row in csv.DictReader(f)]
    assert codes[:16] == ["mean code"] * 16 and codes[16] == picks[0]["code"]

    rod = save_checkpoint(build_model({"name": "mlp", "hidden": 8}, 20), tmp_path / "rod.pt")
    refused = [
        ([str(run), "--cable", str(second)], "drop one"),
        ([str(marker_run[1])], "learned no cable codes"),
        ([str(rod)], "is a rod model"),
        ([str(run), "--adapt-window", "8"], "adapt-window"),
    ]
    for (checkpoint, *rest), needle in refused:
        argv = [*control, str(tmp_path / "refused"), "--adapt-code", *rest]
        argv[argv.index("--checkpoint") + 1] = checkpoint
        capsys.readouterr()
        assert run_dlo(argv) == 2
        said = capsys.readouterr().err.strip()
        assert needle in said and len(said.splitlines()) == 1, said
        assert not (tmp_path / "refused").exists()
    no_model = [a for a in control if a not in ("--checkpoint", str(run))]
    assert run_dlo([*no_model, str(tmp_path / "refused"), "--adapt-code"]) == 2
    said = capsys.readouterr().err.strip()
    assert "pass --checkpoint" in said and len(said.splitlines()) == 1, said
    assert not (tmp_path / "refused").exists()


def test_the_follower_picks_the_code_that_made_the_motion(marker_run, one_thread) -> None:
    """Frames a coded model rolled out with one cable's code (noisy as a tracker's): the
    follower starts at the mean code and, at its first re-pick, takes that cable's."""
    from dlocli.models.code_follow import MIN_WINDOW, CodeFollower, smoothed_start
    from dlocli.runs.control import ControlSpec

    assert ControlSpec.model_fields["adapt_window"].metadata[0].ge == MIN_WINDOW
    torch.manual_seed(0)
    held = held_markers(6)
    model = build_marker_model({"name": "mlp", "hidden": 16, "cable_code": 3}, 6, held)
    episodes = load_dataset(marker_run[0]).episodes("train")
    model.fit_normalization([(e, held) for e in episodes])
    model.add_cables(["a", "b", "c"])
    torch.nn.init.normal_(model.codes, std=3.0)
    rng = np.random.default_rng(0)
    start = np.repeat(episodes[0][:1], 40, 0)
    start[:, held] += np.linspace(0, 0.05, 40)[:, None, None]  # the grippers move apart
    model.cable = 1
    with torch.no_grad():
        made = torch.as_tensor(start, dtype=torch.float32)
        rolled = model.rollout(made[1:2], made[0:1], made[None, 2:])[0].double().numpy()
    frames = np.concatenate([start[:2], rolled])
    frames[:, ~held] += rng.normal(0, 2e-4, frames[:, ~held].shape)
    follower = CodeFollower(model, ["a's code", "b's code", "c's code"], every=20, window=32)
    assert model.cable is None and follower.current == "mean code"
    picks = [follower.observe(step, frame) for step, frame in enumerate(frames)]
    made_picks = [p for p in picks if p is not None]
    assert [p.step for p in made_picks] == [20]
    assert made_picks[0].name == "b's code" and model.cable == 1
    assert made_picks[0].scores_cm["b's code"] == min(made_picks[0].scores_cm.values())
    follower.reset()
    assert model.cable is None and follower.current == "mean code" and not follower.picks
    # the fit's start: a line through noise-free linear motion is that motion
    line = np.arange(10)[:, None, None] * np.ones((1, 6, 3)) * 1e-3
    np.testing.assert_allclose(smoothed_start(line, held)[:2], line[6:8], atol=1e-12)
    with pytest.raises(ValueError, match="window"):
        CodeFollower(model, [], every=1, window=MIN_WINDOW - 1)


def test_a_model_for_any_marker_count_plans_with_the_markers_observed(one_thread) -> None:
    """A model with the codes of several cables holds its first cable's held mask; one whose
    network serves any marker count takes the mask of the markers the task observes (DLO1
    has 13 markers, DLO2-4 12), so the marker view plans with it; a model of one cable, or
    of a fixed count, is left to the view."""
    from dlocli.controllers.views import MarkerView
    from dlocli.env.shape_env import make_env
    from dlocli.runs.control_code import observe_with

    from tiny import MUJOCO_ROD

    env = make_env(MUJOCO_ROD, "single", seed=0, render_mode=None, shapes="near-rest",
                   observation={"kind": "markers", "markers": 8})  # fmt: skip
    try:
        observed = env.marker_layout.held
        arc = build_marker_model({"name": "arc-mlp", "hidden": 8, "cable_code": 2}, 11,
                                 held_markers(11))  # fmt: skip
        arc.add_cables(["a"])
        observe_with(arc, env)  # one cable: its layout
        assert len(arc.held) == 11
        arc.add_cables(["b"])
        observe_with(arc, env)
        assert np.array_equal(arc.held.numpy(), observed)
        MarkerView(env, arc, arc.device)  # plans with it
        mlp = build_marker_model({"name": "mlp", "hidden": 8, "cable_code": 2}, 11,
                                 held_markers(11))  # fmt: skip
        mlp.add_cables(["a", "b"])
        observe_with(mlp, env)
        assert len(mlp.held) == 11
        with pytest.raises(BadInput, match="observe the markers it was trained on"):
            MarkerView(env, mlp, mlp.device)
    finally:
        env.close()
