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
    assert "--depth" in text and "chain: Hidden layers of the per-segment network." in text
    assert "One of: attention, chain, in-bilstm, mlp." in text

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
