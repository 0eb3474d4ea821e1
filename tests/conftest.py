"""Shared fixtures. Tests use the real simulators and real torch models, kept small."""

from __future__ import annotations

import os

import pytest

os.environ.setdefault("MPLBACKEND", "Agg")


def pytest_configure(config: pytest.Config) -> None:
    try:
        import torch

        torch.set_num_threads(min(2, os.cpu_count() or 1))
    except ImportError:
        pass


@pytest.fixture(scope="session")
def small_dataset_dir(tmp_path_factory: pytest.TempPathFactory):
    """A small real MuJoCo single-gripper random dataset (6 episodes x 60 steps)."""
    from dlocli.runs.collect import collect_random
    from dlocli.specs import CollectSpec

    out = tmp_path_factory.mktemp("small_dataset")
    spec = CollectSpec(episodes=6, steps=60, seed=0, out=out)
    collect_random(spec, overwrite=True)
    return out
