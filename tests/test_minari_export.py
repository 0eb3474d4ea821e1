"""`dlo export --format minari`: a real MuJoCo dataset read back with Minari, its observations
equal to the env's own, its env recovered; bad input and existing ids refused."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

import dlocli  # noqa: F401  (registers the dlocli/... Gymnasium ids recover_environment needs)
from dlocli.cli import app
from dlocli.data import Dataset, Episode, load_dataset
from dlocli.env.registration import gym_id

from tiny import MUJOCO_ROD, file_digests

minari = pytest.importorskip("minari")

runner = CliRunner()
DEFAULT_ID = f"dlocli/{MUJOCO_ROD}-single-random-v0"  # collected on the default rod


def run(*args: str):
    return runner.invoke(app, list(args))


@pytest.fixture(scope="module")
def collected(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """3 random episodes of 5 steps, single gripper, near-rest shapes (seed 0)."""
    from dlocli.runs.collect import collect_random
    from dlocli.specs import CollectSpec

    out = tmp_path_factory.mktemp("collect")
    spec = CollectSpec(
        episodes=3, seed=0, out=out, task={"episode_steps": 5, "shapes": "near-rest"}
    )
    collect_random(spec, overwrite=True)
    return out


@pytest.fixture
def minari_root(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    root = tmp_path / "minari"
    monkeypatch.setenv("MINARI_DATASETS_PATH", str(root))
    return root


def _one_error_line(res) -> str:
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in res.output, res.output
    return lines[0]


def test_export_loads_iterates_and_matches_the_env(collected, minari_root):
    from dlocli.env.rollout import stream_seed

    res = run("export", "--format", "minari", str(collected), "--json")
    assert res.exit_code == 0, res.output
    summary = json.loads(res.stdout.strip().splitlines()[-1])
    assert summary["dataset_id"] == DEFAULT_ID and summary["episodes"] == 3
    assert summary["steps"] == 15 and summary["env_id"] == gym_id(MUJOCO_ROD, "single")

    data = load_dataset(collected)
    dataset = minari.load_dataset(DEFAULT_ID)
    assert dataset.total_episodes == 3 and dataset.total_steps == 15
    n = data.n_segments
    episodes = list(dataset.iterate_episodes())
    assert [len(ep) for ep in episodes] == [5, 5, 5]
    for e, ep in enumerate(episodes):
        stored = data.episode(e)
        assert ep.observations.shape == (6, n * 3 + n * 4 + 14 + n * 3 + n * 7)
        np.testing.assert_array_equal(ep.observations[:, : n * 3], stored.positions.reshape(6, -1))
        goal = ep.observations[:, n * 7 + 14 : n * 10 + 14]
        np.testing.assert_array_equal(goal, np.tile(stored.goal.reshape(1, -1), (6, 1)))
        np.testing.assert_array_equal(ep.actions, stored.actions[:, 1, :])  # the right gripper
        np.testing.assert_array_equal(ep.rewards, stored.rewards)
        assert not ep.terminations.any() and ep.truncations.tolist() == [False] * 4 + [True]
    meta = dataset.storage.metadata["dlocli"]
    assert meta["episodes"] == [0, 1, 2] and meta["diverged_episodes"] == []

    env = dataset.recover_environment()
    try:
        assert env.observation_space == dataset.observation_space
        assert env.action_space == dataset.action_space
        # the recovered env replays episode 0 (collect's reset seed, the exported actions)
        obs, _ = env.reset(seed=stream_seed(0, 0))
        replayed = [obs] + [env.step(a)[0] for a in episodes[0].actions]
    finally:
        env.close()
    replayed = np.array(replayed)
    state = n * 10 + 14  # positions, quaternions, grippers, goal: exactly equal
    np.testing.assert_array_equal(replayed[:, :state], episodes[0].observations[:, :state])
    # velocities: recomputed from the float32 states the dataset keeps
    np.testing.assert_allclose(replayed[:, state:], episodes[0].observations[:, state:], atol=1e-4)


def test_existing_id_is_refused_unless_overwrite(collected, minari_root):
    name = "dlocli/tiny-v1"
    assert run("export", str(collected), "--dataset-id", name, "--json").exit_code == 0
    metadata = minari_root / name / "data" / "metadata.json"
    before = metadata.read_bytes()
    res = run("export", str(collected), "--dataset-id", name)
    assert res.exit_code == 2 and "--overwrite" in _one_error_line(res)
    assert metadata.read_bytes() == before
    res = run("export", str(collected), "--dataset-id", name, "--overwrite", "--json")
    assert res.exit_code == 0, res.output
    assert minari.load_dataset(name).total_steps == 15
    assert [p.name for p in minari_root.iterdir()] == ["dlocli"], "no staging left behind"


def test_a_nested_or_escaping_id_is_refused(tmp_path, collected, minari_root):
    """A dataset's folder holds its own data only; an id leads to a folder in the root."""
    assert run("export", str(collected), "--dataset-id", "dlocli/tiny-v1").exit_code == 0
    (minari_root / "notes").write_text("mine\n")
    (tmp_path / "outside").mkdir()
    (minari_root / "elsewhere").symlink_to(tmp_path / "outside")
    before = file_digests(tmp_path)
    for name, words in [("dlocli/tiny-v1/inner-v0", "inside the Minari dataset dlocli/tiny-v1"),
                        ("dlocli/tiny-v1/data/inner-v0", "like dlocli/inner-v0"),
                        ("notes/inner-v0", "is a file"),
                        ("elsewhere/inner-v0", "leads out of")]:  # fmt: skip
        res = run("export", str(collected), "--dataset-id", name)
        assert res.exit_code == 2 and words in _one_error_line(res), res.output
        assert file_digests(tmp_path) == before
    assert sorted(p.name for p in minari_root.iterdir()) == ["dlocli", "elsewhere", "notes"]
    assert not any((tmp_path / "outside").iterdir())
    assert minari.load_dataset("dlocli/tiny-v1").total_steps == 15


