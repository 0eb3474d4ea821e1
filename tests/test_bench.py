"""`dlo bench`: a tiny real benchmark (MuJoCo, SB3, PILCO, online MPC), resume, report, bad
input, and Ray against local processes. Budgets are 60 transitions of 20-step episodes."""

from __future__ import annotations

import csv
import json
import shutil
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from typer.testing import CliRunner

from dlocli.cli import app
from dlocli.errors import BadInput
from dlocli.io import MANIFEST_FILE, written_by_dlo

from tiny import TINY_BENCH, committed_bench, lock_held_elsewhere

runner = CliRunner()
TIMING = ("wall_seconds", "eval_seconds")


def tiny_spec(tmp_path: Path) -> str:
    path = tmp_path / "tiny.json"
    path.write_text(json.dumps(TINY_BENCH))
    return str(path)


def bench(*args: str) -> Any:
    result = runner.invoke(app, ["bench", *args])
    assert result.exit_code == 0, result.output
    return result


def read_rows(run: Path) -> list[dict[str, str]]:
    with open(run / "results.csv") as f:
        return list(csv.DictReader(f))


def without_timing(rows: list[dict[str, str]]) -> list[dict[str, str]]:
    return [{k: v for k, v in row.items() if k not in TIMING} for row in rows]


def test_tiny_bench_resume_and_report(tmp_path: Path):
    run = tmp_path / "run"
    spec = tiny_spec(tmp_path)
    summary = json.loads(
        bench(
            "--spec", spec, "--agents", "zero,random,sac,pilco,mpc", "--out", str(run), "--json"
        ).stdout
    )
    assert summary["jobs_done"] == summary["jobs"] == 5
    for agent in ("zero", "sac", "mpc"):  # every result carries its reference
        assert {"initial_error_mm", "score"} <= set(summary["results"][agent])
    assert abs(summary["results"]["zero"]["score"]) < 0.05
    rows = read_rows(run)
    home = [r for r in rows if r["eval_task"] == "single" and r["eval_goals"] == "fixed"]
    points = {
        a: [int(r["transitions"]) for r in home if r["agent"] == a]
        for a in ("random", "sac", "pilco", "mpc")
    }
    assert points == {
        "random": [20, 40, 60],
        "sac": [20, 40, 60],
        "pilco": [20, 40, 60],
        "mpc": [40, 60],
    }  # mpc: 2 initial random episodes, then 1 trial
    # the same starts for every agent; do nothing keeps the initial error
    zero = [r for r in home if r["agent"] == "zero"]
    assert {r["initial_error_mm"] for r in home} == {zero[0]["initial_error_mm"]}
    assert all(float(r["final_error_mm"]) > 0.9 * float(r["initial_error_mm"]) for r in zero)
    # training-trial rewards: one 20-step episode per 20 transitions for the learning agents
    assert [r["train_episodes"] for r in home if r["agent"] == "sac"] == ["1", "1", "1"]
    assert all(float(r["train_reward"]) < 0 for r in home if r["agent"] in ("sac", "mpc"))
    assert {r["train_reward"] for r in zero} == {""}
    transfers = {(r["agent"], r["eval_task"], r["eval_goals"]) for r in rows} - {
        (a, "single", "fixed") for a in [*points, "zero"]
    }
    assert ("mpc", "bimanual", "fixed") in transfers and ("sac", "single", "random") in transfers
    assert ("sac", "bimanual", "fixed") not in transfers  # a 6-D policy cannot act there
    for name in (
        "spec.json",
        "summary.md",
        "summary.json",
        "plots/fig4_learning_curves.png",
        "plots/fig5_bimanual.png",
        "plots/fig6_random_goals.png",
    ):
        assert (run / name).is_file(), name
    table = (run / "summary.md").read_text()
    assert "| sac | single, fixed goal | single, fixed goal | 1 | 60 |" in table
    assert "Transitions until half the initial error is closed" in table
    assert (run / "plots" / "fig4_training_trials.png").is_file()

    # the sac job saved its final policy; `dlo control` runs it, and refuses sac untrained
    policy = Path(json.loads((run / "jobs" / "sac-s0.json").read_text())["policy"])
    assert (policy / "model.zip").is_file() and (policy / "agent.json").is_file()
    goal = tmp_path / "goal.npy"
    assert runner.invoke(app, ["goal", "--out", str(goal), "--shapes", "near-rest"]).exit_code == 0
    control = ["control", "--goal", str(goal), "--controller", "sac", "--steps", "5", "--json"]
    ran = runner.invoke(app, [*control, "--policy", str(policy), "--out", str(tmp_path / "c1")])
    assert ran.exit_code == 0, ran.output
    assert json.loads(ran.stdout)["steps"] == 5
    untrained = runner.invoke(app, [*control, "--out", str(tmp_path / "c2")])
    assert untrained.exit_code == 2 and "--policy" in untrained.output

    # resume: a lost job is rerun (same result), a new agent added; kept jobs are not rerun
    (run / "jobs" / "random-s0.json").unlink()
    (run / MANIFEST_FILE).unlink()  # as a run killed outright leaves it: its files unrecorded
    kept = {p.name: p.stat().st_mtime_ns for p in (run / "jobs").iterdir()}
    res = bench(
        "--resume", str(run), "--agents", "zero,random,sac,pilco,mpc,mpc-offline", "--workers", "2"
    )
    assert "2 job(s) to run, 4 finished job(s) kept" in res.output
    assert {"spec.json", "jobs/sac-s0.json", "summary.md"} <= written_by_dlo(run)  # adopted
    assert {
        p.name: p.stat().st_mtime_ns for p in (run / "jobs").iterdir() if p.name in kept
    } == kept
    again = read_rows(run)
    assert without_timing([r for r in again if r["agent"] != "mpc-offline"]) == without_timing(rows)
    offline = [
        r
        for r in again
        if r["agent"] == "mpc-offline" and r["eval_task"] == "single" and r["eval_goals"] == "fixed"
    ]
    first_mpc = next(r for r in rows if r["agent"] == "mpc")
    # at the first point both models are trained alike on the same random data
    assert without_timing([offline[0]])[0] | {"agent": "mpc"} == without_timing([first_mpc])[0]
    assert (run / "plots" / "fig7_online_offline.png").is_file()

    shutil.rmtree(run / "plots")
    bench("--report", str(run))
    assert (run / "plots" / "fig4_learning_curves.png").is_file()
    res = runner.invoke(app, ["bench", "--resume", str(run), "--budget", "80"])
    assert res.exit_code == 2 and "conflicts" in res.output


