"""`dlo online` (Algorithm 1): paper defaults, a reduced real run, resume after SIGKILL."""

from __future__ import annotations

import csv
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import torch
from typer.testing import CliRunner

from dlocli.cli import app
from dlocli.data import load_dataset
from dlocli.runs.online import OnlineSpec

runner = CliRunner()
TINY = [
    "--iters",
    "2",
    "--trials",
    "2",
    "--steps",
    "15",
    "--epochs",
    "1",
    "--initial-episodes",
    "2",
    "--hidden",
    "16",
    "--seed",
    "3",
]


def test_defaults_are_the_papers():
    spec = OnlineSpec()
    assert (spec.iters, spec.fit.epochs, spec.trials, spec.task.episode_steps) == (20, 50, 50, 200)
    assert spec.mpc.horizon == 5 and spec.fit.lr == 1e-4 and spec.noise_probability == 0.2
    assert spec.model.name == "in-bilstm" and spec.model.hidden == 150
    assert spec.task.goal == "fixed"
    help_text = runner.invoke(app, ["online", "--help"], env={"COLUMNS": "250"}).output
    assert "[default: 20]" in help_text and "[default: 50]" in help_text


def read_rows(run: Path) -> list[dict[str, str]]:
    with open(run / "metrics.csv") as f:
        return list(csv.DictReader(f))


@pytest.fixture(scope="module")
def uninterrupted(tmp_path_factory):
    out = tmp_path_factory.mktemp("online") / "run"
    res = runner.invoke(app, ["online", *TINY, "--out", str(out), "--json"])
    assert res.exit_code == 0, res.output
    return out, json.loads(res.stdout.strip().splitlines()[-1])


def test_overwrite_starts_afresh(uninterrupted, tmp_path):
    """--overwrite on an earlier run's directory does not reuse its trials or checkpoints."""
    first, _ = uninterrupted
    out = tmp_path / "run"
    shutil.copytree(first, out)
    args = ["online", *TINY[:-1], "4", "--out", str(out), "--overwrite", "--json"]
    assert TINY[-2] == "--seed" and TINY[-1] != "4"
    res = runner.invoke(app, args)
    assert res.exit_code == 0, res.output
    again, before = read_rows(out), read_rows(first)
    assert len(again) == len(before)
    assert [r["cumulative_reward"] for r in again] != [r["cumulative_reward"] for r in before]


def test_reduced_run_writes_everything(uninterrupted):
    out, summary = uninterrupted
    for name in (
        "spec.json",
        "metrics.csv",
        "summary.json",
        "plots/learning_curve.png",
        "checkpoints/iter_01.pt",
        "checkpoints/iter_02.pt",
        "checkpoints/final.pt",
    ):
        assert (out / name).is_file(), name
    rows = read_rows(out)
    assert [(r["iteration"], r["trial"]) for r in rows] == [
        ("1", "1"),
        ("1", "2"),
        ("2", "1"),
        ("2", "2"),
    ]
    assert summary["iterations_done"] == 2
    assert summary["initial_error_mm"] > 0  # the reference: what doing nothing keeps
    first = rows[0]
    assert float(first["score"]) == pytest.approx(
        1 - float(first["final_error_mm"]) / float(first["initial_error_mm"])
    )
    assert summary["transitions"] == 2 * 15 + 4 * 15
    saved = json.loads((out / "spec.json").read_text())
    assert saved["iters"] == 2 and saved["model"]["hidden"] == 16
    from dlocli.models.checkpoints import read_checkpoint

    for name in ("iter_01.pt", "final.pt"):  # the period the model steps by
        assert read_checkpoint(out / "checkpoints" / name)["control_dt"] == 0.02
    # where the rod rested: iteration 1's data (2 episodes), then 2 trials more, each start
    # and the ends where the grippers stood still (the planner's rest_roll reads them)
    rests = [len(read_checkpoint(out / "checkpoints" / name)["rest_states"]["grippers"])
             for name in ("iter_01.pt", "iter_02.pt")]  # fmt: skip
    assert 2 <= rests[0] <= 4 and rests[0] + 2 <= rests[1] <= rests[0] + 4
    # where the time went: model updates, planning, the rest of the trials (simulation)
    assert summary["train_seconds"] > 0 and summary["mpc_seconds"] > 0
    assert summary["simulation_seconds"] > 0
    trials = sum(float(r["trial_seconds"]) for r in rows)
    assert summary["mpc_seconds"] + summary["simulation_seconds"] == pytest.approx(trials, abs=0.2)