def test_a_relative_out_is_the_folder_it_names(tmp_path, collected, monkeypatch):
    monkeypatch.chdir(tmp_path)  # Minari joined a relative root onto itself
    res = run("export", str(collected), "--out", "datasets", "--dataset-id", "dlocli/rel-v0")
    assert res.exit_code == 0, res.output
    assert (tmp_path / "datasets" / "dlocli/rel-v0" / "data" / "metadata.json").is_file()


def test_the_earlier_flag_names_still_work_hidden(tmp_path, collected, minari_root):
    """--name and --root were renamed --dataset-id and --out (the names of the other
    commands); the old spellings still work but --help lists only the new ones."""
    res = run("export", str(collected), "--name", "dlocli/old-v0", "--root", str(tmp_path / "r"))
    assert res.exit_code == 0, res.output
    assert (tmp_path / "r" / "dlocli/old-v0" / "data" / "metadata.json").is_file()
    res = run("export", str(collected), "--dataset-id", "dlocli/a-v0", "--name", "dlocli/b-v0")
    assert res.exit_code == 2 and "--dataset-id" in _one_error_line(res)
    shown = run("export", "--help").output
    assert "--dataset-id" in shown and "--out" in shown
    assert "--name" not in shown and "--root" not in shown


def test_bad_input_exits_2_with_one_line(tmp_path, collected, minari_root):
    not_data = tmp_path / "notes.txt"
    not_data.write_text("not a dataset\n")
    res = run("export", "--format", "minari", str(not_data))
    assert res.exit_code == 2 and "re-collect" in _one_error_line(res)
    res = run("export", str(tmp_path / "missing"))
    assert res.exit_code == 2 and "dlo collect" in _one_error_line(res)
    for name in ("bad id!", "no-version"):
        res = run("export", str(collected), "--dataset-id", name)
        assert res.exit_code == 2 and "--dataset-id" in _one_error_line(res)
    res = run("export", str(collected), "--format", "parquet")
    assert res.exit_code == 2
    assert not minari_root.exists() or not any(minari_root.iterdir())


