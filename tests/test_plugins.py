"""A plugin package from outside dlocli (tests/plugin: a model, a backend, a learning agent,
a planner and a command, each registered by one entry-point line) works in every command: `list`,
`train` (tests/test_model_plugin.py), `online`, `control` and `bench`; the backend's fact
(its segment limit) reaches the spec, and the shared agent tests pick up its learner. Each
command runs in a fresh process that finds the plugin as an installed package."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from tiny import TINY_BENCH

REPO = Path(__file__).resolve().parents[1]
PLUGIN = Path(__file__).resolve().parent / "plugin"
#: an online run of two iterations of two 15-step trials, a tiny model of the plugin's
TINY_ONLINE = ["--iters", "2", "--trials", "2", "--steps", "15", "--epochs", "1",
               "--initial-episodes", "2", "--hidden", "8", "--seed", "3"]  # fmt: skip


def with_plugin(
    *argv: str, cwd: Path = REPO, more: tuple[Path, ...] = ()
) -> subprocess.CompletedProcess:
    """``python argv...`` in a fresh process whose path holds the plugin package (and the
    folders ``more``)."""
    folders = [*map(str, more), str(PLUGIN), str(REPO), os.environ.get("PYTHONPATH", "")]
    path = os.pathsep.join(folders)
    env = {**os.environ, "PYTHONPATH": path, "COLUMNS": "200"}
    return subprocess.run([sys.executable, *argv], capture_output=True, text=True, env=env,
                          cwd=cwd, timeout=600)  # fmt: skip


def dlo(*args: str) -> subprocess.CompletedProcess:
    return with_plugin("-m", "dlocli", *args)


def last_json(res: subprocess.CompletedProcess) -> dict:
    assert res.returncode == 0, res.stderr[-3000:]
    return json.loads(res.stdout.strip().splitlines()[-1])


def test_every_plugin_is_listed():
    listed = last_json(dlo("list", "--json"))
    assert "short-cable" in listed["backends"] and "chain" in listed["models"]
    assert {"best-constant", "shooting"} <= set(listed["controllers"])


def test_a_plugin_command_is_listed_and_runs(tmp_path):
    assert "goal-length" in dlo("--help").stdout
    goal = tmp_path / "goal.npy"
    assert dlo("goal", "--out", str(goal), "--shapes", "near-rest").returncode == 0
    length = last_json(dlo("goal-length", "--goal", str(goal), "--json"))["length_m"]
    assert 0.9 < length < 0.96  # 19 gaps of about a 5 cm segment each, the rod bent
    missing = dlo("goal-length", "--goal", str(tmp_path / "none.npy"))
    # its errors get dlo's one line and exit code
    assert missing.returncode == 2 and missing.stderr.count("\n") == 1, missing.stderr
    assert "none.npy" in missing.stderr


BROKEN_ENTRY_POINTS = """[dlocli.commands]
missing-module = dlo_no_such_module:run
no-docstring = dlo_broken_plugin:undocumented
"""


def test_a_broken_plugin_command_breaks_no_other_command(tmp_path):
    """An installed package whose commands are a missing module's and a function without a
    docstring: `dlo --help` lists every command, the broken one as broken with a warning
    naming the plugin, its entry point and the problem; running it is that line, exit 2."""
    installed = tmp_path / "site"
    info = installed / "dlo_broken_plugin-0.1.dist-info"
    info.mkdir(parents=True)
    (info / "METADATA").write_text("Metadata-Version: 2.1\nName: dlo-broken-plugin\nVersion: 0.1\n")
    (info / "entry_points.txt").write_text(BROKEN_ENTRY_POINTS)
    (installed / "dlo_broken_plugin.py").write_text(
        'def undocumented() -> None:\n    print("ran undocumented")\n'
    )

    def dlo_beside_it(*args: str) -> subprocess.CompletedProcess:
        return with_plugin("-m", "dlocli", *args, more=(installed,))

    shown = dlo_beside_it("--help")
    assert shown.returncode == 0, shown.stderr[-3000:]
    rows = {line.split()[0]: line for line in shown.stdout.splitlines() if line.startswith("  ")}
    assert {"goal", "control", "goal-length", "no-docstring"} <= set(rows), shown.stdout
    assert "Length (m) of the polyline" in rows["goal-length"]  # the good plugin's, intact
    assert "BROKEN" in rows["missing-module"] and "BROKEN" not in rows["no-docstring"]
    warning = shown.stderr.strip()
    assert warning.count("\n") == 0 and warning.startswith("warning: "), shown.stderr
    for words in ("dlo-broken-plugin", "missing-module = dlo_no_such_module:run",
                  "no module named 'dlo_no_such_module'"):  # fmt: skip
        assert words in warning, warning
    broken = dlo_beside_it("missing-module", "--help")
    assert broken.returncode == 2 and broken.stderr.count("\n") == 1, broken.stderr
    assert "dlo-broken-plugin" in broken.stderr and "dlo_no_such_module:run" in broken.stderr
    assert "No module named 'dlo_no_such_module'" in broken.stderr
    undocumented = dlo_beside_it("no-docstring")
    assert undocumented.returncode == 0 and "ran undocumented" in undocumented.stdout
    goal = tmp_path / "goal.npy"
    made = dlo_beside_it("goal", "--out", str(goal), "--shapes", "near-rest")
    assert made.returncode == 0 and goal.exists(), made.stderr[-3000:]


def test_the_backends_segment_limit_reaches_the_spec(tmp_path):
    spec = tmp_path / "spec.yaml"
    spec.write_text(yaml.safe_dump({"backend": {"rod": {"n_segments": 25}}}))
    res = dlo("goal", "--backend", "short-cable", "--spec", str(spec),
              "--out", str(tmp_path / "goal.npy"))  # fmt: skip
    assert res.returncode == 2 and "simulates at most 24 rod segments" in res.stderr
    assert not (tmp_path / "goal.npy").exists()


@pytest.fixture(scope="module")
def online_run(tmp_path_factory) -> tuple[Path, dict]:
    """Algorithm 1 on the plugin's backend, with its model and its planner."""
    out = tmp_path_factory.mktemp("plugin") / "online"
    summary = last_json(dlo("online", *TINY_ONLINE, "--backend", "short-cable", "--model",
                            "chain", "--depth", "2", "--planner", "shooting", "--out", str(out),
                            "--json"))  # fmt: skip
    return out, summary