@pytest.mark.parametrize(
    ("flags", "message"),
    [
        (
            ["--agents", "sac,dqn"],
            "valid agents: held-end, mpc, mpc-offline, pilco, random, sac, td3",
        ),
        (["--budget", "10"], "less than one episode"),
        (["--executor", "ray", "--ray-address", "127.0.0.1:1"], "Ray"),
        (["--ray-address", "127.0.0.1:6379"], "needs --executor ray"),
    ],
)
def test_bad_input_is_one_line_and_exit_2(tmp_path: Path, flags: list[str], message: str):
    out = tmp_path / "out"
    res = runner.invoke(app, ["bench", "--spec", tiny_spec(tmp_path), *flags, "--out", str(out)])
    assert res.exit_code == 2, res.output
    assert message in res.output and "Traceback" not in res.output
    assert not out.exists()
    res = runner.invoke(app, ["bench", "--report", str(tmp_path)])
    assert res.exit_code == 2 and "results.csv" in res.output


def test_processes_share_out_a_bench_skipping_the_jobs_another_holds(tmp_path: Path):
    """A second process on one bench runs the jobs the first does not hold, and says which
    it leaves; once the holder is gone, a resume runs the rest."""
    run = tmp_path / "run"
    bench("--spec", tiny_spec(tmp_path), "--agents", "random", "--out", str(run))
    with lock_held_elsewhere(run / "work" / "locks" / "zero-s0" / ".dlo.lock") as holder:
        out = bench("--resume", str(run), "--agents", "zero", "--seeds", "2").output
        assert f"zero-s0 is running in another process (PID {holder.pid})" in out
        assert sorted(p.name for p in (run / "jobs").iterdir()) == [
            "random-s0.json",
            "zero-s1.json",
        ]
    out = bench("--resume", str(run), "--agents", "zero", "--seeds", "2").output
    assert "1 job(s) to run" in out and "another process" not in out
    assert (run / "jobs" / "zero-s0.json").is_file()


def test_ray_gives_the_same_results_as_local_processes(tmp_path: Path):
    ray = pytest.importorskip("ray")
    spec = tiny_spec(tmp_path)
    common = ["--spec", spec, "--agents", "sac,mpc", "--no-transfer"]
    bench(*common, "--out", str(tmp_path / "local"))
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)  # the suite's instance
    try:
        bench(*common, "--executor", "ray", "--out", str(tmp_path / "ray"))
    finally:
        ray.shutdown()
    assert without_timing(read_rows(tmp_path / "ray")) == without_timing(
        read_rows(tmp_path / "local")
    )


