"""Ensembles (`--members N`): the mean of independently trained networks. Its flattened
layers (what the fused rollout runs) compute its forward; each member trains exactly as the
network alone would from its own seed, in parallel processes, in either view; `dlo eval`
scores it."""

from __future__ import annotations

import json

import pytest
import torch
from typer.testing import CliRunner

from dlocli.data import load_dataset
from dlocli.errors import BadInput
from dlocli.models.checkpoints import load_marker_model, load_model
from dlocli.models.ensemble import Ensemble
from dlocli.models.fit import fit
from dlocli.models.marker_model import build_marker_model
from dlocli.models.marker_training import Cable, scores_cm
from dlocli.models.network import Nodes
from dlocli.models.spec import UpdateSpec, model_spec
from dlocli.recorded_cables import deform

from tiny import pair_and_singles, run_dlo

runner = CliRunner()


def cli(*args: str):
    from dlocli.cli import app

    return runner.invoke(app, list(args))


@pytest.mark.parametrize("name", ["mlp", "arc-mlp"])
def test_its_flattened_layers_compute_its_mean(name: str) -> None:
    spec = model_spec({"name": name, "hidden": 16, "layers": 2, "members": 3})
    torch.manual_seed(0)
    ensemble = Ensemble(spec, Nodes(9, 10, 3, relative=10)).double()
    inputs = torch.randn(4, 9, 10, dtype=torch.float64)
    mean = torch.stack([m(inputs, inputs[:, 1:]) for m in ensemble.members]).mean(0)
    torch.testing.assert_close(ensemble(inputs, inputs[:, 1:]), mean)
    flat, layers = inputs.reshape(4, -1), ensemble.flat_layers(9)
    assert layers is not None
    for i, (weight, bias) in enumerate(layers):
        flat = torch.nn.functional.linear(flat, weight, bias)
        flat = flat.relu() if i < len(layers) - 1 else flat
    torch.testing.assert_close(flat.view(4, 9, 3), mean)
    flat.square().sum().backward()
    assert all(p.grad is not None and bool(p.grad.abs().sum() > 0) for p in ensemble.parameters())


def test_members_of_networks_that_are_not_flat_run_as_written() -> None:
    model = build_marker_model({"name": "in-bilstm", "hidden": 8, "members": 2}, 6,
                               deform.held_markers(6))  # fmt: skip
    x = torch.zeros(1, 6, 3)
    assert model.network.flat_layers(6) is None
    assert model._whole_rollout_layers(x, x, torch.zeros(1, 2, 6, 3)) is None
    assert model.rollout(x, x, torch.zeros(1, 3, 6, 3)).shape == (1, 3, 6, 3)


def test_one_member_is_the_network_itself() -> None:
    model = build_marker_model({"name": "mlp", "hidden": 8}, 6, deform.held_markers(6))
    assert not isinstance(model.network, Ensemble)  # checkpoints saved before keep their keys


def test_each_member_trains_as_the_network_alone_from_its_own_seed(
    marker_run, tmp_path, one_thread
) -> None:
    dataset, _ = marker_run
    common = ["train", "--data", str(dataset), "--model", "mlp", "--hidden", "16",
              "--layers", "2", "--update-steps", "30", "--rollout-steps", "4",
              "--eval-every", "10", "--device", "cpu", "--json"]  # fmt: skip
    pair, singles = pair_and_singles(cli, common, tmp_path)

    ensemble = load_marker_model(pair)
    assert isinstance(ensemble.network, Ensemble) and ensemble.spec.members == 2
    for alone, member in zip(singles, ensemble.network.members, strict=True):
        single = load_marker_model(alone).network.state_dict()
        for key, value in member.state_dict().items():
            torch.testing.assert_close(value, single[key])  # member i: seed 3 + i, as alone

    summary = json.loads((tmp_path / "pair" / "summary.json").read_text())
    rows = (tmp_path / "pair" / "metrics.csv").read_text().splitlines()
    last_val = float(rows[-1].split(",")[3])
    assert summary["cables"][0]["val_score_cm"] == pytest.approx(last_val, rel=1e-3)

    scored = cli("eval", "--checkpoint", str(tmp_path / "pair"), "--data", str(dataset),
                 "--out", str(tmp_path / "eval"), "--json")  # fmt: skip
    assert scored.exit_code == 0, scored.output
    result = json.loads((tmp_path / "eval" / "summary.json").read_text())
    ensemble.reference = True  # plain PyTorch: each member run as written, outputs averaged
    data = load_dataset(dataset)
    expected = scores_cm(ensemble, Cable(data.episodes("eval"), data.held))
    assert result["model_scores_cm"] == pytest.approx(expected, rel=1e-3)