def test_online_runs_on_the_plugins_backend_model_and_planner(online_run):
    out, summary = online_run
    assert summary["iterations_done"] == 2 and summary["transitions"] == 90
    spec = json.loads((out / "spec.json").read_text())
    assert (spec["backend"]["name"], spec["model"]["name"], spec["model"]["depth"]) == (
        "short-cable", "chain", 2)  # fmt: skip
    assert spec["planner"] == "shooting" and spec["mpc"]["samples"] == 8


def test_control_plans_with_the_plugins_planner(online_run, tmp_path):
    out, _ = online_run
    goal = tmp_path / "goal.npy"
    assert dlo("goal", "--backend", "short-cable", "--shapes", "near-rest",
               "--out", str(goal)).returncode == 0  # fmt: skip
    summary = last_json(dlo("control", "--goal", str(goal), "--backend", "short-cable",
                            "--checkpoint", str(out / "checkpoints" / "final.pt"),
                            "--controller", "shooting", "-o", "samples=4", "--steps", "3",
                            "--shapes", "near-rest", "--out", str(tmp_path / "control"),
                            "--json"))  # fmt: skip
    assert summary["controller"] == "shooting" and summary["steps"] == 3


def test_bench_runs_the_plugins_learner_and_plans_with_its_planner(tmp_path):
    spec = tmp_path / "bench.yaml"
    tiny = {**TINY_BENCH, "model": {"name": "chain", "hidden": 8}, "transfer": False}
    spec.write_text(yaml.safe_dump(tiny))
    out = tmp_path / "bench"
    res = dlo("bench", "--spec", str(spec), "--agents", "best-constant,mpc", "--backend",
              "short-cable", "--planner", "shooting", "--out", str(out), "--json")  # fmt: skip
    last_json(res)
    jobs = {json.loads(p.read_text())["agent"] for p in (out / "jobs").glob("*.json")}
    assert jobs == {"best-constant", "mpc"}
    saved = json.loads((out / "spec.json").read_text())
    assert saved["planner"] == "shooting" and saved["model"]["name"] == "chain"


def test_the_shared_agent_tests_pick_up_the_plugins_learner():
    res = with_plugin("-m", "pytest", "-q", "-p", "no:cacheprovider", "-k", "best-constant",
                      str(REPO / "tests" / "test_agents.py"))  # fmt: skip
    assert res.returncode == 0, res.stdout[-3000:]
    assert "2 passed" in res.stdout, res.stdout[-3000:]
