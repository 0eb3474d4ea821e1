"""Issue 70's acceptance: a model family added to the tree (tests/tiny_family.py: its module
and one registration line) trains in both views, as an ensemble and with cable codes, where
the view can have them; the rod view, which has one rod and so no cable to tell apart,
refuses codes in one stated line. An ensemble's member i is the network trained alone from
seed + i; `dlo eval` scores the ensemble; planners read it as one model."""

from __future__ import annotations

import json
import sys

import numpy as np
import pytest
import torch
from typer.testing import CliRunner

from dlocli.data import MarkerDataset, load_dataset
from dlocli.errors import BadInput, UnknownName
from dlocli.models.base import NO_CABLE_CODES, build_model
from dlocli.models.checkpoints import load_marker_model, load_model, load_planning_model
from dlocli.models.ensemble import Ensemble
from dlocli.models.fit import ENSEMBLE_DOES_NOT_RESUME
from dlocli.models.member_fits import member_state
from dlocli.models.spec import TrainSpec
from dlocli.recorded_cables.deform import held_markers
from dlocli.registry import models
from dlocli.runs.train import run_training

runner = CliRunner()


def cli(*args: str):
    from dlocli.cli import app

    return runner.invoke(app, list(args))


@pytest.fixture(scope="module")
def family():
    """The family's module imported (its registration line run) for these tests alone; the
    members' worker processes import it as they unpickle its spec."""
    import tiny_family

    yield tiny_family.NAME
    models.unregister(tiny_family.NAME)
    sys.modules.pop("tiny_family", None)


def test_a_registration_is_removed_whole_and_an_unknown_name_is_refused():
    models.register("scratch", "dlocli.models.network:Network", "a stand-in",
                    spec="dlocli.models.spec:ModelSpec")  # fmt: skip
    models.unregister("scratch")
    assert "scratch" not in models and models.summary("scratch") == ""
    with pytest.raises(UnknownName, match="unknown model 'scratch'; valid models: "):
        models.spec_cls("scratch")  # its spec went with it
    with pytest.raises(UnknownName, match="unknown model 'scratch'"):
        models.unregister("scratch")


def train(out, data, seed: int, **options) -> dict:
    fields = {"name": options.pop("name"), "hidden": 8, **options.pop("model", {})}
    spec = TrainSpec(data=data, model=fields, device="cpu", seed=seed, out=out, **options)
    return run_training(spec)


def same_weights(member: torch.nn.Module, alone: torch.nn.Module) -> None:
    expected = alone.state_dict()
    for key, value in member.state_dict().items():
        torch.testing.assert_close(value, expected[key], rtol=0, atol=0)


def test_the_rod_view_trains_it_alone_and_as_an_ensemble(
    family, small_dataset_dir, tmp_path, one_thread
):
    rod = {"name": family, "epochs": 1, "batch_size": 64}
    train(tmp_path / "alone", [small_dataset_dir], 4, **rod)
    pair = train(tmp_path / "pair", [small_dataset_dir], 3, model={"members": 2}, **rod)
    assert pair["model"] == family and np.isfinite(pair["val_loss"])
    assert (tmp_path / "pair" / "metrics.csv").read_text().count("\n") == 2  # header, epoch 1

    ensemble = load_model(tmp_path / "pair", "cpu")
    assert isinstance(ensemble.network, Ensemble) and ensemble.spec.members == 2
    same_weights(ensemble.network.members[1], load_model(tmp_path / "alone", "cpu").network)

    # planners read it as one model: each step's change is the members' mean
    planner = load_planning_model(tmp_path / "pair" / "checkpoints" / "final.pt")
    recorded = load_dataset(small_dataset_dir).transitions(np.arange(1))["state"][:3]
    state = torch.as_tensor(recorded, dtype=torch.float32)
    action = torch.zeros(3, 2, 6)
    action[:, 1, 0] = 0.5
    inputs = planner.normalize(state, action, None)
    views = []
    for index in range(2):
        view = build_model(planner.spec.model_copy(update={"members": 1}), planner.n_segments)
        view.load_state_dict(member_state(planner, index))
        views.append(view.predict_delta(*inputs))
    torch.testing.assert_close(planner.predict_delta(*inputs), torch.stack(views).mean(0))
    plan = action[:, None].expand(3, 4, 2, 6)
    assert planner.rollout(state, plan).shape == (3, 4, planner.n_segments, 7)

    scored = cli("eval", "--checkpoint", str(tmp_path / "pair"), "--data",
                 str(small_dataset_dir), "--device", "cpu", "--json")  # fmt: skip
    assert scored.exit_code == 0, scored.output
    assert json.loads(scored.output.strip().splitlines()[-1])["one_step_mm"] > 0

    with pytest.raises(BadInput, match="drop --cable-code") as refused:
        train(tmp_path / "codes", [small_dataset_dir], 3, model={"cable_code": 2}, **rod)
    assert str(refused.value) == NO_CABLE_CODES and not (tmp_path / "codes").exists()
    spec = TrainSpec.model_validate_json((tmp_path / "pair" / "spec.json").read_text())
    with pytest.raises(BadInput) as no_resume:
        run_training(spec, resume=True)
    assert str(no_resume.value) == ENSEMBLE_DOES_NOT_RESUME


def two_cables(root) -> list:
    """Two small recorded cables of 6 markers, one swinging more than the other."""
    held = held_markers(6)
    line = np.stack([np.linspace(0, 0.8, 6), np.zeros(6), np.full(6, 0.5)], -1)
    paths = []
    for cable, step in enumerate((1e-3, 3e-3)):
        rng = np.random.default_rng(cable)

        def recording() -> np.ndarray:
            return line + np.cumsum(rng.normal(0, step, (12, 6, 3)), 0)  # noqa: B023

        trajectories = {split: [(str(i), recording()) for i in range(n)]
                        for split, n in (("train", 4), ("eval", 2))}  # fmt: skip
        data = MarkerDataset.from_trajectories(trajectories, held, {"rate_hz": 100.0})
        paths.append(data.save(root / f"cable{cable}.h5"))
    return paths


def test_the_marker_view_trains_it_as_an_ensemble_with_cable_codes(family, tmp_path, one_thread):
    cables = two_cables(tmp_path)
    markers = {"name": family, "model": {"cable_code": 2}, "update_steps": 20,
               "rollout_steps": 4, "eval_every": 10, "batch_size": 4}  # fmt: skip
    train(tmp_path / "alone", cables, 6, **markers)
    markers["model"] = {"cable_code": 2, "members": 2}
    pair = train(tmp_path / "pair", cables, 5, **markers)
    assert pair["form"] == "markers" and len(pair["cables"]) == 2

    ensemble = load_marker_model(tmp_path / "pair")
    assert isinstance(ensemble.network, Ensemble) and ensemble.codes.shape == (2, 2, 2)
    alone = load_marker_model(tmp_path / "alone")
    same_weights(ensemble.network.members[1], alone.network)
    torch.testing.assert_close(ensemble.codes.detach()[:, 1], alone.codes.detach())

    scored = cli("eval", "--checkpoint", str(tmp_path / "pair"), "--data", str(cables[1]),
                 "--device", "cpu", "--json")  # fmt: skip
    assert scored.exit_code == 0, scored.output
    assert json.loads(scored.output.strip().splitlines()[-1])["cable_code"].startswith("its own")
