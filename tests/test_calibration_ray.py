"""`dlo calibrate --executor ray` on a local Ray cluster of 2 CPUs: the same history (every
candidate and score) and the same fitted material as the local executor; a cluster lost
midway keeps the finished generations, says how to go on, and the resumed run ends as the
uninterrupted one, as does a run whose driver (and its own Ray instance) was killed; an
address that does not answer is one line and nothing written."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path

import pytest
from test_calibration import TRUE_E, _simulate, _spec_file, _write
from test_online_ray import killed_at_exit

from dlocli.io import run_dir_entries, written_by_dlo

from tiny import run_dlo

pytest.importorskip("cma")
ray = pytest.importorskip("ray")
GENERATIONS = 2
#: the history file whose presence makes a replay take its Ray worker down (travels with the
#: function: the workers' environment is the cluster's)
LOSE_AFTER: list[str] = []


@pytest.fixture(scope="module")
def cable(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Two train recordings of a rod of stiffness TRUE_E, one eval recording."""
    folder = tmp_path_factory.mktemp("synthetic") / "CABLE"
    return _write(folder, {"train": [_simulate(TRUE_E, 0), _simulate(TRUE_E, 1)],
                           "eval": [_simulate(TRUE_E, 2)]})  # fmt: skip


@pytest.fixture(scope="module")
def spec(tmp_path_factory: pytest.TempPathFactory) -> Path:
    folder = tmp_path_factory.mktemp("spec")
    return _spec_file(folder, train_trajectories=2, population=4, generations=GENERATIONS)


@pytest.fixture(scope="module")
def local_run(cable: Path, spec: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("local") / "run"
    assert calibrate(spec, cable, "--executor", "local", "--out", str(out)) == 0
    return out


def calibrate(spec: Path, cable: Path, *argv: str) -> int:
    return run_dlo(["calibrate", "--spec", str(spec), "--source", str(cable), *argv, "--json"])


def assert_same_fit(run: Path, reference: Path) -> None:
    """Every generation's candidates and scores, the fitted material and the eval scores
    equal bit for bit."""
    got, want = (json.loads((r / "history.json").read_text()) for r in (run, reference))
    assert len(got["generations"]) == GENERATIONS
    assert got["generations"] == want["generations"]
    got, want = (json.loads((r / "report.json").read_text()) for r in (run, reference))
    for name in ("parameters", "train_best_cm", "eval_default_cm", "eval_calibrated_cm"):
        assert got[name] == want[name], name
    assert (run / "calibrated.yaml").read_text() == (reference / "calibrated.yaml").read_text()


def test_ray_calibration_equals_the_local_executors(cluster, cable, spec, local_run, tmp_path):
    out = tmp_path / "ray"
    assert calibrate(spec, cable, "--executor", "ray", "--workers", "2", "--out", str(out)) == 0
    assert_same_fit(out, local_run)
    assert json.loads((out / "spec.json").read_text())["executor"] == "ray"
    # the search moved: the check compares fits, not two copies of the start
    first, last = json.loads((out / "history.json").read_text())["generations"][:: GENERATIONS - 1]
    assert first["candidates"] != last["candidates"]


def _lose_the_cluster_in_generation_2(rod: dict, *args: object) -> object:
    """A replay that takes its Ray worker down once generation 1 is written (as a node that
    dies would)."""
    from dlocli.calibration.fit import replay_named

    if Path(LOSE_AFTER[0]).is_file():
        os._exit(1)
    return replay_named(rod, *args)


def test_a_cluster_lost_midway_keeps_finished_generations_and_resume_ends_the_same(
    cluster, cable, spec, local_run, tmp_path, monkeypatch, capsys
):
    from ray import cloudpickle

    from dlocli.calibration import fit

    cloudpickle.register_pickle_by_value(sys.modules[__name__])  # the workers lack tests/
    out = tmp_path / "run"
    monkeypatch.setattr(sys.modules[__name__], "LOSE_AFTER", [str(out / "history.json")])
    monkeypatch.setattr(fit, "replay_named", _lose_the_cluster_in_generation_2)
    assert calibrate(spec, cable, "--executor", "ray", "--out", str(out)) == 1
    errors = [line for line in capsys.readouterr().err.splitlines() if line.startswith("error:")]
    assert len(errors) == 1, errors
    assert errors[0].startswith("error: the local Ray instance stopped answering"), errors[0]
    assert f"--resume {out}" in errors[0] and "--executor local" in errors[0]
    done = json.loads((out / "history.json").read_text())["generations"]
    want = json.loads((local_run / "history.json").read_text())["generations"]
    assert done == want[:1] and not (out / "report.json").exists()

    monkeypatch.undo()
    assert run_dlo(["calibrate", "--resume", str(out), "--executor", "ray", "--json"]) == 0
    assert_same_fit(out, local_run)


@pytest.mark.slow
def test_a_killed_ray_driver_resumes_to_the_uninterrupted_fit(cluster, cable, tmp_path):
    """`dlo calibrate --executor ray` in its own session, with its own local Ray instance,
    killed (SIGKILL, the whole process group) once a generation is written; --resume (on
    the module's cluster) ends with the uninterrupted local run's fit."""
    generations = 4  # room to kill it before the last one
    spec = _spec_file(tmp_path, train_trajectories=2, population=4, generations=generations)
    reference, out, log = tmp_path / "local", tmp_path / "run", tmp_path / "driver.log"
    assert calibrate(spec, cable, "--out", str(reference)) == 0
    env = {k: v for k, v in os.environ.items() if k != "RAY_ADDRESS"}  # not the module's Ray
    env["PYTHONPATH"] = str(Path(__file__).parents[1])
    command = [sys.executable, "-m", "dlocli", "calibrate", "--spec", str(spec), "--source",
               str(cable), "--executor", "ray", "--out", str(out), "--json"]  # fmt: skip
    with log.open("w") as sink:
        driver = subprocess.Popen(command, env=env, stdout=sink, stderr=subprocess.STDOUT,
                                  start_new_session=True)  # fmt: skip
    with killed_at_exit(driver) as started:
        end = time.monotonic() + 300
        while not (out / "history.json").is_file():
            assert driver.poll() is None, f"the driver ended first:\n{log.read_text()}"
            assert time.monotonic() < end, log.read_text()
            time.sleep(0.05)
    assert len(started) > 1  # the driver and its Ray instance were killed, not the driver alone
    done = json.loads((out / "history.json").read_text())["generations"]
    assert 1 <= len(done) < generations and not (out / "report.json").exists()

    assert run_dlo(["calibrate", "--resume", str(out), "--executor", "ray", "--json"]) == 0
    got, want = (json.loads((r / "history.json").read_text()) for r in (out, reference))
    assert got["generations"] == want["generations"]
    assert (out / "calibrated.yaml").read_text() == (reference / "calibrated.yaml").read_text()
    assert run_dir_entries(out) <= written_by_dlo(out)


def test_an_address_that_does_not_answer_is_one_line_and_nothing_written(
    cable, spec, tmp_path, capsys
):
    out = tmp_path / "run"
    address = "127.0.0.1:1"
    code = calibrate(spec, cable, "--executor", "ray", "--ray-address", address, "--out", str(out))
    assert code == 2
    line = capsys.readouterr().err.strip()
    assert line.count("\n") == 0 and address in line and "ray start --head" in line, line
    assert not out.exists()
