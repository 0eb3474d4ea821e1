"""`dlo online --executor ray` on a local Ray cluster of 2 CPUs: the same trials as the local
executor bit for bit; a cluster lost midway keeps the finished trials and says how to go on;
the resumed run ends as the uninterrupted one; an address that does not answer is one line."""

from __future__ import annotations

import json
import os
import sys
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from dlocli.cli import app
from dlocli.data import load_dataset

ray = pytest.importorskip("ray")
runner = CliRunner()
TINY = ["--iters", "2", "--trials", "2", "--steps", "15", "--epochs", "1",
        "--initial-episodes", "2", "--hidden", "16", "--seed", "3"]  # fmt: skip
TRIALS = [(k, j) for k in (1, 2) for j in (1, 2)]


@pytest.fixture(scope="module")
def cluster():
    """One local Ray instance for the module (starting one takes seconds)."""
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
    try:
        yield ray.get_runtime_context().gcs_address
    finally:
        ray.shutdown()


@pytest.fixture(scope="module")
def local_run(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("local") / "run"
    online("--executor", "local", "--out", str(out))
    return out


def online(*args: str, code: int = 0) -> str:
    res = runner.invoke(app, ["online", *TINY, *args, "--json"])
    assert res.exit_code == code, res.output
    return res.output


def assert_same_trials(run: Path, reference: Path, trials=TRIALS) -> None:
    """Every array of every trial file equal bit for bit, and the same references."""
    for k, j in trials:
        name = f"iter_{k:02d}/trial_{j:03d}.h5"
        got, want = load_dataset(run / "data" / name), load_dataset(reference / "data" / name)
        for field in ("positions", "quaternions", "actions", "rewards"):
            assert np.array_equal(getattr(got, field), getattr(want, field)), (name, field)
    if trials == TRIALS:
        summary, expected = (json.loads((r / "summary.json").read_text()) for r in (run, reference))
        assert summary["curve"] == expected["curve"]
        for name in ("zero_final_error_mm", "random_final_error_mm", "transitions"):
            assert summary[name] == expected[name], name


def test_ray_trials_equal_the_local_executors(cluster, local_run, tmp_path):
    out = tmp_path / "ray"
    online("--executor", "ray", "--workers", "2", "--out", str(out))
    assert_same_trials(out, local_run)
    assert json.loads((out / "spec.json").read_text())["executor"] == "ray"


def _lose_the_cluster_in_iteration_2(spec_json: str, model: object, k: int, j: int) -> object:
    """A trial that takes its Ray worker down in iteration 2 (as a node that dies would)."""
    from dlocli.runs import online as module

    if k == 2:
        os._exit(1)
    return module._run_trial(spec_json, model, k, j)


def test_a_cluster_lost_midway_keeps_finished_trials_and_resume_ends_the_same(
    cluster, local_run, tmp_path, monkeypatch
):
    from ray import cloudpickle

    from dlocli.runs import online as module

    cloudpickle.register_pickle_by_value(sys.modules[__name__])  # the workers lack tests/
    monkeypatch.setattr(module, "_run_trial", _lose_the_cluster_in_iteration_2)
    out = tmp_path / "run"
    output = online("--executor", "ray", "--workers", "2", "--out", str(out), code=1)
    # Ray's own "(raylet) A worker died" notice may come too: ours is the one error line
    errors = [line for line in output.splitlines() if line.startswith("error:")]
    assert len(errors) == 1, output
    line = errors[0]
    assert line.startswith("error: the local Ray instance stopped answering"), line
    assert f"--resume {out}" in line
    assert "ray start" in line and "--executor local" in line
    assert_same_trials(out, local_run, [(1, 1), (1, 2)])  # iteration 1's trials kept
    assert not (out / "data" / "iter_02").is_dir() or not any((out / "data" / "iter_02").iterdir())

    monkeypatch.undo()
    res = runner.invoke(app, ["online", "--resume", str(out), "--executor", "ray", "--json"])
    assert res.exit_code == 0, res.output
    assert_same_trials(out, local_run)


@pytest.mark.parametrize("address", ["127.0.0.1:1", "ray://127.0.0.1:1"])
def test_an_address_that_does_not_answer_is_one_line_and_nothing_written(address, tmp_path):
    out = tmp_path / "run"
    res = runner.invoke(app, ["online", *TINY, "--executor", "ray", "--ray-address", address,
                              "--out", str(out)])  # fmt: skip
    assert res.exit_code == 2, res.output
    line = res.output.strip()
    assert line.count("\n") == 0 and address in line and "ray start --head" in line
    assert not out.exists()
