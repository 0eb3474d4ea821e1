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


@pytest.fixture(scope="session")
def marker_run(tmp_path_factory: pytest.TempPathFactory):
    """A tiny marker dataset (4 train and 2 eval recordings of 6 markers, 12 frames) and an
    untrained marker model fitted to its scales: ``(dataset.h5, checkpoint.pt)``."""
    import numpy as np

    from dlocli.data import MarkerDataset
    from dlocli.models.checkpoints import save_checkpoint
    from dlocli.models.marker_model import build_marker_model
    from dlocli.recorded_cables.deform import held_markers

    rng = np.random.default_rng(0)
    line = np.stack([np.linspace(0, 0.8, 6), np.zeros(6), np.full(6, 0.5)], -1)

    def recording() -> np.ndarray:
        return line + np.cumsum(rng.normal(0, 1e-3, (12, 6, 3)), 0)

    held = held_markers(6)
    data = MarkerDataset.from_trajectories(
        {s: [(str(i), recording()) for i in range(n)] for s, n in (("train", 4), ("eval", 2))},
        held, {"rate_hz": 100.0},
    )  # fmt: skip
    root = tmp_path_factory.mktemp("markers")
    model = build_marker_model({"name": "in-bilstm", "hidden": 8}, 6, held)
    model.fit_normalization([(e, held) for e in data.episodes("train")])
    save_checkpoint(model, root / "model.pt")  # tagged with the model's form
    return data.save(root / "dataset.h5"), root / "model.pt"


@pytest.fixture(scope="session")
def deform_reference(tmp_path_factory: pytest.TempPathFactory):
    """tiny.write_cable's recordings (3 train, 2 eval) imported from DEFORM pickles: the
    dataset every other format of the same recordings must give."""
    from dlocli.data import load_dataset

    from tiny import dlo_import, write_cable

    root = tmp_path_factory.mktemp("deform")
    write_cable(root / "CABLE", n_train=3, n_eval=2)
    assert dlo_import(root / "CABLE", root / "out") == 0
    return load_dataset(root / "out")


@pytest.fixture(scope="module")
def cluster():
    """One local Ray instance of 2 CPUs for the module (starting one takes seconds); the runs
    in this process join it at its address, which the fixture gives."""
    ray = pytest.importorskip("ray")
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
    try:
        yield ray.get_runtime_context().gcs_address
    finally:
        ray.shutdown()
