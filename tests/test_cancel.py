"""A cancel token handed to a long run stops it where it is safe, its finished work saved, and
the run reports through the one callback shape as it goes: `dlo eval`, `dlo track`,
`dlo bench`, `dlo sample`, `dlo export` and `dlo import`, each a small real run whose progress
callback cancels after the first unit; a token cancelled before the run, or at its first
event, stops it before its first unit with nothing written (an earlier run's files left as they
were); each command hands its run the process's token and ends as on Ctrl-C (exit 130, one line)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from test_track_command import recorded  # noqa: F401  (the recorded clouds, a fixture)
from typer.testing import CliRunner

from dlocli.bench.run import resume_bench, start_bench
from dlocli.bench.spec import BenchSpec
from dlocli.cancel import CancelToken
from dlocli.data import MarkerDataset, load_dataset
from dlocli.events import Began, Event
from dlocli.models.spec import EvalSpec, TrainSpec
from dlocli.recorded_cables.importing import run_import
from dlocli.recorded_cables.spec import ImportSpec
from dlocli.runs.evaluate import run_evaluation
from dlocli.runs.sample import run_sample
from dlocli.runs.sample_spec import SampleSpec
from dlocli.runs.track import run_track
from dlocli.runs.train import run_training
from dlocli.tracking.spec import TrackSpec

from tiny import TINY_BENCH, write_cable

runner = CliRunner()


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


class CancelAtFirst:
    """A progress callback that keeps every event and cancels ``token`` at the first one; with
    ``already``, the token is cancelled before the run starts."""

    def __init__(self, already: bool) -> None:
        self.token = CancelToken()
        self.events: list[Event] = []
        if already:
            self.token.cancel()

    def __call__(self, event: Event) -> None:
        self.events.append(event)
        self.token.cancel()

    def only_began(self) -> bool:
        return len(self.events) <= 1 and all(isinstance(e, Began) for e in self.events)


def files_of(folder: Path) -> dict[str, bytes]:
    """Every file under ``folder`` (but a run's lock) and its bytes."""
    return {str(path.relative_to(folder)): path.read_bytes() for path in folder.rglob("*")
            if path.is_file() and not path.name.endswith(".lock")}  # fmt: skip


def dlo(*args: str):
    from dlocli.cli import app

    return runner.invoke(app, list(args))


def cli_with_cancelled_token(monkeypatch: pytest.MonkeyPatch, command: str, *args: str):
    """``dlo COMMAND ARGS`` whose process-wide token was cancelled before the run (a Ctrl-C
    at its start): the command must hand that token to its run."""
    token = CancelToken()
    token.cancel()
    monkeypatch.setattr(f"dlocli.cli.{command}.signal_token", lambda: token)
    return dlo(command, *args)


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


@pytest.mark.parametrize("already", [True, False], ids=["cancelled-before", "at-first-event"])
def test_eval_stopped_before_its_first_measurement_writes_nothing(
    rod_model, small_dataset_dir, tmp_path, already
):
    out = tmp_path / "eval"
    spec = EvalSpec(checkpoint=rod_model, data=small_dataset_dir, device="cpu", max_starts=16,
                    out=out)  # fmt: skip
    run_evaluation(spec)
    earlier = files_of(out)
    watch = CancelAtFirst(already)
    with pytest.raises(KeyboardInterrupt):
        run_evaluation(spec, overwrite=True, progress=watch, cancel=watch.token)
    assert watch.only_began() and watch.token.reason is None, "stopped once, at once"
    assert files_of(out) == earlier


def test_dlo_eval_hands_its_token_and_exits_as_on_ctrl_c(
    monkeypatch, rod_model, small_dataset_dir, tmp_path
):
    out = tmp_path / "eval"
    args = ["--checkpoint", str(rod_model), "--data", str(small_dataset_dir), "--device", "cpu",
            "--max-starts", "16", "--out", str(out)]  # fmt: skip
    assert dlo("eval", *args).exit_code == 0
    earlier = files_of(out)
    res = cli_with_cancelled_token(monkeypatch, "eval", *args, "--overwrite")
    assert res.exit_code == 130 and "interrupted" in res.output, res.output
    assert files_of(out) == earlier


@pytest.mark.parametrize("already", [True, False], ids=["cancelled-before", "at-first-event"])
def test_track_stopped_before_its_first_episode_writes_nothing(recorded, tmp_path, already):  # noqa: F811
    source, _ = recorded
    spec = TrackSpec(source=source, out=tmp_path / "tracked")
    run_track(spec)
    earlier = files_of(tmp_path / "tracked")
    watch = CancelAtFirst(already)
    with pytest.raises(KeyboardInterrupt):
        run_track(spec, overwrite=True, progress=watch, cancel=watch.token)
    assert watch.only_began() and watch.token.reason is None
    assert files_of(tmp_path / "tracked") == earlier


def test_dlo_track_hands_its_token_and_exits_as_on_ctrl_c(monkeypatch, recorded, tmp_path):  # noqa: F811
    source, _ = recorded
    out = tmp_path / "tracked"
    run_track(TrackSpec(source=source, out=out))
    earlier = files_of(out)
    res = cli_with_cancelled_token(monkeypatch, "track", "--source", str(source), "--out",
                                   str(out), "--overwrite")  # fmt: skip
    assert res.exit_code == 130 and "interrupted" in res.output, res.output
    assert files_of(out) == earlier


@pytest.mark.parametrize("already", [True, False], ids=["cancelled-before", "at-first-event"])
def test_bench_resumed_and_stopped_at_once_keeps_its_finished_jobs(tmp_path, already):
    out = tmp_path / "run"
    spec = BenchSpec.model_validate({**TINY_BENCH, "agents": ["zero", "random"], "out": out})
    watch = CancelAfter("job")
    with pytest.raises(KeyboardInterrupt):
        start_bench(spec, progress=watch, cancel=watch.token)
    jobs = files_of(out / "jobs")
    stop = CancelAtFirst(already)
    with pytest.raises(KeyboardInterrupt):
        resume_bench(out, {}, progress=stop, cancel=stop.token)
    assert stop.only_began() and stop.token.reason is None
    assert files_of(out / "jobs") == jobs and list(jobs) == ["zero-s0.json"]
    assert not (out / "summary.json").exists() and not (out / "results.csv").exists()


def test_dlo_bench_hands_its_token_and_exits_as_on_ctrl_c(monkeypatch, tmp_path):
    out = tmp_path / "run"
    spec = BenchSpec.model_validate({**TINY_BENCH, "agents": ["zero"], "out": out})
    res = cli_with_cancelled_token(monkeypatch, "bench", "--spec", str(write_spec(spec, tmp_path)))
    assert res.exit_code == 130 and "interrupted" in res.output, res.output
    assert not list((out / "jobs").glob("*.json")) and not (out / "summary.json").exists()


def write_spec(spec: BenchSpec, folder: Path) -> Path:
    path = folder / "bench.json"
    path.write_text(spec.model_dump_json())
    return path


@pytest.mark.parametrize(
    "where",
    [
        "dlocli.runs.collect:collect_random",
        "dlocli.runs.train:run_training",
        "dlocli.runs.evaluate:run_evaluation",
        "dlocli.runs.track:run_track",
        "dlocli.runs.calibrate:run_calibration",
        "dlocli.calibration.family:run_family",
        "dlocli.runs.adapt:run_adaptation",
        "dlocli.runs.control:run_control",
        "dlocli.runs.online.run:start_online",
        "dlocli.runs.online.run:resume_online",
        "dlocli.bench.run:start_bench",
        "dlocli.bench.run:resume_bench",
        "dlocli.runs.sample:run_sample",
        "dlocli.runs.export:export_minari",
        "dlocli.recorded_cables.importing:run_import",
        "dlocli.bridge.cell:serve",
        "dlocli.bridge.server:serve",
    ],
)
def test_every_long_command_takes_the_one_callback_and_a_token(where: str):
    import importlib
    import inspect

    module, name = where.split(":")
    parameters = inspect.signature(getattr(importlib.import_module(module), name)).parameters
    assert {"progress", "cancel"} <= set(parameters), f"{where} takes {list(parameters)}"


# ----------------------------------------------------------------------------- dlo sample
def sample_spec(out: Path) -> SampleSpec:
    return SampleSpec(train=2, eval=1, seconds=0.2, out=out)


def test_sample_stops_between_recordings_and_keeps_those_written(tmp_path):
    whole = run_sample(sample_spec(tmp_path / "whole"))
    watch = CancelAfter("recording")
    out = tmp_path / "stopped"
    with pytest.raises(KeyboardInterrupt):
        run_sample(sample_spec(out), progress=watch, cancel=watch.token)
    assert watch.done() == [0, 1] and watch.events[0].total == 3
    assert watch.events[1].values == {"split": "train", "file": "take_000.pkl"}
    kept = files_of(out)
    assert sorted(kept) == [".dlo-written.json", "spec.json", "summary.json", "train/take_000.pkl"]
    assert kept["train/take_000.pkl"] == (tmp_path / "whole/train/take_000.pkl").read_bytes()
    spec = json.loads((tmp_path / "whole/spec.json").read_text())
    assert json.loads(kept["spec.json"]) == {**spec, "out": str(out)}
    summary = json.loads(kept["summary.json"].decode().replace(str(out), str(tmp_path / "whole")))
    stopped = {"train_recordings": 1, "eval_recordings": 0, "stopped": "KeyboardInterrupt"}
    assert summary == {**whole, **stopped}  # the same command reads the folder


@pytest.mark.parametrize("already", [True, False], ids=["cancelled-before", "at-first-event"])
def test_sample_stopped_before_its_first_recording_writes_nothing(tmp_path, already):
    out = tmp_path / "cable"
    run_sample(sample_spec(out))
    earlier = files_of(out)
    watch = CancelAtFirst(already)
    with pytest.raises(KeyboardInterrupt):
        run_sample(sample_spec(out), overwrite=True, progress=watch, cancel=watch.token)
    assert watch.only_began() and watch.token.reason is None
    assert files_of(out) == earlier


def test_dlo_sample_hands_its_token_and_exits_as_on_ctrl_c(monkeypatch, tmp_path):
    out = tmp_path / "cable"
    run_sample(sample_spec(out))
    earlier = files_of(out)
    flags = ["--train", "2", "--eval", "1", "--seconds", "0.2", "--out", str(out)]
    res = cli_with_cancelled_token(monkeypatch, "sample", *flags, "--overwrite")
    assert res.exit_code == 130 and "interrupted" in res.output, res.output
    assert files_of(out) == earlier


# ----------------------------------------------------------------------------- dlo export
@pytest.fixture(scope="module")
def collected(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """3 random episodes of 5 steps (seed 0)."""
    from dlocli.runs.collect import collect_random
    from dlocli.specs import CollectSpec

    out = tmp_path_factory.mktemp("collect")
    spec = CollectSpec(episodes=3, seed=0, out=out,
                       task={"episode_steps": 5, "shapes": "near-rest"})  # fmt: skip
    collect_random(spec, overwrite=True)
    return out


def test_export_reports_each_episode_and_a_stop_leaves_the_dataset_as_it_was(collected, tmp_path):
    pytest.importorskip("minari")
    from dlocli.runs.export import export_minari

    root = tmp_path / "minari"
    events: list[Event] = []
    export_minari(collected, root=root, progress=events.append)
    assert [e.done for e in events] == [0, 1, 2, 3] and events[0].total == 3
    assert events[1].values == {"steps": 5, "exported": True}
    earlier = files_of(root)
    watch = CancelAfter("episode", 2)
    with pytest.raises(KeyboardInterrupt):
        export_minari(collected, root=root, overwrite=True, progress=watch, cancel=watch.token)
    assert watch.done() == [0, 1, 2]
    assert files_of(root) == earlier and not list(root.glob(".dlo-export-*"))


@pytest.mark.parametrize("already", [True, False], ids=["cancelled-before", "at-first-event"])
def test_export_stopped_before_its_first_episode_writes_nothing(collected, tmp_path, already):
    pytest.importorskip("minari")
    from dlocli.runs.export import export_minari

    root = tmp_path / "minari"
    export_minari(collected, root=root)
    earlier = files_of(root)
    watch = CancelAtFirst(already)
    with pytest.raises(KeyboardInterrupt):
        export_minari(collected, root=root, overwrite=True, progress=watch, cancel=watch.token)
    assert watch.only_began() and watch.token.reason is None
    assert files_of(root) == earlier and not list(root.glob(".dlo-export-*"))


def test_dlo_export_hands_its_token_and_exits_as_on_ctrl_c(monkeypatch, collected, tmp_path):
    pytest.importorskip("minari")
    root = tmp_path / "minari"
    assert dlo("export", str(collected), "--out", str(root), "--json").exit_code == 0
    earlier = files_of(root)
    res = cli_with_cancelled_token(monkeypatch, "export", str(collected), "--out", str(root),
                                   "--overwrite")  # fmt: skip
    assert res.exit_code == 130 and "interrupted" in res.output, res.output
    assert files_of(root) == earlier and not list(root.glob(".dlo-export-*"))


# ----------------------------------------------------------------------------- dlo import
def test_import_reports_each_file_and_a_stop_writes_nothing(tmp_path):
    source = write_cable(tmp_path / "cable", n_train=2, n_eval=1)
    spec = ImportSpec(source=source, out=tmp_path / "imported")
    events: list[Event] = []
    run_import(spec, progress=events.append)
    assert [e.done for e in events] == [0, 1, 2, 3] and events[0].total == 3
    assert events[3].values == {"split": "eval", "file": "0.pkl"}
    earlier = files_of(tmp_path / "imported")
    for n in (1, 3):  # between files, and after the last one before writing
        watch = CancelAfter("recording", n)
        with pytest.raises(KeyboardInterrupt):
            run_import(spec, overwrite=True, progress=watch, cancel=watch.token)
        assert watch.done()[-1] == n
        assert files_of(tmp_path / "imported") == earlier


@pytest.mark.parametrize("already", [True, False], ids=["cancelled-before", "at-first-event"])
def test_import_stopped_before_its_first_file_writes_nothing(tmp_path, already):
    source = write_cable(tmp_path / "cable", n_train=2, n_eval=1)
    spec = ImportSpec(source=source, out=tmp_path / "imported")
    run_import(spec)
    earlier = files_of(tmp_path / "imported")
    watch = CancelAtFirst(already)
    with pytest.raises(KeyboardInterrupt):
        run_import(spec, overwrite=True, progress=watch, cancel=watch.token)
    assert watch.only_began() and watch.token.reason is None
    assert files_of(tmp_path / "imported") == earlier


def test_dlo_import_hands_its_token_and_exits_as_on_ctrl_c(monkeypatch, tmp_path):
    source = write_cable(tmp_path / "cable", n_train=2, n_eval=1)
    out = tmp_path / "imported"
    run_import(ImportSpec(source=source, out=out))
    earlier = files_of(out)
    token = CancelToken()
    token.cancel()
    monkeypatch.setattr("dlocli.cli.importing.signal_token", lambda: token)  # `import`: a keyword
    res = dlo("import", "--source", str(source), "--out", str(out), "--overwrite")
    assert res.exit_code == 130 and "interrupted" in res.output, res.output
    assert files_of(out) == earlier