def test_references_run_from_the_trials_starts(uninterrupted):
    """Doing nothing and random actions from every trial's start and goal: the same initial
    error as the trial, their means in the curve and the summary."""
    out, summary = uninterrupted
    table = json.loads((out / "references.json").read_text())
    assert sorted(table) == ["held-end", "random", "zero"]
    rows = {(int(r["iteration"]), int(r["trial"])): r for r in read_rows(out)}
    for name in ("zero", "random", "held-end"):
        assert sorted(table[name]) == sorted(f"{k}/{j}" for k, j in rows)
        for (k, j), row in rows.items():
            ran = table[name][f"{k}/{j}"]
            assert ran["initial_error_mm"] == pytest.approx(float(row["initial_error_mm"]))
    zero = [table["zero"][f"2/{j}"]["final_error_mm"] for j in (1, 2)]
    assert summary["zero_final_error_mm"] == pytest.approx(np.mean(zero))
    assert summary["random_final_error_mm"] != summary["zero_final_error_mm"]
    servo = [table["held-end"][f"2/{j}"]["final_error_mm"] for j in (1, 2)]
    assert summary["held_end_final_error_mm"] == pytest.approx(np.mean(servo))
    assert summary["reference_seconds"] > 0


def test_threads_override_reaches_the_workers_and_the_update_and_warns_once(
    uninterrupted, tmp_path, monkeypatch
):
    """--threads 2 with 2 local workers: every trial (in a pool process) and the model update
    ran with 2 torch threads, where the default gives a trial 1; on 2 CPUs that is 4 busy
    threads: one warning, once."""
    from dlocli import threads
    from dlocli.models.checkpoints import read_checkpoint

    first, _ = uninterrupted
    assert {load_dataset(f).attrs["threads"] for f in (first / "data").glob("iter_*/*.h5")} == {1}
    monkeypatch.setattr(threads, "_warned", False)
    monkeypatch.setattr(threads, "machine_cpus", lambda: 2)
    out = tmp_path / "run"
    one_iteration = [*TINY[:1], "1", *TINY[2:]]
    args = ["online", *one_iteration, "--workers", "2", "--threads", "2", "--out", str(out)]
    res = runner.invoke(app, args)
    assert res.exit_code == 0, res.output
    assert res.output.count("warning: --threads 2 x 2 process(es) = 4 busy threads") == 1
    assert [load_dataset(f).attrs["threads"] for f in (out / "data").glob("iter_*/*.h5")] == [2, 2]
    assert read_checkpoint(out / "checkpoints" / "iter_01.pt")["threads"] == 2


def test_references_shared_among_workers_match_the_serial_ones(uninterrupted, tmp_path):
    from dlocli.runs.online import OnlineRun

    first, _ = uninterrupted
    out = tmp_path / "run"
    shutil.copytree(first, out)
    (out / "references.json").unlink()
    spec = OnlineSpec.model_validate_json((out / "spec.json").read_text())
    run = OnlineRun(spec.model_copy(update={"workers": 2, "out": out}))
    try:
        run.run_references(2)
    finally:
        run.executor.close()
    serial = json.loads((first / "references.json").read_text())
    shared = json.loads((out / "references.json").read_text())
    for name in ("zero", "random"):
        for key in ("2/1", "2/2"):
            a, b = serial[name][key], shared[name][key]
            assert {k: v for k, v in a.items() if k != "seconds"} == {
                k: v for k, v in b.items() if k != "seconds"
            }


def _steps(run: Path, tag: str) -> list[int]:
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    events = EventAccumulator(str(run / "tensorboard"))
    events.Reload()
    return [e.step for e in events.Scalars(tag)]


def test_tensorboard_events_hold_loss_and_error(uninterrupted):
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    out, summary = uninterrupted
    events = EventAccumulator(str(out / "tensorboard"))
    events.Reload()
    assert {"loss/train", "loss/val", "trials/final_error_mm", "trials/score"} <= set(
        events.Tags()["scalars"]
    )
    assert [e.step for e in events.Scalars("loss/train")] == [1, 2]  # 1 epoch per iteration
    errors = events.Scalars("trials/final_error_mm")
    assert [e.step for e in errors] == [c[0] for c in summary["curve"]]  # at transitions
    assert errors[-1].value == pytest.approx(summary["final_error_mm"], rel=1e-5)


def test_resumed_finished_run_keeps_its_time(uninterrupted, tmp_path):
    first, summary = uninterrupted
    out = tmp_path / "run"
    shutil.copytree(first, out)
    res = runner.invoke(app, ["online", "--resume", str(out), "--json"])
    assert res.exit_code == 0, res.output
    assert json.loads(res.stdout.strip().splitlines()[-1])["seconds"] >= summary["seconds"]


