"""No file a user is handed runs code when dlo loads it (issue 33): a policy zip for
`dlo control --policy`, a bench folder's checkpoints for `dlo bench --resume`. Each crafted
file holds a pickle that would create a marker file if anything unpickled it; real SB3,
PILCO and MuJoCo at tiny sizes."""

from __future__ import annotations

import base64
import json
import pickle
import shutil
from pathlib import Path
from typing import Any

import cloudpickle
import pytest

from dlocli.bench import jobs
from dlocli.bench.spec import BenchSpec

from tiny import (
    TINY_BENCH,
    Payload,
    control_with_policy,
    crafted_policy,
    edit_policy_data,
    file_digests,
    run_dlo,
)


def _pickled(value: Any) -> dict[str, str]:
    """An entry of SB3's ``data`` as SB3 writes a cloudpickled attribute."""
    return {":type:": "<class 'object'>", ":serialized:": base64.b64encode(
        cloudpickle.dumps(value)).decode()}  # fmt: skip


REFUSED = {
    # an attribute SB3 would unpickle that dlo never writes
    "unknown-pickled-entry": lambda m, marker: edit_policy_data(m, evil=_pickled(Payload(marker))),
    # SB3 reads tensors with torch.load(weights_only=True)
    "pickled-weights": lambda m, marker: m.update({"policy.pth": pickle.dumps(Payload(marker))}),
    "pickled-variables": lambda m, marker: m.update(
        {"pytorch_variables.pth": pickle.dumps(Payload(marker))}
    ),
}


@pytest.mark.parametrize("case", sorted(REFUSED))
def test_a_crafted_policy_is_refused_and_runs_nothing(
    case: str,
    sac_policy: Path,
    near_rest_goal: Path,
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
):
    marker = tmp_path / "pwned"
    crafted = crafted_policy(sac_policy, tmp_path / "policy", lambda m: REFUSED[case](m, marker))
    before = file_digests(crafted, near_rest_goal.parent)
    capsys.readouterr()
    assert run_dlo(control_with_policy(near_rest_goal, crafted, tmp_path / "out")) == 2
    err = capsys.readouterr().err
    lines = [line for line in err.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith("error: ") and "Traceback" not in err, err
    assert "--policy" in lines[0]
    assert not marker.exists()
    assert file_digests(crafted, near_rest_goal.parent) == before


def test_pickled_entries_dlo_writes_are_never_unpickled(
    sac_policy: Path, near_rest_goal: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
):
    """SB3 pickles the policy class, spaces, schedules and the last observation: dlo takes
    them from the agent it builds instead, so crafted ones stay inert and the policy acts."""
    marker = tmp_path / "pwned"
    entries = ("policy_class", "lr_schedule", "observation_space", "action_space", "_last_obs",
               "ep_info_buffer", "train_freq", "replay_buffer_class")  # fmt: skip
    crafted = crafted_policy(sac_policy, tmp_path / "policy", lambda m: edit_policy_data(
        m, **{name: _pickled(Payload(marker)) for name in entries}))  # fmt: skip
    assert run_dlo([*control_with_policy(near_rest_goal, crafted, tmp_path / "out"), "--json"]) == 0
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
    crafted_policy(slot, tmp_path / "crafted", lambda m: edit_policy_data(
        m, evil=_pickled(Payload(marker))))  # fmt: skip
    shutil.copy(tmp_path / "crafted" / "model.zip", slot / "model.zip")
    result = jobs.run_job(SPEC.model_dump_json(), "sac", 0, str(tmp_path / "job"))
    assert not marker.exists() and result["resumed_at"] == []  # refused: the job started again