def test_runs_saved_before_a_model_field_existed_keep_their_jobs(tmp_path: Path):
    """A spec.json written before `absolute_position` existed means the model it had then
    (absolute positions), and its jobs keep their fingerprint, so --resume reuses them."""
    from dlocli.bench.run import load_bench_spec
    from dlocli.bench.spec import BenchSpec, fingerprint

    spec = BenchSpec(model={"absolute_position": True})
    saved = spec.model_dump(mode="json")
    del saved["model"]["absolute_position"]
    (tmp_path / "spec.json").write_text(json.dumps(saved))
    again = load_bench_spec(tmp_path)
    assert again.model.absolute_position is True
    assert fingerprint(again) == fingerprint(spec)
    moved = spec.model_copy(
        update={"model": spec.model.model_copy(update={"absolute_position": False})}
    )
    assert fingerprint(moved) != fingerprint(spec)


def test_each_seed_has_its_own_goal_and_agents_their_own_budgets():
    from dlocli.bench.agents import fixed_goal
    from dlocli.bench.run import check_spec
    from dlocli.bench.spec import BenchSpec, eval_points, fingerprint

    spec = BenchSpec.model_validate({**TINY_BENCH, "budgets": {"sac": 100}})
    assert np.abs(fixed_goal(spec, "single", 0) - fixed_goal(spec, "single", 1)).max() > 0.01
    np.testing.assert_array_equal(fixed_goal(spec, "single", 1), fixed_goal(spec, "single", 1))
    assert eval_points(spec, "sac") == [20, 40, 60, 80, 100]
    assert eval_points(spec, "td3") == [20, 40, 60]
    # a longer budget reruns that agent's jobs only
    assert fingerprint(spec, "sac") != fingerprint(spec.model_copy(update={"budgets": {}}), "sac")
    assert fingerprint(spec, "zero") == fingerprint(spec.model_copy(update={"budgets": {}}), "zero")
    check_spec(spec)
    mismatched = spec.model_copy(
        update={"task": spec.task.model_copy(update={"observe_velocity": False})}
    )
    with pytest.raises(BadInput, match="same information"):
        check_spec(mismatched)


@pytest.mark.parametrize("example", ["bench_paper", "bench_bimanual", "bench_paper_mirror"])
def test_committed_paper_bench_jobs_resume_without_rerunning(example: str, tmp_path: Path):
    """The committed bench runs' job files hold under today's code: a resume keeps them."""
    from dlocli.bench.run import BenchRun, load_bench_spec

    source = committed_bench(example, tmp_path / example)
    run = BenchRun(load_bench_spec(source))
    jobs = sorted((source / "jobs").glob("*.json"))
    assert jobs
    for path in jobs:
        agent, _, seed = path.stem.rpartition("-s")
        assert run.finished(agent, int(seed)) is not None, f"{path.name} would run again"


def test_a_kept_bench_run_reports_its_kept_summary(tmp_path: Path):
    """examples/bench_paper keeps the summary and jobs.json, not the job files: the job files
    rebuilt from them (examples/bench_jobs.py) report the same results and tables."""
    kept = Path(__file__).parent.parent / "examples" / "bench_paper"
    run = committed_bench("bench_paper", tmp_path / "bench_paper")
    bench("--report", str(run))
    assert (run / "results.csv").read_bytes() == (kept / "results.csv").read_bytes()

    def table(path: Path) -> list[str]:
        return [line for line in path.read_text().splitlines() if line.startswith("|")]

    assert table(run / "summary.md") == table(kept / "summary.md")


def test_report_merges_runs_into_a_new_directory_labelling_shared_agents(tmp_path: Path):
    """Fig. 5 from several runs: the same agent learned alike in two runs (e.g. mpc with and
    without the mirror option) is two agents, each named after its run."""
    committed = committed_bench("bench_paper", tmp_path / "bench_paper")
    plain, mirrored, merged = tmp_path / "plain", tmp_path / "mirrored", tmp_path / "fig5"
    for run in (plain, mirrored):
        (run / "jobs").mkdir(parents=True)
        shutil.copy(committed / "spec.json", run / "spec.json")
    for job in committed.glob("jobs/*.json"):
        if job.name.startswith(("zero", "mpc-s")):  # not mpc-offline
            shutil.copy(job, plain / "jobs")
        if job.name.startswith(("zero-s0", "mpc-s")):
            shutil.copy(job, mirrored / "jobs")
    merged.mkdir()
    bench("--report", str(merged), "--report", str(plain), "--report", str(mirrored))
    table = json.loads((merged / "summary.json").read_text())["table"]
    agents = {row["agent"] for row in table}
    # the do-nothing reference is one agent, its seed 0 (in both runs) counted once
    assert agents == {"zero", "mpc [plain]", "mpc [mirrored]"}
    zero = [row for row in table if row["agent"] == "zero"]
    assert zero and all(row["seeds"] == 3 for row in zero)  # 4 if seed 0 counted twice
    assert (merged / "plots" / "fig5_bimanual.png").is_file()
    assert not (merged / "results.csv").exists()  # the sources keep theirs
