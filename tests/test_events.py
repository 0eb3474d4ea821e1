"""Every long-running run reports through one callback type: a real tiny run of each gives
:class:`dlocli.events.Event` only, each unit counted up from its phase's Began to its total.
(Calibration's run: tests/test_calibration.py, where its recorded cable is built.)"""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from dlocli.bench.run import start_bench
from dlocli.bench.spec import BenchSpec
from dlocli.events import Began, Event
from dlocli.models.fitting import BatchDone, Validated
from dlocli.models.spec import TrainSpec
from dlocli.runs.collect import collect_random
from dlocli.runs.control import ControlSpec, run_control
from dlocli.runs.online import OnlineSpec, start_online
from dlocli.runs.train import run_training
from dlocli.specs import CollectSpec, TaskSpec

from tiny import TINY_BENCH


def counted(events: list, unit: str) -> list[list[float]]:
    """The ``done`` of ``unit`` per phase (a Began starts one, its own ``done`` first); each
    phase counts up (never down) within its total. Every event is an Event."""
    assert events and all(isinstance(e, Event) for e in events), events[:3]
    phases: list[list[float]] = []
    for event in (e for e in events if e.unit == unit):
        if isinstance(event, Began) or not phases:
            phases.append([])
        phases[-1].append(event.done)
        assert event.total is None or event.done <= event.total, event
    for phase in phases:
        assert phase == sorted(phase) and phase[-1] > phase[0], (unit, phase)
    return phases


def test_collect_reports_each_episode(tmp_path: Path):
    events: list = []
    spec = CollectSpec(episodes=3, steps=3, seed=1, out=tmp_path / "run",
                       task={"reset_settle_steps": 10})  # fmt: skip
    collect_random(spec, progress=events.append)
    assert counted(events, "episode") == [[0, 1, 2, 3]]
    assert isinstance(events[0], Began)


def test_train_reports_its_epochs_and_batches(small_dataset_dir: Path, tmp_path: Path):
    events: list = []
    spec = TrainSpec(data=small_dataset_dir, model={"hidden": 16}, epochs=2, lr=3e-3,
                     batch_size=64, device="cpu", out=tmp_path / "run")  # fmt: skip
    run_training(spec, progress=events.append)
    assert counted(events, "epoch") == [[0, 1, 2]]
    assert all(isinstance(e, Validated) for e in events[1:] if e.unit == "epoch")
    batches = [e for e in events if e.unit == "batch"]
    assert all(isinstance(e, BatchDone) and e.values["loss"] > 0 for e in batches)
    for epoch in (1, 2):  # each epoch counts its batches afresh, up to all of them
        done = [e.done for e in batches if e.values["epoch"] == epoch]
        assert done[0] == 1 and done == sorted(set(done)) and done[-1] == batches[0].total


def test_control_reports_each_step(near_rest_goal: Path, tmp_path: Path):
    events: list = []
    task = TaskSpec(goal_file=near_rest_goal, shapes="near-rest", episode_steps=6)
    spec = ControlSpec(task=task, controller="random", out=tmp_path / "run", seed=1)
    summary = run_control(spec, events.append)
    assert counted(events, "step") == [[0, 1, 2, 3, 4, 5, 6]]
    last = events[-1].values
    assert last["shape_error_mm"] == pytest.approx(summary["final_error_mm"], abs=0.05)


def test_online_reports_iterations_updates_and_trials(tmp_path: Path):
    events: list = []
    spec = OnlineSpec.model_validate({
        "iters": 2, "trials": 2, "initial_episodes": 2, "seed": 3, "out": tmp_path / "run",
        "task": {"episode_steps": 10}, "model": {"hidden": 16},
        "fit": {"epochs": 2, "device": "cpu"},
    })  # fmt: skip
    start_online(spec, progress=events.append)
    assert counted(events, "random") == [[1, 2]]
    assert counted(events, "iteration") == [[0, 1, 1, 2]]  # k starts (k - 1 done), k is done
    assert counted(events, "epoch") == [[0, 1, 2], [0, 1, 2]]  # one update per iteration
    assert counted(events, "trial") == [[0, 1, 2], [0, 1, 2]]
    trials = [e for e in events if e.unit == "trial" and not isinstance(e, Began)]
    assert len(trials) == 4 and all(e.values["final_error_mm"] > 0 for e in trials)


def test_bench_reports_its_jobs(tmp_path: Path):
    events: list = []
    spec = BenchSpec.model_validate({**TINY_BENCH, "agents": ["zero", "random"],
                                     "out": tmp_path / "run"})  # fmt: skip
    summary = start_bench(spec, progress=events.append)
    assert counted(events, "job") == [[0, 1, 2]]
    assert events[0].values["total"] == 2 and summary["jobs_done"] == 2
    jobs = {e.values["job"] for e in events[1:]}
    assert jobs == {"zero-s0", "random-s0"}
    assert json.loads((tmp_path / "run" / "summary.json").read_text())
