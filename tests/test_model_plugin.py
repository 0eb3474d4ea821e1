"""A dynamics model from outside the package, registered through the ``dlocli.models``
entry-point group, brings its own option: `dlo train --help` offers it as a flag and its
value reaches the model. The plugin is installed as a package is (a dist-info with its entry
point) in a directory on the path of a fresh process."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from itertools import pairwise
from pathlib import Path

import pytest

PLUGIN = '''
from typing import ClassVar

import torch
from pydantic import Field

from dlocli.models.base import ACTION_DIM, STATE_DIM, DynamicsModel, mlp, node_actions
from dlocli.models.spec import ModelSpec


class ChainSpec(ModelSpec):
    depth: int = Field(1, gt=0, le=8, description="Hidden layers of the per-segment network.")


class ChainModel(DynamicsModel):
    """Each segment on its own: one MLP from its features and its gripper's command."""

    spec_cls: ClassVar[type[ModelSpec]] = ChainSpec

    def __init__(self, spec, n_segments):
        super().__init__(spec, n_segments)
        sizes = [self.feature_dim + ACTION_DIM] + [spec.hidden] * spec.depth + [STATE_DIM]
        self.net = mlp(sizes)

    def predict_delta(self, state_n, action_n):
        actions = node_actions(action_n, self.n_segments)
        return self.net(torch.cat([state_n, actions], -1))
'''


@pytest.fixture(scope="module")
def plugin_path(tmp_path_factory: pytest.TempPathFactory) -> Path:
    root = tmp_path_factory.mktemp("plugin")
    (root / "chain_plugin.py").write_text(PLUGIN)
    info = root / "chain_plugin-0.1.dist-info"
    info.mkdir()
    (info / "METADATA").write_text("Metadata-Version: 2.1\nName: chain-plugin\nVersion: 0.1\n")
    (info / "entry_points.txt").write_text("[dlocli.models]\nchain = chain_plugin:ChainModel\n")
    return root


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
    assert "One of: chain, in-bilstm, mlp." in text

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
