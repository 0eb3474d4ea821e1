"""Shared fixtures. Tests use the real simulators and real torch models, kept small."""

from __future__ import annotations

import os

import pytest

os.environ.setdefault("MPLBACKEND", "Agg")


def pytest_configure(config: pytest.Config) -> None:
    # one torch thread per test process: `-n 2` on 2 cores runs two of them, and more threads
    # than cores only add synchronisation (the tests' models are small)
    try:
        import torch

        torch.set_num_threads(1)
    except ImportError:
        pass


@pytest.fixture(scope="module")
def one_thread():
    """One torch thread for a module whose tests compare runs or time planners (batch-1..64
    work where a second thread only adds synchronisation), whatever a test before set."""
    import torch

    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


@pytest.fixture(scope="session")
def small_dataset_dir(tmp_path_factory: pytest.TempPathFactory):
    """A small real MuJoCo single-gripper random dataset (6 episodes x 60 steps)."""
    from dlocli.runs.collect import collect_random
    from dlocli.specs import CollectSpec

    out = tmp_path_factory.mktemp("small_dataset")
    spec = CollectSpec(episodes=6, steps=60, seed=0, out=out)
    collect_random(spec, overwrite=True)
    return out


@pytest.fixture(scope="session")
def sac_policy(tmp_path_factory: pytest.TempPathFactory):
    """A tiny SAC policy directory as `dlo bench` saves it (model.zip and agent.json)."""
    from dlocli.controllers.sb3_agents import SACAgent
    from dlocli.env.shape_env import make_env
    from dlocli.specs import BackendSpec, TaskSpec

    from tiny import TINY_AGENTS

    task = TaskSpec(episode_steps=20, reset_motion_steps=10, reset_settle_steps=10)
    env = make_env(BackendSpec(), task, seed=0)
    agent = SACAgent(env, seed=0, **TINY_AGENTS["sac"])
    agent.learn(25)
    directory = tmp_path_factory.mktemp("policy")
    agent.save_policy(directory)
    env.close()
    return directory


@pytest.fixture(scope="session")
def near_rest_goal(tmp_path_factory: pytest.TempPathFactory):
    """A goal file from `dlo goal --shapes near-rest` (the default 20 segments)."""
    from tiny import run_dlo

    path = tmp_path_factory.mktemp("goal") / "goal.npy"
    assert run_dlo(["goal", "--out", str(path), "--shapes", "near-rest"]) == 0
    return path