def test_resume_after_sigkill_matches_uninterrupted(uninterrupted, tmp_path):
    reference, summary = uninterrupted
    out = tmp_path / "killed"
    cmd = [sys.executable, "-m", "dlocli.cli", "online", *TINY, "--out", str(out), "--json"]
    # the killed run uses the torch thread count of this process, as the reference did:
    # float sums differ with the thread count
    env = {**os.environ, "OMP_NUM_THREADS": str(torch.get_num_threads())}
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, env=env)
    deadline = time.time() + 300
    while not (out / "checkpoints" / "iter_02.pt").exists():  # inside iteration 2
        assert proc.poll() is None and time.time() < deadline, "run ended before iteration 2"
        time.sleep(0.05)
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait()
    res = runner.invoke(app, ["online", "--resume", str(out), "--json"])
    assert res.exit_code == 0, res.output
    resumed = json.loads(res.stdout.strip().splitlines()[-1])
    assert resumed["transitions"] == summary["transitions"]
    assert _steps(out, "trials/final_error_mm") == [c[0] for c in summary["curve"]], "once each"
    rows = read_rows(out)
    keys = [(r["iteration"], r["trial"]) for r in rows]
    assert len(keys) == len(set(keys)) == 4, "no duplicate or missing trials"
    for k in (1, 2):
        for j in (1, 2):
            a = load_dataset(reference / "data" / f"iter_{k:02d}" / f"trial_{j:03d}.h5")
            b = load_dataset(out / "data" / f"iter_{k:02d}" / f"trial_{j:03d}.h5")
            np.testing.assert_allclose(a.positions, b.positions, atol=1e-6)


def test_resume_bad_input(tmp_path, uninterrupted):
    out, _ = uninterrupted
    before = sorted(p.name for p in out.rglob("*"))
    res = runner.invoke(app, ["online", "--resume", str(out), "--trials", "9"])
    assert res.exit_code == 2 and "conflicts" in res.output
    assert sorted(p.name for p in out.rglob("*")) == before
    res = runner.invoke(app, ["online", "--resume", str(tmp_path)])
    assert res.exit_code == 2 and "not an online run" in res.output


@pytest.mark.parametrize("schedule", ["epochs", "steps"])
def test_offline_comparison_runs_beside_the_online_loop(tmp_path, schedule):
    """Paper Fig. 7 (`--offline`): after each iteration a fresh model on as many random
    transitions, trained as long as the online one, runs the same trials."""
    out = tmp_path / "run"
    spec = tmp_path / "spec.yaml"
    spec.write_text(f"fit: {{schedule: {schedule}, update_steps: 4, eval_every: 2}}\n")
    res = runner.invoke(app, ["online", *TINY, "--offline", "--spec", str(spec), "--out",
                              str(out), "--json"])  # fmt: skip
    assert res.exit_code == 0, res.output
    summary = json.loads((out / "summary.json").read_text())
    online, offline = summary["curve"], summary["offline_curve"]
    assert [c["transitions"] for c in offline] == [c["transitions"] for c in online]
    for k in (1, 2):
        assert (out / "checkpoints" / f"offline_{k:02d}.pt").is_file()
        random = load_dataset(out / "offline" / f"random_{k:02d}.h5")
        assert random.n_transitions >= online[k - 1]["transitions"] - 2 * 15  # as much data
    assert (out / "plots" / "learning_curve.png").is_file()


def test_log_gets_a_line_per_unit_and_ctrl_c_stops_quietly(tmp_path):
    """Output to a file: a plain progress line per finished trial and iteration (with elapsed
    time and ETA). Ctrl-C (SIGINT to the whole process group, as a terminal sends it) while
    two workers run trials: exit 130, one line on stderr, no worker traceback."""
    out, log, err = tmp_path / "run", tmp_path / "log.txt", tmp_path / "err.txt"
    cmd = [sys.executable, "-m", "dlocli", "online", *TINY, "--workers", "2", "--out", str(out)]
    with log.open("w") as stdout, err.open("w") as stderr:
        proc = subprocess.Popen(cmd, stdout=stdout, stderr=stderr, start_new_session=True)
        deadline = time.time() + 300
        while log.read_text().count("epoch 1/1") < 2:  # iteration 2's trials start
            assert proc.poll() is None and time.time() < deadline, err.read_text()
            time.sleep(0.1)
        os.killpg(proc.pid, signal.SIGINT)
        assert proc.wait(timeout=120) == 130
    lines = log.read_text().splitlines()
    assert [line.split("  ")[0] for line in lines if line.startswith(("trial", "iteration"))][
        :3
    ] == ["trial 1/2", "trial 2/2", "iteration 1/2"], lines
    assert "elapsed 0:00:" in lines[-1] and any("eta 0:" in line for line in lines), lines
    assert err.read_text().splitlines() == ["interrupted: finished work was saved"]
