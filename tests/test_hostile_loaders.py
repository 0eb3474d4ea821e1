"""No file a user is handed runs code when dlo loads it (issue 33): a policy zip for
`dlo control --policy`, a bench folder's checkpoints for `dlo bench --resume`. Each crafted
file holds a pickle that would create a marker file if anything unpickled it; real SB3,
PILCO and MuJoCo at tiny sizes."""

from __future__ import annotations

import base64
import json
import pickle
import shutil
import zipfile
from pathlib import Path
from typing import Any

import cloudpickle
import pytest

from dlocli.bench import jobs
from dlocli.bench.spec import BenchSpec

from tiny import TINY_AGENTS, TINY_BENCH, Payload, file_digests, run_dlo


@pytest.fixture(scope="module")
def policy(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A tiny SAC policy as `dlo bench` saves it (model.zip and agent.json)."""
    from dlocli.controllers.sb3_agents import SACAgent
    from dlocli.env.shape_env import make_env
    from dlocli.specs import BackendSpec, TaskSpec

    task = TaskSpec(episode_steps=20, reset_motion_steps=10, reset_settle_steps=10)
    env = make_env(BackendSpec(), task, seed=0)
    agent = SACAgent(env, seed=0, **TINY_AGENTS["sac"])
    agent.learn(25)
    directory = tmp_path_factory.mktemp("policy")
    agent.save_policy(directory)
    env.close()
    return directory


@pytest.fixture(scope="module")
def goal(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("goal") / "goal.npy"
    assert run_dlo(["goal", "--out", str(path), "--shapes", "near-rest"]) == 0
    return path


def _pickled(value: Any) -> dict[str, str]:
    """An entry of SB3's ``data`` as SB3 writes a cloudpickled attribute."""
    return {":type:": "<class 'object'>", ":serialized:": base64.b64encode(
        cloudpickle.dumps(value)).decode()}  # fmt: skip


def _crafted_policy(policy: Path, target: Path, edit: Any) -> Path:
    """A copy of ``policy`` whose model.zip is rewritten by ``edit(members)`` (name -> bytes)."""
    shutil.copytree(policy, target)
    with zipfile.ZipFile(policy / "model.zip") as archive:
        members = {name: archive.read(name) for name in archive.namelist()}
    edit(members)
    with zipfile.ZipFile(target / "model.zip", "w") as archive:
        for name, data in members.items():
            archive.writestr(name, data)
    return target


def _edit_data(members: dict[str, bytes], **entries: Any) -> None:
    data = json.loads(members["data"])
    data.update(entries)
    members["data"] = json.dumps(data).encode()


def _control(goal: Path, policy: Path, out: Path) -> list[str]:
    return ["control", "--goal", str(goal), "--controller", "sac", "--policy", str(policy),
            "--steps", "3", "--shapes", "near-rest", "--out", str(out)]  # fmt: skip


REFUSED = {
    # an attribute SB3 would unpickle that dlo never writes
    "unknown-pickled-entry": lambda m, marker: _edit_data(m, evil=_pickled(Payload(marker))),
    # SB3 reads tensors with torch.load(weights_only=True)
    "pickled-weights": lambda m, marker: m.update({"policy.pth": pickle.dumps(Payload(marker))}),
    "pickled-variables": lambda m, marker: m.update(
        {"pytorch_variables.pth": pickle.dumps(Payload(marker))}
    ),
}


@pytest.mark.parametrize("case", sorted(REFUSED))
def test_a_crafted_policy_is_refused_and_runs_nothing(
    case: str, policy: Path, goal: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
):
    marker = tmp_path / "pwned"
    crafted = _crafted_policy(policy, tmp_path / "policy", lambda m: REFUSED[case](m, marker))
    before = file_digests(crafted, goal.parent)
    capsys.readouterr()
    assert run_dlo(_control(goal, crafted, tmp_path / "out")) == 2
    err = capsys.readouterr().err
    lines = [line for line in err.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith("error: ") and "Traceback" not in err, err
    assert "--policy" in lines[0]
    assert not marker.exists()
    assert file_digests(crafted, goal.parent) == before


def test_pickled_entries_dlo_writes_are_never_unpickled(
    policy: Path, goal: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
):
    """SB3 pickles the policy class, spaces, schedules and the last observation: dlo takes
    them from the agent it builds instead, so crafted ones stay inert and the policy acts."""
    marker = tmp_path / "pwned"
    entries = ("policy_class", "lr_schedule", "observation_space", "action_space", "_last_obs",
               "ep_info_buffer", "train_freq", "replay_buffer_class")  # fmt: skip
    crafted = _crafted_policy(policy, tmp_path / "policy", lambda m: _edit_data(
        m, **{name: _pickled(Payload(marker)) for name in entries}))  # fmt: skip
    assert run_dlo([*_control(goal, crafted, tmp_path / "out"), "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["steps"] == 3
    assert not marker.exists()


# ----------------------------------------------------------------------------- bench resume
SPEC = BenchSpec.model_validate({k: v for k, v in TINY_BENCH.items() if k != "workers"})


class Stop(Exception):
    """Stands for the job's process being killed."""


def _stopped_job(agent: str, work: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    """Run ``agent``'s job until its third evaluation; the checkpoint slot it leaves."""
    evaluate, calls = jobs.evaluate, [0]

    def stopping(*args: Any, **kwargs: Any) -> Any:
        calls[0] += 1
        if calls[0] == 3:
            raise Stop
        return evaluate(*args, **kwargs)

    monkeypatch.setattr(jobs, "evaluate", stopping)
    with pytest.raises(Stop):
        jobs.run_job(SPEC.model_dump_json(), agent, 0, str(work))
    monkeypatch.undo()
    (slot,) = (work / jobs.RESUME_DIR).glob("point-*")
    return slot


def _plant(slot: Path, marker: Path, names: tuple[str, ...]) -> None:
    for name in names:
        (slot / name).write_bytes(pickle.dumps(Payload(marker)))


@pytest.mark.parametrize(
    ("agent", "crafted", "continued"),
    [
        # not JSON: a checkpoint that does not load starts the job again
        ("sac", ("learner.json",), False),
        ("pilco", ("generators.json",), False),
        ("pilco", ("learner.pt",), False),  # torch.load(weights_only=True)
        ("sac", ("generators.pkl", "learner.pkl"), True),  # where pickles were: never read
    ],
    ids=["sac-learner-json", "pilco-generators-json", "pilco-tensors", "sac-old-pickle-files"],
)
def test_a_crafted_bench_checkpoint_runs_nothing(
    agent: str,
    crafted: tuple[str, ...],
    continued: bool,
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
):
    marker = tmp_path / "pwned"
    slot = _stopped_job(agent, tmp_path / "job", monkeypatch)
    _plant(slot, marker, crafted)
    result = jobs.run_job(SPEC.model_dump_json(), agent, 0, str(tmp_path / "job"))
    assert not marker.exists()
    assert bool(result["resumed_at"]) == continued
    assert max(row["transitions"] for row in result["rows"]) == 60


def test_a_crafted_policy_in_a_bench_checkpoint_runs_nothing(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
):
    marker = tmp_path / "pwned"
    slot = _stopped_job("sac", tmp_path / "job", monkeypatch)
    _crafted_policy(slot, tmp_path / "crafted", lambda m: _edit_data(
        m, evil=_pickled(Payload(marker))))  # fmt: skip
    shutil.copy(tmp_path / "crafted" / "model.zip", slot / "model.zip")
    result = jobs.run_job(SPEC.model_dump_json(), "sac", 0, str(tmp_path / "job"))
    assert not marker.exists() and result["resumed_at"] == []  # refused: the job started again
