"""The online loop's fixed-cost model update (``FitSpec.schedule == "steps"``), on real data
with a real model: its step budget, its early stopping, a cost that does not grow with the
data, determinism, the weighting of the newest episodes, and exact resume in `dlo online`."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch
from pydantic import ValidationError
from typer.testing import CliRunner

from dlocli.cli import app
from dlocli.data import load_dataset
from dlocli.migrations import LEGACY_VALUES
from dlocli.models.base import build_model
from dlocli.models.checkpoints import read_checkpoint
from dlocli.models.fit import fit as fit_model
from dlocli.models.rod_training import transition_tensors, validation_loss
from dlocli.models.spec import TrainSpec, UpdateSpec
from dlocli.models.splits import split_episodes
from dlocli.models.step_schedule import recent_rows, sample_batch
from dlocli.models.update_steps import train_like_online

runner = CliRunner()
STEPS = {"schedule": "steps", "lr": 3e-3, "batch_size": 16, "val_fraction": 0.2, "device": "cpu"}


def fresh(data, seed: int = 0):
    torch.manual_seed(seed)
    return build_model({"hidden": 16}, data.n_segments)


def weights(model) -> list[torch.Tensor]:
    return [p.detach().clone() for p in model.parameters()]


pytestmark = pytest.mark.usefixtures("one_thread")  # conftest.py


@pytest.fixture(scope="module")
def data(small_dataset_dir):
    return load_dataset(small_dataset_dir)


def test_defaults_leave_the_papers_schedule_and_old_fingerprints():
    fit = UpdateSpec()
    assert fit.schedule == "epochs"
    changed = {k for k, v in LEGACY_VALUES["fit"].items() if getattr(fit, k) != v}
    assert changed == {"mirror"}  # on by default since the bimanual transfer measurements
    help_text = runner.invoke(app, ["online", "--help"], env={"COLUMNS": "250"}).output
    assert "--schedule" in help_text and "--update-steps" in help_text
    assert '"epochs" (the paper\'s)' in " ".join(help_text.split())


def test_takes_exactly_update_steps_without_early_stopping(data):
    fit = UpdateSpec(**STEPS, update_steps=30, eval_every=10, patience=0)
    result = fit_model(fresh(data), data, fit)
    assert result.steps == 30
    assert [r.count for r in result.history] == [10, 20, 30]
    lowest = min(result.history, key=lambda record: record.val_loss)
    assert (result.best_step, result.best_val_loss) == (lowest.count, lowest.val_loss)
    # Adam's step count is that of the weights kept (the best validation)
    assert result.optimizer_state["state"][0]["step"] == result.best_step


def test_early_stopping_stops_and_restores_the_best_weights(data):
    """At a learning rate too small to change a float32 weight, no validation improves on
    the starting weights: training stops after `patience` validations and keeps them."""
    model = fresh(data)
    before = weights(model)
    fit = UpdateSpec(**{**STEPS, "lr": 1e-12}, update_steps=50, eval_every=2, patience=3)
    events: list = []
    result = fit_model(model, data, fit, progress=events.append)
    assert result.steps == 6 < fit.update_steps
    # the progress bar ends full, at the steps taken, saying why
    last = events[-1]
    assert (last.unit, last.done, last.total, last.values["stopped_early"]) == ("step", 6, 6, True)
    assert [r.count for r in result.history] == [2, 4, 6]
    assert result.best_step == 0
    for a, b in zip(before, weights(model), strict=True):
        assert torch.equal(a, b)
    # a learning rate that moves the weights: stopped or not, the kept weights are the best
    fit = UpdateSpec(**STEPS, update_steps=40, eval_every=2, patience=2)
    result = fit_model(model, data, fit)
    assert result.steps <= 40 and result.history[-1].count == result.steps
    val = transition_tensors(data, result.val_episodes, torch.device("cpu"))
    assert result.best_val_loss == min(r.val_loss for r in result.history)
    assert validation_loss(model, val) == pytest.approx(result.best_val_loss, rel=1e-6)


def counting(model) -> dict[str, int]:
    """Count the rows ``model.loss`` sees, for training (with gradients) and validation."""
    seen = {"train_calls": 0, "train_rows": 0, "val_rows": 0}
    loss = model.loss

    def counted(state, *args, **kwargs):
        kind = "train" if torch.is_grad_enabled() else "val"
        seen[f"{kind}_rows"] += len(state)
        seen["train_calls"] += kind == "train"
        return loss(state, *args, **kwargs)

    model.loss = counted
    return seen


def test_cost_does_not_grow_with_the_data(data):
    """The same batches and validation rows on 4 episodes as on 24 (counted, not timed)."""
    fit = UpdateSpec(**STEPS, update_steps=12, eval_every=4, patience=0, val_transitions=40)
    counts = []
    for dataset in (data.subset(np.arange(4)), data.concat(data).concat(data).concat(data)):
        model = fresh(dataset)
        counts.append(counting(model))
        fit_model(model, dataset, fit)
    assert counts[0] == counts[1]
    assert counts[0]["train_calls"] == 12 and counts[0]["train_rows"] == 12 * 16
    assert counts[0]["val_rows"] == (1 + 3) * 40  # the starting weights, then 3 validations


def test_same_seed_same_weights(data):
    fit = UpdateSpec(**STEPS, update_steps=15, eval_every=5, seed=7)
    runs = []
    for seed in (7, 7, 8):
        model = fresh(data)
        fit_model(model, data, fit.model_copy(update={"seed": seed}), recent_episodes=[5])
        runs.append(weights(model))
    assert all(torch.equal(a, b) for a, b in zip(runs[0], runs[1], strict=True))
    assert not all(torch.equal(a, b) for a, b in zip(runs[0], runs[2], strict=True))


@pytest.mark.parametrize("mirror", [False, True])
def test_recent_rows_are_those_of_the_recent_episodes(data, mirror):
    train_eps, _ = split_episodes(data.n_episodes, 0.2)
    recent = train_eps[-2:]
    rows = recent_rows(data, train_eps, np.array([*recent, 99]), mirror)
    cpu = torch.device("cpu")
    every = transition_tensors(data, train_eps, cpu, mirror=mirror)
    only = transition_tensors(data, recent, cpu, mirror=mirror)
    assert torch.equal(every["state"][rows], only["state"])
    assert torch.equal(every["next_state"][rows], only["next_state"])


def test_batches_weight_in_the_newest_episodes(data):
    fit = UpdateSpec(**STEPS, recent_fraction=0.5)
    gen = torch.Generator().manual_seed(0)
    recent = torch.arange(90, 100)
    batch = sample_batch(100, recent, fit, gen)
    assert len(batch) == 16 and bool(torch.isin(batch[:8], recent).all())
    assert len(sample_batch(10, recent - 90, fit, gen)) == 16  # all rows recent: unweighted
    # in training: the share of sampled rows from the recent episodes
    train_eps, _ = split_episodes(data.n_episodes, fit.val_fraction)
    recent_eps = train_eps[-1:]  # one training episode of five: a fifth of the rows
    uniform = len(recent_rows(data, train_eps, recent_eps, False)) / sum(
        int(data.episode_lengths[e]) - 1 for e in train_eps
    )
    shares = {}
    for fraction in (0.0, 0.5):
        fit_k = fit.model_copy(update={"recent_fraction": fraction, "update_steps": 40})
        shares[fraction] = fit_model(fresh(data), data, fit_k, recent_episodes=recent_eps)
    assert shares[0.0].recent_share == pytest.approx(uniform, abs=0.06)
    assert shares[0.5].recent_share == pytest.approx(0.5 + 0.5 * uniform, abs=0.06)


def test_dlo_train_offers_only_the_fields_it_uses(small_dataset_dir, tmp_path):
    """`dlo train` has no schedule: its spec refuses the online loop's update fields, its
    --help lists none, and the specs it saved when it held them (at the one schedule it
    ran) still load, where saved specs are read."""
    with pytest.raises(ValidationError, match="schedule"):
        TrainSpec(data=small_dataset_dir, schedule="steps")
    saved = {"schedule": "epochs", "recent_fraction": 0.5, "patience": 5, "val_transitions": 9}
    assert TrainSpec.model_validate(TrainSpec.saved_layout(saved)) == TrainSpec()
    help_text = runner.invoke(app, ["train", "--help"], env={"COLUMNS": "250"}).output
    assert "--epochs" in help_text and "--update-steps" in help_text  # rod and marker data
    for flag in ("--schedule", "--recent-fraction", "--patience", "--val-transitions"):
        assert flag not in help_text, flag
    spec = tmp_path / "steps.yaml"
    spec.write_text("schedule: steps\n")
    res = runner.invoke(app, ["train", "--data", str(small_dataset_dir), "--spec", str(spec),
                              "--out", str(tmp_path / "run")])  # fmt: skip
    assert res.exit_code == 2 and "field 'schedule' is retired" in res.output, res.output
    assert not (tmp_path / "run").exists()


def test_online_steps_schedule_resumes_exactly(tmp_path):
    """Iteration 2's update redone from iteration 1's checkpoint (as after a kill) gives the
    same model and the same trials."""
    spec_file = tmp_path / "spec.yaml"
    spec_file.write_text("fit: {eval_every: 5, patience: 2}\n")
    out = tmp_path / "run"
    args = ["online", "--spec", str(spec_file), "--shapes", "near-rest", "--steps", "15",
            "--trials", "2", "--iters", "2", "--initial-episodes", "2", "--hidden", "16",
            "--schedule", "steps", "--update-steps", "20", "--horizon", "2", "--seed", "3",
            "--device", "cpu", "--out", str(out), "--json"]  # fmt: skip
    res = runner.invoke(app, args)
    assert res.exit_code == 0, res.output
    summary = json.loads(res.stdout.strip().splitlines()[-1])
    assert summary["iterations_done"] == 2 and summary["train_seconds"] > 0
    saved = json.loads((out / "spec.json").read_text())["fit"]
    assert (saved["schedule"], saved["update_steps"], saved["eval_every"]) == ("steps", 20, 5)
    reference = read_checkpoint(out / "checkpoints" / "iter_02.pt")
    assert 0 < reference["steps"] <= 20
    metrics = (out / "metrics.csv").read_text()

    (out / "checkpoints" / "iter_02.pt").unlink()  # killed during iteration 2's update
    (out / "checkpoints" / "final.pt").unlink()
    for trial in (out / "data" / "iter_02").glob("*.h5"):
        trial.unlink()
    res = runner.invoke(app, ["online", "--resume", str(out), "--json"])
    assert res.exit_code == 0, res.output
    again = read_checkpoint(out / "checkpoints" / "iter_02.pt")
    assert again["steps"] == reference["steps"]
    for name, tensor in reference["state_dict"].items():
        assert torch.equal(tensor, again["state_dict"][name]), name

    def results(text: str) -> list[list[str]]:  # the timing columns aside
        rows = [line.split(",") for line in text.splitlines()]
        keep = [i for i, name in enumerate(rows[0]) if not name.endswith("seconds")]
        return [[row[i] for i in keep] for row in rows]

    assert results((out / "metrics.csv").read_text()) == results(metrics)


@pytest.mark.parametrize("schedule", ["epochs", "steps"])
def test_offline_model_trains_as_long_as_the_online_one(data, schedule):
    """Fig. 7's offline model after k updates: E·k epochs, or update_steps·k steps (the
    steps schedule keeps the offline comparison's cost bounded too)."""
    fit = UpdateSpec(**{**STEPS, "schedule": schedule}, epochs=2, update_steps=6, eval_every=3,
                     patience=0)  # fmt: skip
    result = train_like_online(fresh(data), data, fit, updates=3)
    if schedule == "steps":
        assert result.steps == 18 and [r.count for r in result.history][-1] == 18
    else:
        assert [r.count for r in result.history] == [1, 2, 3, 4, 5, 6]


def test_fit_is_the_one_entry_point_of_both_rod_schedules(data):
    """dlocli.fit picks the schedule from the spec: the same weights as the schedule's own
    (private) function (the marker schedule runs in tests/test_real_cables.py through `dlo
    train`)."""
    from dlocli.models.rod_training import _train_model
    from dlocli.models.step_schedule import _train_steps

    steps = UpdateSpec(**{**STEPS, "update_steps": 12, "eval_every": 6})
    epochs = steps.model_copy(update={"schedule": "epochs", "epochs": 1})
    recent = {"recent_episodes": np.array([5])}  # weighed in by the steps schedule only
    for spec, own, own_options in ((steps, _train_steps, recent), (epochs, _train_model, {})):
        by_fit, by_own = fresh(data), fresh(data)
        result = fit_model(by_fit, data, spec, **recent)
        own(by_own, data, spec, **own_options)
        assert result.history[-1].unit == ("step" if spec.schedule == "steps" else "epoch")
        assert all(map(torch.equal, weights(by_fit), weights(by_own))), spec.schedule
