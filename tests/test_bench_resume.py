"""A bench job stopped between evaluation points continues from its last one, exactly: the
real MuJoCo env, SB3, PILCO and the online loop, at tiny sizes (20-step episodes)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest

from dlocli.bench import jobs
from dlocli.bench.spec import BenchSpec
from dlocli.tensorboard import available

from tiny import TINY_AGENTS, TINY_BENCH

#: three evaluation points of one episode each
SPEC: dict[str, Any] = {k: v for k, v in TINY_BENCH.items() if k != "workers"}
TIMING = ("wall_seconds", "eval_seconds")


class Stop(Exception):
    """Stands for the job's process being killed."""


def _rows(result: dict[str, Any]) -> list[dict[str, Any]]:
    return [{k: v for k, v in row.items() if k not in TIMING} for row in result["rows"]]


def _stop_at_evaluation(monkeypatch: pytest.MonkeyPatch, stop_at: int) -> list[int]:
    """Make the ``stop_at``-th evaluation (1-based) raise Stop once; returns the call count."""
    calls, stopped = [0], []
    evaluate = jobs.evaluate

    def counted(*args: Any, **kwargs: Any) -> dict[str, float]:
        calls[0] += 1
        if calls[0] == stop_at and not stopped:
            stopped.append(True)
            raise Stop
        return evaluate(*args, **kwargs)

    monkeypatch.setattr(jobs, "evaluate", counted)
    return calls


@pytest.mark.parametrize("agent", ["sac", "td3", "pilco", "mpc-offline", "mpc"])
def test_a_stopped_job_continues_from_its_last_point_exactly(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, agent: str
):
    spec = BenchSpec.model_validate(SPEC).model_dump_json()
    whole = jobs.run_job(spec, agent, 0, str(tmp_path / "whole"))
    assert not (tmp_path / "whole" / jobs.RESUME_DIR).exists()  # a finished job keeps none
    if agent in ("sac", "td3") and available():  # one SB3 event file per job, not per point
        assert len(list((tmp_path / "whole" / "tensorboard").glob("*_0/events.*"))) == 1

    points = len({row["transitions"] for row in whole["rows"]})
    per_point = sum(1 for row in whole["rows"] if row["eval"] == 0)
    calls = _stop_at_evaluation(monkeypatch, stop_at=(points - 1) * per_point + 1)
    with pytest.raises(Stop):  # stopped while evaluating its last point
        jobs.run_job(spec, agent, 0, str(tmp_path / "stopped"))
    slots = list((tmp_path / "stopped" / jobs.RESUME_DIR).glob("point-*"))
    assert [slot.name for slot in slots] == [f"point-{points - 2}"]  # only the newest kept
    before = json.loads((slots[0] / "progress.json").read_text())["seconds"]

    calls[0] = 0
    resumed = jobs.run_job(spec, agent, 0, str(tmp_path / "stopped"))
    finals = len(whole["rows"]) - points * per_point  # the bimanual transfer, if any
    assert calls[0] == per_point + finals  # the earlier points were not learned or evaluated again
    assert _rows(resumed) == _rows(whole)
    continued_at = sorted({row["transitions"] for row in whole["rows"]})[-2]
    assert whole["resumed_at"] == [] and resumed["resumed_at"] == [continued_at]
    assert resumed["seconds"] > before > 0  # the job's time counts its earlier process
    if agent in ("sac", "td3") and available():  # one event file per process of the job
        assert len(list((tmp_path / "stopped" / "tensorboard").glob("*_0/events.*"))) == 2


def test_a_checkpoint_of_other_settings_is_not_used(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
):
    spec = BenchSpec.model_validate(SPEC)
    _stop_at_evaluation(monkeypatch, stop_at=3)  # after the first point's two evaluations
    with pytest.raises(Stop):
        jobs.run_job(spec.model_dump_json(), "sac", 0, str(tmp_path))
    progress = next((tmp_path / jobs.RESUME_DIR).glob("point-*/progress.json"))
    assert json.loads(progress.read_text())["index"] == 0

    monkeypatch.undo()
    other = spec.model_copy(update={"options": {"sac": {**TINY_AGENTS["sac"], "tau": 0.5}}})
    result = jobs.run_job(other.model_dump_json(), "sac", 0, str(tmp_path))
    fresh = jobs.run_job(other.model_dump_json(), "sac", 0, str(tmp_path / "fresh"))
    assert _rows(result) == _rows(fresh)


def test_bench_resume_says_which_jobs_continue(tmp_path: Path, monkeypatch: pytest.MonkeyPatch):
    from typer.testing import CliRunner

    from dlocli.bench.run import BenchRun, load_bench_spec
    from dlocli.cli import app

    spec_file, run = tmp_path / "spec.json", tmp_path / "run"
    spec_file.write_text(json.dumps({**SPEC, "agents": ["zero"]}))
    runner = CliRunner()
    assert runner.invoke(app, ["bench", "--spec", str(spec_file), "--out", str(run)]).exit_code == 0
    spec = load_bench_spec(run).model_copy(update={"agents": ["zero", "sac"]})
    (job,) = BenchRun(spec).jobs()
    _stop_at_evaluation(monkeypatch, stop_at=5)  # after two points, while evaluating the third
    with pytest.raises(Stop):
        jobs.run_job(spec.model_dump_json(), job.agent, job.seed, job.scratch)

    res = runner.invoke(app, ["bench", "--resume", str(run), "--agents", "zero,sac"])
    assert res.exit_code == 0, res.output
    assert "sac-s0 continues from its checkpoint at 40 transitions" in res.output
    assert "sac-s0: 60/60 transitions, fixed goal" in res.output  # a line per point
    assert json.loads((run / "jobs" / "sac-s0.json").read_text())["resumed_at"] == [40]


def test_a_damaged_checkpoint_starts_the_job_again(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
):
    spec = BenchSpec.model_validate(SPEC).model_dump_json()
    _stop_at_evaluation(monkeypatch, stop_at=5)
    with pytest.raises(Stop):
        jobs.run_job(spec, "sac", 0, str(tmp_path / "job"))
    for chunk in (tmp_path / "job" / jobs.RESUME_DIR).glob("shared/replay/*.npz"):
        chunk.unlink()  # the replay buffer's rows are lost

    monkeypatch.undo()
    again = jobs.run_job(spec, "sac", 0, str(tmp_path / "job"))
    assert "checkpoint does not load" in capsys.readouterr().err
    fresh = jobs.run_job(spec, "sac", 0, str(tmp_path / "fresh"))
    assert again["resumed_at"] == [] and _rows(again) == _rows(fresh)


def test_a_checkpoint_written_before_its_later_fields_existed_still_loads(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
):
    spec = BenchSpec.model_validate(SPEC).model_dump_json()
    _stop_at_evaluation(monkeypatch, stop_at=5)
    with pytest.raises(Stop):
        jobs.run_job(spec, "random", 0, str(tmp_path / "job"))
    (progress,) = (tmp_path / "job" / jobs.RESUME_DIR).glob("point-*/progress.json")
    saved = json.loads(progress.read_text())
    del saved["resumed_at"], saved["seconds"]  # as the first version wrote it
    progress.write_text(json.dumps(saved))

    monkeypatch.undo()
    resumed = jobs.run_job(spec, "random", 0, str(tmp_path / "job"))
    assert resumed["resumed_at"] == [40]
    assert _rows(resumed) == _rows(jobs.run_job(spec, "random", 0, str(tmp_path / "fresh")))