def test_a_rod_ensemble_trains_each_member_as_the_network_alone(
    small_dataset_dir, tmp_path, one_thread
) -> None:
    """The rod view trains an ensemble through the same mechanism: member i is the network
    `dlo train --seed 3+i` trains alone; `dlo eval` scores it; it does not resume after an
    epoch, and the online loop's updates refuse it, each in one line."""
    common = ["train", "--data", str(small_dataset_dir), "--model", "mlp", "--hidden", "16",
              "--epochs", "2", "--batch-size", "64", "--device", "cpu", "--json"]  # fmt: skip
    pair, singles = pair_and_singles(cli, common, tmp_path)
    ensemble = load_model(pair, "cpu")
    assert isinstance(ensemble.network, Ensemble) and ensemble.spec.members == 2
    for alone, member in zip(singles, ensemble.network.members, strict=True):
        single = load_model(alone, "cpu").network.state_dict()
        for key, value in member.state_dict().items():
            torch.testing.assert_close(value, single[key], rtol=0, atol=0)
    assert not (pair / "checkpoints" / "last.pt").exists()  # saved once all members are done

    scored = cli("eval", "--checkpoint", str(pair), "--data", str(small_dataset_dir), "--json")
    assert scored.exit_code == 0, scored.output
    resumed = cli("train", "--resume", str(pair))
    assert resumed.exit_code == 2 and len(resumed.output.strip().splitlines()) == 1
    assert "does not resume after an epoch" in resumed.output, resumed.output
    with pytest.raises(BadInput, match="the online loop updates one network"):
        fit(ensemble, load_dataset(small_dataset_dir), UpdateSpec(device="cpu"))


@pytest.mark.parametrize(
    "members,needle",
    [("0", "greater than or equal to 1"), ("-1", "greater than or equal to 1"),
     ("65", "less than or equal to 64"), ("nan", "valid integer"), ("2.5", "valid integer")],
)  # fmt: skip
def test_a_bad_member_count_is_refused_in_one_line(marker_run, tmp_path, capsys, members, needle):
    """From the `dlo` entry point: one line, exit 2, before any run directory exists."""
    dataset, _ = marker_run
    out = tmp_path / "run"
    assert run_dlo(["train", "--data", str(dataset), "--members", members, "--out", str(out)]) == 2
    said = capsys.readouterr().err.strip()
    assert needle in said and "--members" in said and len(said.splitlines()) == 1
    assert not out.exists()


def test_a_fine_tune_saves_the_model_it_trains_and_refuses_other_members(marker_run, tmp_path,
                                                                         capsys):  # fmt: skip
    """`dlo train --init-from` a 2-member mlp: spec.json and the summary name the
    checkpoint's model (not the default in-bilstm); --members 3 is one line, nothing
    written."""
    data, _ = marker_run
    fast = ["--update-steps", "4", "--rollout-steps", "3", "--eval-every", "2", "--device",
            "cpu", "--json"]  # fmt: skip
    pair = tmp_path / "pair"
    assert run_dlo(["train", "--data", str(data), "--model", "mlp", "--hidden", "8",
                    "--members", "2", *fast, "--out", str(pair)]) == 0  # fmt: skip
    tuned = tmp_path / "tuned"
    assert run_dlo(["train", "--data", str(data), "--init-from", str(pair), *fast,
                    "--out", str(tuned)]) == 0  # fmt: skip
    saved = json.loads((tuned / "spec.json").read_text())["model"]
    assert (saved["name"], saved["hidden"], saved["members"]) == ("mlp", 8, 2), saved
    assert json.loads((tuned / "summary.json").read_text())["model"] == "mlp"
    assert load_marker_model(tuned / "checkpoints" / "final.pt").spec.members == 2
    capsys.readouterr()
    other = tmp_path / "other"
    assert run_dlo(["train", "--data", str(data), "--init-from", str(pair), "--members", "3",
                    *fast, "--out", str(other)]) == 2  # fmt: skip
    line = capsys.readouterr().err.strip()
    assert len(line.splitlines()) == 1 and "members 2, not the 3 requested" in line, line
    assert "drop --members" in line and not other.exists()
