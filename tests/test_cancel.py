"""A cancel token handed to a long run stops it where it is safe, its finished work saved, and
the run reports through the one callback shape as it goes: `dlo eval`, `dlo track` and
`dlo bench`, each a small real run whose progress callback cancels after the first unit."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from test_track_command import recorded  # noqa: F401  (the recorded clouds, a fixture)

from dlocli.bench.run import resume_bench, start_bench
from dlocli.bench.spec import BenchSpec
from dlocli.cancel import CancelToken
from dlocli.data import MarkerDataset, load_dataset
from dlocli.events import Began, Event
from dlocli.models.spec import EvalSpec, TrainSpec
from dlocli.runs.evaluate import run_evaluation
from dlocli.runs.track import run_track
from dlocli.runs.train import run_training
from dlocli.tracking.spec import TrackSpec

from tiny import TINY_BENCH


class CancelAfter:
    """A progress callback that keeps every event and cancels ``token`` once ``n`` units
    of ``unit`` are done."""

    def __init__(self, unit: str, n: int = 1) -> None:
        self.unit, self.n = unit, n
        self.token = CancelToken()
        self.events: list[Event] = []

    def __call__(self, event: Event) -> None:
        self.events.append(event)
        if event.unit == self.unit and not isinstance(event, Began) and event.done >= self.n:
            self.token.cancel()

    def done(self) -> list[float]:
        return [e.done for e in self.events if e.unit == self.unit]


@pytest.fixture(scope="module")
def rod_model(small_dataset_dir: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("rod_model")
    spec = TrainSpec(data=small_dataset_dir, model={"hidden": 8}, epochs=1, batch_size=64,
                     device="cpu", out=out)  # fmt: skip
    run_training(spec, overwrite=True)
    return out


def test_eval_on_rod_data_stops_between_measurements(rod_model, small_dataset_dir, tmp_path):
    spec = EvalSpec(checkpoint=rod_model, data=small_dataset_dir, device="cpu", max_starts=16)
    whole = run_evaluation(spec)
    watch = CancelAfter("measurement")
    out = tmp_path / "eval"
    stopped = spec.model_copy(update={"out": out})
    with pytest.raises(KeyboardInterrupt):
        run_evaluation(stopped, progress=watch, cancel=watch.token)
    assert watch.done() == [0, 1] and isinstance(watch.events[0], Began)
    assert watch.events[0].total == 3 and watch.events[1].values["name"] == "one step"
    saved = json.loads((out / "summary.json").read_text())
    assert saved["stopped"] == "KeyboardInterrupt" and "rollout5_mm" not in saved
    assert saved["one_step_mm"] == whole["one_step_mm"]  # the same numbers as a whole run
    assert (out / "spec.json").is_file()


def test_eval_on_markers_reports_each_predictor_and_stops(marker_run, tmp_path):
    data, model = marker_run
    spec = EvalSpec(checkpoint=model, data=data, device="cpu")
    events: list[Event] = []
    whole = run_evaluation(spec, progress=events.append)
    names = [e.values["name"] for e in events if not isinstance(e, Began)]
    assert names == ["model", "freeze", "straight_line", "timing"]
    assert [e.done for e in events] == [0, 1, 2, 3, 4] and events[0].total == 4
    watch = CancelAfter("measurement", 2)
    out = tmp_path / "eval"
    with pytest.raises(KeyboardInterrupt):
        run_evaluation(spec.model_copy(update={"out": out}), progress=watch, cancel=watch.token)
    saved = json.loads((out / "summary.json").read_text())
    assert saved["model_score_cm"] == whole["model_score_cm"]
    assert saved["freeze_score_cm"] == whole["freeze_score_cm"]
    assert "straight_line_score_cm" not in saved and saved["stopped"] == "KeyboardInterrupt"


def test_track_stops_between_frames_and_keeps_the_tracked_episodes(recorded, tmp_path):  # noqa: F811
    source, _ = recorded
    spec = TrackSpec(source=source, out=tmp_path / "tracked")
    watch = CancelAfter("episode")
    with pytest.raises(KeyboardInterrupt):
        run_track(spec, progress=watch, cancel=watch.token)
    assert watch.done() == [0, 1] and watch.events[0].total == 3
    assert watch.events[1].values["split"] == "train" and watch.events[1].values["visible"] > 0
    summary = json.loads((tmp_path / "tracked" / "summary.json").read_text())
    assert summary["stopped"] == "KeyboardInterrupt"
    assert summary["train_episodes"] == 1 and summary["eval_episodes"] == 0
    data = load_dataset(tmp_path / "tracked")
    assert isinstance(data, MarkerDataset) and data.episode_names("train") == ["seed0"]


def test_bench_stops_between_jobs_and_resume_runs_the_rest(tmp_path):
    spec = BenchSpec.model_validate({**TINY_BENCH, "agents": ["zero", "random"],
                                     "out": tmp_path / "run"})  # fmt: skip
    watch = CancelAfter("job")
    with pytest.raises(KeyboardInterrupt):
        start_bench(spec, progress=watch, cancel=watch.token)
    assert watch.done() == [0, 1] and watch.events[0].total == 2
    assert [p.name for p in (tmp_path / "run" / "jobs").iterdir()] == ["zero-s0.json"]
    events: list[Event] = []
    summary = resume_bench(tmp_path / "run", {}, progress=events.append)
    assert [e.done for e in events] == [0, 1] and events[1].values["job"] == "random-s0"
    assert summary["jobs_done"] == 2


def test_a_bench_job_in_this_process_meets_the_token(tmp_path):
    spec = BenchSpec.model_validate({**TINY_BENCH, "agents": ["zero"], "out": tmp_path / "run"})
    token = CancelToken()
    token.cancel()  # before the job's env first steps
    with pytest.raises(KeyboardInterrupt):
        start_bench(spec, cancel=token)
    assert not list((tmp_path / "run" / "jobs").glob("*.json"))


def test_only_the_commands_reach_for_the_process_wide_token():
    """The library is handed its token; only the CLI (and processes.py, which owns it) reads
    the process's stop signals."""
    package = Path(__file__).resolve().parent.parent / "dlocli"
    readers = ("signal_token(", "raise_if_stopped(", "pending_stop(")
    found = [
        str(path.relative_to(package))
        for path in package.rglob("*.py")
        if path.parts[-2] != "cli" and path.name != "processes.py"
        and any(reader in path.read_text() for reader in readers)
    ]  # fmt: skip
    assert not found, f"{found} read the process's stop signals: take a cancel token instead"
