"""A dynamics model from outside the package, registered through the ``dlocli.models``
entry-point group, brings its own option: `dlo train --help` offers it as a flag and its
value reaches the model. The plugin (tests/plugin) is installed as a package is (a dist-info
with its entry points) in a directory on the path of a fresh process."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from itertools import pairwise
from pathlib import Path

import pytest

from dlocli.registry import models


@pytest.fixture(scope="module")
def plugin_path() -> Path:
    """The plugin package of tests/plugin: its model ``chain`` has the option ``depth``."""
    return Path(__file__).resolve().parent / "plugin"


def dlo(plugin_path: Path, *args: str) -> subprocess.CompletedProcess:
    repo = Path(__file__).resolve().parents[1]
    path = os.pathsep.join([str(plugin_path), str(repo), os.environ.get("PYTHONPATH", "")])
    env = {**os.environ, "PYTHONPATH": path, "COLUMNS": "200"}
    return subprocess.run([sys.executable, "-m", "dlocli", *args], capture_output=True,
                          text=True, env=env, timeout=600)  # fmt: skip


def test_a_plugin_model_brings_its_own_option(plugin_path, small_dataset_dir, tmp_path):
    shown = dlo(plugin_path, "train", "--help")
    assert shown.returncode == 0, shown.stderr
    text = " ".join(shown.stdout.split())
    assert "--depth" in text and "chain: Hidden layers of the per-node network." in text
    built_in = [n for n in models.names() if n != "chain"]  # the plugin joins the built-ins
    assert f"One of: {', '.join(sorted([*built_in, 'chain']))}." in text

    out = tmp_path / "run"
    res = dlo(plugin_path, "train", "--data", str(small_dataset_dir), "--model", "chain",
              "--depth", "3", "--hidden", "8", "--epochs", "1", "--batch-size", "64",
              "--device", "cpu", "--out", str(out), "--json")  # fmt: skip
    assert res.returncode == 0, res.stderr
    summary = json.loads(res.stdout.strip().splitlines()[-1])
    sizes = [14 + 6, 8, 8, 8, 7]  # features (with velocity) and command, 3 hidden, the change
    assert summary["parameters"] == sum((a + 1) * b for a, b in pairwise(sizes))
    saved = json.loads((out / "spec.json").read_text())["model"]
    assert (saved["name"], saved["depth"], saved["hidden"]) == ("chain", 3, 8)

    wrong = dlo(plugin_path, "train", "--data", str(small_dataset_dir), "--depth", "3",
                "--out", str(tmp_path / "wrong"))  # fmt: skip
    assert wrong.returncode == 2 and "model.depth" in wrong.stderr + wrong.stdout


def test_a_plugin_model_learns_a_recorded_cable_through_the_marker_view(
    plugin_path, marker_run, tmp_path
):
    """The same plugin network, with no marker code of its own, trains on recorded markers
    and is scored by `dlo eval` against freezing the cable on the same recordings."""
    dataset, _ = marker_run
    out = tmp_path / "markers"
    res = dlo(plugin_path, "train", "--data", str(dataset), "--model", "chain", "--depth", "2",
              "--hidden", "8", "--update-steps", "30", "--rollout-steps", "4", "--device", "cpu",
              "--out", str(out), "--json")  # fmt: skip
    assert res.returncode == 0, res.stderr
    summary = json.loads(res.stdout.strip().splitlines()[-1])
    sizes = [10, 8, 8, 3]  # a marker's features, 2 hidden, its acceleration
    assert summary["form"] == "markers"
    assert summary["parameters"] == sum((a + 1) * b for a, b in pairwise(sizes))
    scored = dlo(plugin_path, "eval", "--checkpoint", str(out), "--data", str(dataset),
                 "--out", str(tmp_path / "eval"), "--json")  # fmt: skip
    assert scored.returncode == 0, scored.stderr
    result = json.loads((tmp_path / "eval" / "summary.json").read_text())
    assert result["episodes"] == 2 and len(result["model_scores_cm"]) == 2
    assert 0 < result["model_score_cm"] < 10 * result["freeze_score_cm"]
