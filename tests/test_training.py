"""Training, evaluation and the `dlo train` / `dlo eval` commands, on real simulator data."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch
from typer.testing import CliRunner

from dlocli.data import load_dataset
from dlocli.models.base import build_model
from dlocli.models.checkpoints import load_model, read_checkpoint
from dlocli.models.evaluation import evaluate_model
from dlocli.models.fit import fit as fit_model
from dlocli.models.fitting import Validated
from dlocli.models.rod_training import transition_tensors, validation_loss
from dlocli.models.spec import FitSpec
from dlocli.models.splits import split_episodes
from dlocli.registry import models

TINY = {"hidden": 24}
FAST_FIT = {"lr": 3e-3, "batch_size": 16, "val_fraction": 0.2, "device": "cpu"}
EVAL_KEYS = {
    "one_step_mm", "rollout5_mm", "rollout50_mm",
    "persistence_one_step_mm", "persistence_rollout5_mm", "persistence_rollout50_mm",
}  # fmt: skip

runner = CliRunner()


def cli(*args: str):
    from dlocli.cli import app

    return runner.invoke(app, list(args))


def fresh(name: str, data, seed: int = 0):
    torch.manual_seed(seed)
    return build_model({"name": name, **TINY}, data.n_segments)


def test_split_is_by_trajectory_and_stable_as_data_grows():
    train, val = split_episodes(10, 0.2)
    assert len(val) >= 1 and set(train).isdisjoint(val) and len(train) + len(val) == 10
    bigger_train, bigger_val = split_episodes(40, 0.2)
    assert set(val) <= set(bigger_val) and set(train) <= set(bigger_train)
    assert 4 <= len(bigger_val) <= 12


@pytest.mark.parametrize("name", models.names())
def test_training_reduces_validation_loss(small_dataset_dir, name):
    data = load_dataset(small_dataset_dir)
    model = fresh(name, data)
    fit = FitSpec(epochs=4, **FAST_FIT)
    _, val_eps = split_episodes(data.n_episodes, fit.val_fraction)
    train_eps = np.setdiff1d(np.arange(data.n_episodes), val_eps)
    model.fit_normalization(data.transitions(train_eps))
    val = transition_tensors(data, val_eps, torch.device("cpu"))
    before = validation_loss(model, val)
    result = fit_model(model, data, fit)
    assert [(r.unit, r.count) for r in result.history] == [("epoch", n) for n in (1, 2, 3, 4)]
    assert result.val_loss < 0.85 * before, (before, result.history)
    assert result.history[-1].train_loss < result.history[0].train_loss
    assert result.optimizer_state["state"], "Adam moments to continue from"


def test_training_is_reproducible_and_continues(small_dataset_dir):
    data = load_dataset(small_dataset_dir)
    fit = FitSpec(epochs=1, **{**FAST_FIT, "batch_size": 64})
    a, b = fresh("in-bilstm", data), fresh("in-bilstm", data)
    first = fit_model(a, data, fit)
    fit_model(b, data, fit)
    for pa, pb in zip(a.parameters(), b.parameters(), strict=True):
        assert torch.equal(pa, pb), "same seed on CPU, same weights"
    std = a.delta_std.clone()
    more = fit_model(a, data, fit, optimizer_state=first.optimizer_state)
    assert torch.equal(a.delta_std, std), "continued training keeps the normalisation"
    assert more.optimizer_state["state"][0]["step"] == 2 * first.optimizer_state["state"][0]["step"]


@pytest.mark.parametrize("name", models.names())
def test_evaluation_keys(small_dataset_dir, name):
    data = load_dataset(small_dataset_dir)
    model = fresh(name, data)
    model.fit_normalization(data.transitions())
    metrics = evaluate_model(model, data, np.array([0, 1]), max_starts=16)
    assert EVAL_KEYS <= metrics.keys()
    assert all(metrics[k] is not None and metrics[k] >= 0 for k in EVAL_KEYS)
    assert metrics["persistence_rollout50_mm"] > metrics["persistence_rollout5_mm"] > 0
    # every transition but each episode's first (whose previous state is not recorded)
    assert metrics["eval_transitions"] == int(data.episode_lengths[:2].sum()) - 2


def test_a_trained_model_beats_persistence(small_dataset_dir):
    """On the data it learned from (300 transitions are too few to generalise reliably)."""
    data = load_dataset(small_dataset_dir)
    model = fresh("mlp", data)
    result = fit_model(model, data, FitSpec(epochs=8, **FAST_FIT))
    metrics = evaluate_model(model, data, result.train_episodes)
    assert metrics["one_step_mm"] < metrics["persistence_one_step_mm"]
    assert metrics["rollout5_mm"] < metrics["persistence_rollout5_mm"]


def test_train_and_eval_commands(small_dataset_dir, tmp_path):
    run = tmp_path / "run"
    res = cli("train", "--data", str(small_dataset_dir), "--hidden", "16", "--epochs", "1",
              "--batch-size", "64", "--lr", "3e-3", "--device", "cpu", "--out", str(run),
              "--json")  # fmt: skip
    assert res.exit_code == 0, res.output
    summary = json.loads(res.stdout.strip().splitlines()[-1])
    assert EVAL_KEYS <= summary.keys() and summary["epochs"] == 1
    for name in ("spec.json", "metrics.csv", "summary.json", "checkpoints/final.pt",
                 "checkpoints/best.pt", "plots/rollout.png", "plots/loss.png"):  # fmt: skip
        assert (run / name).is_file(), name
    assert (run / "metrics.csv").read_text().splitlines()[0] == "epoch,train_loss,val_loss,seconds"
    assert json.loads((run / "spec.json").read_text())["model"]["hidden"] == 16
    assert "optimizer" in read_checkpoint(run)
    assert read_checkpoint(run)["control_dt"] == 0.02  # the collected data's control period
    assert load_model(run).spec.hidden == 16

    plot = tmp_path / "eval.png"
    res = cli("eval", "--checkpoint", str(run), "--data", str(small_dataset_dir), "--device", "cpu",
              "--plot", str(plot), "--json")  # fmt: skip
    assert res.exit_code == 0, res.output
    assert EVAL_KEYS <= json.loads(res.stdout.strip().splitlines()[-1]).keys()
    assert plot.stat().st_size > 1000

    more = tmp_path / "more"
    res = cli("train", "--data", str(small_dataset_dir), "--epochs", "1", "--init-from", str(run),
              "--device", "cpu", "--out", str(more), "--json")  # fmt: skip
    assert res.exit_code == 0, res.output
    assert json.loads((more / "spec.json").read_text())["model"]["hidden"] == 16, "adopted"
    res = cli("train", "--data", str(small_dataset_dir), "--hidden", "17", "--init-from",
              str(run), "--out", str(tmp_path / "mismatch"))  # fmt: skip
    assert res.exit_code == 2 and "requested" in res.output, res.output

    plain = tmp_path / "plain"
    res = cli("train", "--data", str(small_dataset_dir), "--hidden", "16", "--epochs", "1",
              "--no-velocity-input", "--device", "cpu", "--out", str(plain))  # fmt: skip
    assert res.exit_code == 0, res.output
    assert json.loads((plain / "spec.json").read_text())["model"]["velocity_input"] is False
    assert load_model(plain).spec.velocity_input is False


def test_bad_input_exits_2(small_dataset_dir, tmp_path):
    not_data = tmp_path / "notdata.h5"
    not_data.write_bytes(b"hello")
    corrupt = tmp_path / "corrupt.pt"
    corrupt.write_bytes(b"\x00" * 64)
    data = str(small_dataset_dir)
    out = str(tmp_path / "out")
    cases = [
        ("train", "--data", str(tmp_path / "missing"), "--out", out),
        ("train", "--data", str(not_data), "--out", out),
        ("train", "--data", data, "--device", "cuda:9", "--out", out),
        ("train", "--data", data, "--model", "lstm", "--out", out),
        ("train", "--data", data, "--epochs", "-1", "--out", out),
        ("train", "--data", data, "--init-from", str(corrupt), "--out", out),
        ("eval", "--checkpoint", str(corrupt), "--data", data),
        ("eval", "--checkpoint", str(tmp_path), "--data", data),
        ("eval", "--checkpoint", str(corrupt), "--data", str(not_data)),
    ]
    for args in cases:
        res = cli(*args)
        assert res.exit_code == 2, (args, res.output)
        assert "Traceback" not in res.output
        assert len(res.output.strip().splitlines()) <= 2, res.output


def test_stopped_training_resumes_to_the_same_model(small_dataset_dir, tmp_path):
    from dlocli.models.spec import TrainSpec
    from dlocli.runs.train import resumed_spec, run_training

    spec = TrainSpec(data=small_dataset_dir, model=TINY, epochs=3, **FAST_FIT)
    whole = run_training(spec.model_copy(update={"out": tmp_path / "whole"}))

    def stop_after_epoch_2(event):
        if event.done == 2 and isinstance(event, Validated):
            raise KeyboardInterrupt  # the user's Ctrl-C, after epoch 2 is done
        if event.values.get("epoch") == 3:
            pytest.fail("epoch 3 started before the stop")

    stopped = tmp_path / "stopped"
    with pytest.raises(KeyboardInterrupt):
        run_training(spec.model_copy(update={"out": stopped}), progress=stop_after_epoch_2)
    assert read_checkpoint(stopped / "checkpoints" / "last.pt")["epoch"] == 1, "epoch 2 unsaved"
    resumed = run_training(resumed_spec(stopped, {"epochs": 3}), resume=True)

    final = {k: read_checkpoint(p / "checkpoints" / "final.pt")["state_dict"]
             for k, p in (("whole", tmp_path / "whole"), ("resumed", stopped))}  # fmt: skip
    assert all(torch.equal(v, final["resumed"][k]) for k, v in final["whole"].items())
    assert resumed["val_loss"] == whole["val_loss"]
    assert len((stopped / "metrics.csv").read_text().splitlines()) == 1 + 3

    res = cli("train", "--resume", str(stopped), "--epochs", "5")
    assert res.exit_code == 2 and "conflicts" in res.output, res.output
    res = cli("train", "--resume", str(tmp_path))
    assert res.exit_code == 2 and "not a training run" in res.output, res.output


def test_hidden_is_the_width_of_every_model(small_dataset_dir, tmp_path):
    """`dlo train --model mlp --hidden 16` builds a smaller model than `--hidden 150`; so
    does every registered model."""
    parameters = {}
    for hidden in (16, 150):
        out = tmp_path / f"mlp-{hidden}"
        res = cli("train", "--data", str(small_dataset_dir), "--model", "mlp", "--hidden",
                  str(hidden), "--epochs", "1", "--batch-size", "64", "--device", "cpu",
                  "--out", str(out), "--json")  # fmt: skip
        assert res.exit_code == 0, res.output
        parameters[hidden] = json.loads(res.stdout.strip().splitlines()[-1])["parameters"]
        assert load_model(out).spec.hidden == hidden
    assert parameters[16] < parameters[150]
    for name in models.names():  # widths every model takes (attention: a multiple of its heads)
        count = [sum(p.numel() for p in build_model({"name": name, "hidden": h}, 20).parameters())
                 for h in (16, 160)]  # fmt: skip
        assert count[0] < count[1], name


def test_a_cancelled_token_stops_the_fit_before_its_next_step(small_dataset_dir):
    """Cancellation reaches the library as the token it is given: cancelled after the first
    epoch's validation, the fit stops before the second epoch's first gradient step."""
    from dlocli.cancel import CancelToken
    from dlocli.models.fitting import BatchDone

    data = load_dataset(small_dataset_dir)
    token, seen = CancelToken(), []

    def progress(event):
        seen.append(event)
        if isinstance(event, Validated):
            token.cancel()

    with pytest.raises(KeyboardInterrupt):
        fit_model(fresh("mlp", data), data, FitSpec(epochs=3, **FAST_FIT), progress=progress,
                  cancel=token)  # fmt: skip
    assert not any(isinstance(e, BatchDone) and e.values["epoch"] > 1 for e in seen)
    assert token.reason is None, "the stop is raised once"
    fit_model(fresh("mlp", data), data, FitSpec(epochs=1, **FAST_FIT), cancel=token)