def test_diverged_and_empty_episodes(tmp_path, collected, minari_root):
    from dlocli.runs.export import export_minari

    data = load_dataset(collected)
    cut = data.episode(1)
    cut = Episode(**{**cut.__dict__, "diverged": True})
    empty = data.episode(2)
    empty = Episode(
        positions=empty.positions[:1],
        quaternions=empty.quaternions[:1],
        grippers=empty.grippers[:1],
        actions=empty.actions[:0],
        rewards=empty.rewards[:0],
        goal=empty.goal,
        diverged=True,
    )
    path = Dataset.from_episodes([data.episode(0), cut, empty], data.attrs).save(tmp_path / "d.h5")

    kept = export_minari(path, "dlocli/diverged-v0")
    assert kept["episodes"] == 2 and kept["skipped_episodes"] == 1
    assert kept["diverged_episodes"] == 1
    meta = minari.load_dataset("dlocli/diverged-v0").storage.metadata["dlocli"]
    assert meta["episodes"] == [0, 1] and meta["diverged_episodes"] == [1]
    skipped = export_minari(path, "dlocli/diverged-v1", skip_diverged=True)
    assert skipped["episodes"] == 1 and skipped["steps"] == 5


def test_bimanual_with_a_non_default_rod_is_recovered(tmp_path, minari_root):
    """12-D actions (left then right); a rod the backend's name alone does not give."""
    from minari.dataset.minari_dataset import MinariDataset

    from dlocli.runs.collect import collect_random
    from dlocli.specs import CollectSpec

    spec = CollectSpec(
        episodes=1,
        out=tmp_path / "c",
        backend={"rod": {"n_segments": 6}},
        task={"name": "bimanual", "episode_steps": 3, "shapes": "near-rest",
              "observe_velocity": False},
    )  # fmt: skip
    collect_random(spec)
    res = run("export", str(tmp_path / "c"), "--out", str(tmp_path / "elsewhere"), "--json")
    assert res.exit_code == 0, res.output
    assert not minari_root.exists(), "--out, not $MINARI_DATASETS_PATH"
    summary = json.loads(res.stdout.strip().splitlines()[-1])
    assert summary["observation_dim"] == 6 * 10 + 14 and summary["action_dim"] == 12
    assert summary["env_id"] == gym_id(MUJOCO_ROD, "bimanual")

    path = tmp_path / "elsewhere" / f"dlocli/{MUJOCO_ROD}-bimanual-random-v0" / "data"
    dataset = MinariDataset(path)
    stored = load_dataset(tmp_path / "c")
    (episode,) = dataset.iterate_episodes()
    np.testing.assert_array_equal(episode.actions, stored.actions.reshape(3, 12))
    # the registered entry point, the whole backend (its 6-segment rod) in the kwargs
    assert dataset.spec.env_spec.entry_point == "dlocli.env.shape_env:DLOShapeEnv"
    assert dataset.spec.env_spec.kwargs["backend"]["rod"]["n_segments"] == 6
    env = dataset.recover_environment()
    try:
        assert env.unwrapped.n_segments == 6
        assert env.observation_space == dataset.observation_space
        assert env.action_space == dataset.action_space
    finally:
        env.close()


def test_a_disk_too_small_is_refused_before_writing(collected, minari_root, monkeypatch):
    """HDF5 (Minari's writer) crashes the process on a full disk (a segfault after a dozen
    tracebacks, measured), so the export checks the free space first. The file system is
    shrunk by reporting it so: a real full disk needs root to make."""
    import shutil
    from collections import namedtuple

    usage = namedtuple("usage", "total used free")
    real = shutil.disk_usage
    minari_root.mkdir(parents=True)
    monkeypatch.setattr(shutil, "disk_usage", lambda p: usage(*real(p)[:2], 100_000))
    res = run("export", str(collected))
    assert res.exit_code == 1
    line = _one_error_line(res)
    assert "No space left on device" in line and "MB are free" in line, line
    assert not any(minari_root.iterdir())  # no dataset, no staging directory left
