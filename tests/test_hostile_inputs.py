"""Broken and hostile input files (issue 33): damaged datasets, goals, specs and run files
end in one line naming the file, exit 2, and leave every existing file as it was."""

from __future__ import annotations

import json
import os
import pickle
import shutil
from collections.abc import Callable
from pathlib import Path

import h5py
import numpy as np
import pytest

from dlocli.bench.report import COLUMNS
from dlocli.errors import BadInput

from tiny import (
    MUJOCO_ROD,
    TINY_BENCH,
    control_with_policy,
    crafted_policy,
    edit_policy_data,
    file_digests,
    run_dlo,
    swinging_cable,
    write_cable,
)


def _set(name: str, value: Callable[[np.ndarray], np.ndarray]) -> Callable[[h5py.File], None]:
    def change(f: h5py.File) -> None:
        new = value(f[name][()])
        del f[name]
        f[name] = new

    return change


def _set_attr(name: str, value: object) -> Callable[[h5py.File], None]:
    return lambda f: f.attrs.__setitem__(name, value)


def _zero_length_episode(f: h5py.File) -> None:
    """Episode 0 shortened to no transition, its other states and actions dropped: shapes
    consistent, the length refused by itself."""
    lengths = f["episode_lengths"][()]
    t0 = int(lengths[0])
    _set("episode_lengths", lambda a: np.concatenate([[0], a[1:]]))(f)
    for name in ("positions", "quaternions", "grippers"):
        _set(name, lambda a: a[t0:])(f)
    for name in ("actions", "rewards"):
        _set(name, lambda a: a[t0:])(f)


# (id, change to a good dataset file, words the one line must hold)
DATASETS: list[tuple[str, Callable[[h5py.File], None], str]] = [
    # lengths that no longer fit the arrays are found by the shape check first
    ("zero-length", _set("episode_lengths", lambda a: np.where(np.arange(len(a)) == 0, 0, a)),
     "inconsistent array shapes"),
    ("negative-length", _set("episode_lengths", lambda a: -a), "inconsistent array shapes"),
    ("zero-length-consistent", _zero_length_episode, "episode_lengths"),
    ("rewards-rows", _set("rewards", lambda a: a[:-1]), "rewards"),
    ("diverged-rows", _set("diverged", lambda a: a[:-1]), "diverged"),
    ("gripper-columns", _set("grippers", lambda a: a[..., :6]), "grippers"),
    ("zero-quaternions", _set("quaternions", lambda a: 0 * a), "quaternions"),
    ("scaled-quaternions", _set("quaternions", lambda a: 1000 * a), "quaternions"),
    ("huge-actions", _set("actions", lambda a: 1e6 * a), "actions"),
    ("huge-positions", _set("positions", lambda a: (1e37 * a).astype(np.float32)), "positions"),
    ("format-version", _set_attr("format_version", 99), "format_version"),
    ("no-episodes", lambda f: [_set(n, lambda a: a[:0])(f) for n in
                               ("episode_lengths", "positions", "quaternions", "grippers",
                                "actions", "rewards", "goals", "diverged")],
     "no episodes"),
]  # fmt: skip


def _one_line(argv: list[str], capsys, roots: list[Path], code: int = 2) -> str:
    before = file_digests(*roots)
    exit_code = run_dlo(argv)
    err = capsys.readouterr().err
    lines = [line for line in err.splitlines() if line.strip()]
    assert exit_code == code, err
    assert len(lines) == 1 and lines[0].startswith("error: "), err
    assert len(lines[0]) < 600
    assert file_digests(*roots) == before
    return lines[0]


@pytest.mark.parametrize(("case", "change", "words"), DATASETS, ids=[c[0] for c in DATASETS])
def test_a_damaged_dataset_is_refused_on_load(
    case, change, words, small_dataset_dir, tmp_path, capsys
):
    bad = tmp_path / "dataset.h5"
    shutil.copyfile(small_dataset_dir / "dataset.h5", bad)
    with h5py.File(bad, "r+") as f:
        change(f)
    line = _one_line(["train", "--data", str(bad), "--epochs", "1", "--out",
                      str(tmp_path / "out")], capsys, [tmp_path])  # fmt: skip
    assert words in line and str(bad) in line


def test_the_good_dataset_still_loads(small_dataset_dir):
    from dlocli.data import load_dataset

    assert load_dataset(small_dataset_dir).n_episodes == 6


def _goal_npz(path: Path) -> None:
    with open(path, "wb") as f:  # np.savez to an open file keeps the .npy name
        np.savez(f, goal=np.zeros((20, 3)))


def _goal_claiming_terabytes(path: Path) -> None:
    with open(path, "wb") as f:
        np.lib.format.write_array_header_1_0(
            f, {"descr": "<f8", "fortran_order": False, "shape": (2**40 // 8, 1)}
        )


def _goal_of_huge_numbers(path: Path) -> None:
    """Finite, but their differences overflow to inf."""
    goal = np.full((20, 3), 1e308)
    goal[::2] *= -1
    np.save(path, goal)


@pytest.mark.parametrize("write", [_goal_npz, _goal_claiming_terabytes, _goal_of_huge_numbers])
def test_a_goal_that_is_not_one_small_array_is_refused(write, tmp_path, capsys):
    goal = tmp_path / "goal.npy"
    write(goal)
    line = _one_line(["control", "--goal", str(goal), "--controller", "zero", "--out",
                      str(tmp_path / "out")], capsys, [tmp_path])  # fmt: skip
    assert str(goal) in line


@pytest.mark.parametrize("suffix", [".json", ".yaml"])
def test_a_spec_nested_past_the_recursion_limit_is_refused(suffix, tmp_path, capsys):
    spec = tmp_path / f"deep{suffix}"
    depth = 100_000 if suffix == ".json" else 5_000
    spec.write_text(f'{{"seed": {"[" * depth}{"]" * depth}}}')
    line = _one_line(["goal", "--spec", str(spec), "--out", str(tmp_path / "g.npy")],
                     capsys, [tmp_path])  # fmt: skip
    assert str(spec) in line


@pytest.mark.parametrize("damage", [b"{not json", b"\xff\xfe\x00", b"[1, 2]", b'{"inputs": 3}'])
def test_damaged_fingerprints_on_resume_are_refused(damage, tmp_path, capsys):
    run = tmp_path / "run"
    assert run_dlo(["collect", "--episodes", "1", "--steps", "2", "--shapes", "near-rest",
                      "--out", str(run), "--json"]) == 0  # fmt: skip
    capsys.readouterr()
    (run / "fingerprints.json").write_bytes(damage)
    line = _one_line(["collect", "--resume", str(run)], capsys, [tmp_path])
    assert "fingerprints.json" in line


@pytest.mark.parametrize("damage", [b"{not json", b"\xff", b"[]"])
def test_a_damaged_bench_job_or_reference_file_is_refused(damage, tmp_path):
    from dlocli.errors import BadInput
    from dlocli.io import read_json

    (tmp_path / "jobs.json").write_bytes(damage)
    with pytest.raises(BadInput, match="jobs.json is damaged"):
        read_json(tmp_path / "jobs.json", dict)


def test_a_very_long_error_is_cut_to_one_short_line(tmp_path, capsys):
    long_path = tmp_path / ("x" * 5000) / "goal.npy"
    line = _one_line(["control", "--goal", str(long_path), "--controller", "zero", "--out",
                      str(tmp_path / "out")], capsys, [tmp_path])  # fmt: skip
    assert " ... " in line and line.endswith("(or read from)")


def test_json_output_of_the_damaged_files_helper_keeps_good_files(tmp_path):
    from dlocli.io import read_json

    (tmp_path / "ok.json").write_text(json.dumps({"a": 1}))
    assert read_json(tmp_path / "ok.json", dict) == {"a": 1}


# ----------------------------------------------------------------------------- names and files
#: what Python makes of a shell argument holding a byte that is not UTF-8 (a surrogate escape)
NOT_UTF8 = os.fsdecode(b"\xff")


@pytest.mark.parametrize(
    "command",
    [["goal", "--shapes", "near-rest"],
     ["collect", "--episodes", "1", "--steps", "2", "--shapes", "near-rest"]],
    ids=["goal-file", "run-directory"],
)  # fmt: skip
def test_an_output_path_that_is_not_utf8_is_refused(command, tmp_path, capsys):
    out = tmp_path / f"{NOT_UTF8}out"
    line = _one_line([*command, "--out", str(out)], capsys, [tmp_path])
    assert "not valid UTF-8" in line and "\\xffout" in line
    assert not out.exists()


@pytest.mark.parametrize(
    "content",
    [b"\xff\xfe\x00\x01" * 256,
     b"agent,seed\n\x00\x00,1\n",
     (",".join(COLUMNS) + "\n" + ",".join(["x"] * len(COLUMNS)) + "\n").encode()],
    ids=["binary", "nul-bytes", "text-for-numbers"],
)  # fmt: skip
def test_report_on_a_csv_that_is_not_bench_results_is_refused(content, tmp_path, capsys):
    (tmp_path / "results.csv").write_bytes(content)
    line = _one_line(["bench", "--report", str(tmp_path)], capsys, [tmp_path])
    assert "is not a dlo bench results.csv" in line


def _truncate_zip(policy: Path) -> None:
    zip_path = policy / "model.zip"
    zip_path.write_bytes(zip_path.read_bytes()[: zip_path.stat().st_size // 2])


def _drop_transitions(policy: Path) -> None:
    meta = json.loads((policy / "agent.json").read_text())
    del meta["transitions"]
    (policy / "agent.json").write_text(json.dumps(meta))


# (id, change to the zip's entries (name -> bytes), change to the policy folder afterwards)
BROKEN_POLICIES = [
    ("no-data-entry", lambda m: m.pop("data"), None),
    ("no-weights-entry", lambda m: m.pop("policy.pth"), None),
    ("data-not-json", lambda m: m.update(data=b"{not json"), None),
    ("data-not-utf8", lambda m: m.update(data=b"\xff\xfe\x00"), None),
    ("data-entry-of-wrong-type", lambda m: edit_policy_data(m, policy_kwargs="x"), None),
    ("weights-truncated", lambda m: m.update({"policy.pth": m["policy.pth"][:1000]}), None),
    ("zip-truncated", lambda m: None, _truncate_zip),
    ("agent-json-without-transitions", lambda m: None, _drop_transitions),
]


@pytest.mark.parametrize(("case", "edit", "after"), BROKEN_POLICIES,
                         ids=[c[0] for c in BROKEN_POLICIES])  # fmt: skip
def test_a_broken_policy_is_refused(
    case, edit, after, sac_policy, near_rest_goal, tmp_path, capsys
):
    policy = crafted_policy(sac_policy, tmp_path / "policy", edit)
    if after is not None:
        after(policy)
    argv = control_with_policy(near_rest_goal, policy, tmp_path / "out")
    line = _one_line(argv, capsys, [tmp_path, near_rest_goal.parent])
    assert f"--policy {policy}" in line


@pytest.mark.parametrize(
    ("raised", "code"),
    [(RuntimeError("the rest state diverged\n  at step 3"), 1),
     (BadInput("no such option\n  of the agent"), 2)],
    ids=["machine-failure", "bad-input"],
)  # fmt: skip
def test_a_failed_bench_job_is_one_line_naming_the_job_and_its_cause(
    raised, code, tmp_path, capsys, monkeypatch
):
    def fail(*args: object) -> None:
        raise raised

    monkeypatch.setattr("dlocli.bench.run.run_job", fail)
    spec = tmp_path / "bench.json"
    spec.write_text(json.dumps(TINY_BENCH | {"agents": ["zero"]}))
    argv = ["bench", "--spec", str(spec), "--out", str(tmp_path / "out"), "--json"]
    line = _one_line(argv, capsys, [spec], code=code)
    assert "zero-s0" in line and " ".join(str(raised).split()) in line


@pytest.mark.parametrize(
    "argv",
    [["control", "--goal", "{tmp}/missing.npy", "--controller", "zero", "--out", "{tmp}/out"],
     ["online", "--iters", "-1", "--out", "{tmp}/out"]],
    ids=["control", "online"],
)  # fmt: skip
def test_an_input_error_has_no_blank_line_before_it(argv, tmp_path, capsys):
    code = run_dlo([part.format(tmp=tmp_path) for part in argv])
    out, err = capsys.readouterr()
    assert code == 2 and out == "", out
    assert err.startswith("error: ") and err.count("\n") == 1, err


@pytest.mark.parametrize(
    "action, words",
    [(np.zeros(6, dtype=complex), "real numbers"), (np.array([object()] * 6), "real numbers"),
     (np.array(list("abcdef")), "real numbers"), (np.zeros(12), "shape"),
     (np.zeros((1, 6)), "shape"), (np.full(6, np.nan), "NaN")],
    ids=["complex", "object", "text", "too-long", "batched", "nan"],
)  # fmt: skip
def test_the_env_refuses_an_action_that_is_not_one(action, words):
    import dlocli
    from dlocli.errors import BadOption

    env = dlocli.make_env(MUJOCO_ROD, "single", seed=0, render_mode=None, episode_steps=5,
                          shapes="near-rest")  # fmt: skip
    env.reset()
    with pytest.raises(BadOption, match=words):
        env.step(action)
    env.step(np.zeros(6))  # the env is still good
    env.close()
    env.close()  # twice is fine
    for call in (lambda: env.step(np.zeros(6)), env.reset):
        with pytest.raises(BadOption, match="after close"):
            call()


@pytest.mark.parametrize(
    "argv",
    [["control", "--goal", "{loop}/goal.npy", "--controller", "zero", "--out", "{tmp}/out"],
     ["collect", "--episodes", "1", "--steps", "5", "--out", "{loop}/run"],
     ["train", "--data", "{loop}", "--out", "{tmp}/out"]],
    ids=["goal", "out", "data"],
)  # fmt: skip
def test_a_path_into_a_loop_of_links_is_one_line(argv, tmp_path, capsys):
    (tmp_path / "a").symlink_to(tmp_path / "b")
    (tmp_path / "b").symlink_to(tmp_path / "a")
    args = [a.format(loop=tmp_path / "a", tmp=tmp_path) for a in argv]
    line = _one_line(args, capsys, [tmp_path])
    assert "links loop" in line and str(tmp_path / "a") in line
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("command", ["control", "eval"])
def test_a_text_file_as_checkpoint_is_one_line(command, near_rest_goal, small_dataset_dir,
                                               tmp_path, capsys):  # fmt: skip
    text = tmp_path / "model.pt"
    text.write_text("hello\n")
    argv = {"control": ["control", "--goal", str(near_rest_goal)],
            "eval": ["eval", "--data", str(small_dataset_dir)]}[command]  # fmt: skip
    line = _one_line([*argv, "--checkpoint", str(text), "--out", str(tmp_path / "out")],
                     capsys, [tmp_path])  # fmt: skip
    assert str(text) in line and "checkpoint" in line


# ------------------------------------------------------------------ marker datasets (issue 44)
# (id, change to a good marker dataset file, words the one line must hold)
MARKER_DATASETS: list[tuple[str, Callable[[h5py.File], None], str]] = [
    ("held-indices", _set("held", lambda a: np.array([0, 1, 99, 5, 0, 0])), "held holds int64"),
    ("held-nan", _set("held", lambda a: np.where(a, 1.0, np.nan)), "held holds float64"),
    ("held-one-end", _set("held", lambda a: np.array([1, 1, 0, 0, 0, 0], bool)), "each end"),
    ("split-code", _set("split", lambda a: a + 2), "split holds [2]"),
    ("split-negative", _set("split", lambda a: a.astype(np.int8) - 1), "split holds [-1]"),
    ("split-nan", _set("split", lambda a: np.where(a == 1, np.nan, 0)), "split holds [nan]"),
    ("no-train-split", _set("split", lambda a: 1 + 0 * a), "no train episodes"),
    ("rate-zero", _set_attr("rate_hz", 0.0), "rate_hz is 0.0"),
    ("rate-negative", _set_attr("rate_hz", -100.0), "rate_hz is -100.0"),
    ("rate-nan", _set_attr("rate_hz", np.nan), "rate_hz is nan"),
    ("rate-text", _set_attr("rate_hz", "fast"), "rate_hz is fast"),
    ("positions-text", _set("positions", lambda a: a.astype("S8")), "not numbers"),
]  # fmt: skip


@pytest.mark.parametrize("command", ["train", "eval"])
@pytest.mark.parametrize(("case", "change", "words"), MARKER_DATASETS,
                         ids=[c[0] for c in MARKER_DATASETS])  # fmt: skip
def test_a_damaged_marker_dataset_is_refused_by_train_and_eval(
    command, case, change, words, marker_run, tmp_path, capsys
):
    dataset, checkpoint = marker_run
    bad = tmp_path / "dataset.h5"
    shutil.copyfile(dataset, bad)
    with h5py.File(bad, "r+") as f:
        change(f)
    argv = {"train": ["train", "--rollout-steps", "2", "--update-steps", "1"],
            "eval": ["eval", "--checkpoint", str(checkpoint)]}[command]  # fmt: skip
    line = _one_line([*argv, "--data", str(bad), "--out", str(tmp_path / "out")], capsys,
                     [tmp_path])  # fmt: skip
    assert words in line and str(bad) in line


def test_eval_refuses_a_marker_dataset_without_an_eval_split(marker_run, tmp_path, capsys):
    dataset, checkpoint = marker_run
    bad = tmp_path / "dataset.h5"
    shutil.copyfile(dataset, bad)
    with h5py.File(bad, "r+") as f:
        _set("split", lambda a: 0 * a)(f)
    line = _one_line(["eval", "--checkpoint", str(checkpoint), "--data", str(bad)], capsys,
                     [tmp_path])  # fmt: skip
    assert "no eval episodes" in line and str(bad) in line


@pytest.mark.parametrize(("scale", "words"), [(0.0, "position_scale holds [0.0"),
                                             (-1.0, "position_scale holds [-1.0"),
                                             (float("inf"), "NaN or inf weights")])  # fmt: skip
def test_a_marker_checkpoint_with_a_scale_not_positive_is_refused(
    scale, words, marker_run, tmp_path, capsys
):
    import torch

    dataset, checkpoint = marker_run
    payload = torch.load(checkpoint, weights_only=True)
    payload["state_dict"]["position_scale"] = torch.full((3,), scale)
    bad = tmp_path / "model.pt"
    torch.save(payload, bad)
    line = _one_line(["eval", "--checkpoint", str(bad), "--data", str(dataset)], capsys,
                     [tmp_path])  # fmt: skip
    assert words in line and str(bad) in line


def test_a_text_file_as_a_marker_checkpoint_is_one_line(marker_run, tmp_path, capsys):
    text = tmp_path / "model.pt"
    text.write_text("hello\n")
    line = _one_line(["eval", "--checkpoint", str(text), "--data", str(marker_run[0])], capsys,
                     [tmp_path])  # fmt: skip
    assert f"{text} is not a readable model checkpoint" in line


def test_the_good_marker_dataset_evaluates(marker_run, tmp_path, capsys):
    dataset, checkpoint = marker_run
    assert run_dlo(["eval", "--checkpoint", str(checkpoint), "--data", str(dataset)]) == 0


# ----------------------------------------------------------------------- recordings (issue 44)
def _fifo(root: Path) -> str:
    os.mkfifo(root / "train" / "x.pkl")  # opened for reading, it would wait for a writer
    return "not a regular file"


def _name_not_utf8(root: Path) -> str:
    shutil.copyfile(root / "train" / "0.pkl", root / "train" / f"a{NOT_UTF8}.pkl")
    return "a\\xff.pkl: the file name is not valid UTF-8"


def _millimetres(root: Path) -> str:
    (root / "train" / "0.pkl").write_bytes(pickle.dumps((1000 * swinging_cable(0)).tolist()))
    return "pass --units"


def _int_beyond_float(root: Path) -> str:
    (root / "train" / "0.pkl").write_bytes(pickle.dumps([[[10**400] * 6] * 3] * 5))
    return "too large for a float"


@pytest.mark.parametrize("damage", [_fifo, _name_not_utf8, _millimetres, _int_beyond_float])
def test_a_recording_that_is_not_one_is_refused_by_import(damage, tmp_path, capsys):
    root = write_cable(tmp_path / "CABLE", n_train=1, n_eval=0, frames=5)
    words = damage(root)
    line = _one_line(["import", "--source", str(root), "--out", str(tmp_path / "out")], capsys,
                     [tmp_path])  # fmt: skip
    assert words in line
    assert not (tmp_path / "out").exists()


def test_a_millimetre_recording_imports_in_metres_when_told(tmp_path, capsys):
    root = write_cable(tmp_path / "CABLE", n_train=1, n_eval=0, frames=5)
    _millimetres(root)
    out = tmp_path / "out"
    assert run_dlo(["import", "--source", str(root), "--units", "mm", "--out", str(out)]) == 0
    from dlocli.data import load_dataset

    np.testing.assert_allclose(load_dataset(out).episodes()[0][0], swinging_cable(0)[0].T,
                               atol=1e-6)  # fmt: skip


@pytest.mark.parametrize("out", ["CABLE/train/out", "CABLE", "."], ids=["inside", "same", "above"])
def test_import_refuses_an_out_by_its_source(out, tmp_path, capsys):
    root = write_cable(tmp_path / "CABLE", n_train=1, n_eval=0, frames=5)
    line = _one_line(["import", "--source", str(root), "--out", str(tmp_path / out)], capsys,
                     [tmp_path])  # fmt: skip
    assert "apart from the recordings" in line


# ------------------------------------------------------------------------- resumes (issue 44)
def _saved_run(tmp_path: Path, command: str) -> Path:
    """A run directory holding only the spec.json a fresh `dlo COMMAND` would save."""
    from dlocli.calibration.spec import CalibrateSpec
    from dlocli.runs.online import OnlineSpec

    run = tmp_path / "run"
    run.mkdir()
    if command == "calibrate":
        source = write_cable(tmp_path / "CABLE", n_train=2, n_eval=1, frames=5)
        spec = CalibrateSpec(source=source, cable_length=1.0, cable_mass=0.1, out=run)
    else:
        spec = OnlineSpec(out=run)
    (run / "spec.json").write_text(json.dumps(spec.model_dump(mode="json")))
    return run


@pytest.mark.parametrize(
    ("command", "flags", "words"),
    [("calibrate", ["--generations", "0"], "field 'generations'"),
     ("calibrate", ["--workers", "1000"], "field 'workers'"),
     ("online", ["--workers", "1000"], "field 'workers'"),
     ("online", ["--executor", "nosuch"], "field 'executor'")],
    ids=["calibrate-generations", "calibrate-workers", "online-workers", "online-executor"],
)  # fmt: skip
def test_flags_a_resume_takes_are_checked_as_a_fresh_run_checks_them(
    command, flags, words, tmp_path, capsys
):
    run = _saved_run(tmp_path, command)
    line = _one_line([command, "--resume", str(run), *flags], capsys, [tmp_path])
    assert words in line and f"--resume {run}" in line


def _generation(candidates: object, scores: object) -> dict[str, object]:
    return {"generations": [{"candidates": candidates, "scores": scores}]}


# (id, history.json content, words) for a run of population 8 fitting 3 parameters
DAMAGED_HISTORIES = [
    ("scores-short", _generation([[0.5] * 3] * 8, [1.0] * 3), "3 scores, not 8"),
    ("scores-text", _generation([[0.5] * 3] * 8, ["1.0"] * 8), "generations.0.scores.0"),
    ("candidate-short", _generation([[0.5] * 2] * 8, [1.0] * 8), "not 8 of 3 parameters"),
    ("generations-number", {"generations": 3}, "field 'generations'"),
    ("seconds-text", {"seconds": "soon"}, "field 'seconds'"),
    ("scores-true", _generation([[0.5] * 3] * 8, [True] * 8), "generations.0.scores.0"),
]


@pytest.mark.parametrize(("case", "history", "words"), DAMAGED_HISTORIES,
                         ids=[c[0] for c in DAMAGED_HISTORIES])  # fmt: skip
def test_a_damaged_calibration_history_is_refused_on_resume(case, history, words, tmp_path, capsys):
    run = _saved_run(tmp_path, "calibrate")
    (run / "history.json").write_text(json.dumps(history))
    line = _one_line(["calibrate", "--resume", str(run)], capsys, [tmp_path])
    assert words in line and "history.json" in line


# --------------------------------------------------------------------- strict specs (issue 44)
STRICT_SPECS = [
    ("goal", "seed: true", "field 'seed': Value error, a boolean where a number belongs"),
    ("goal", "task: {episode_steps: false}", "field 'task.episode_steps': Value error, a boolean"),
    ("collect", "steps: 5", "field 'steps' is retired; write it as 'task.episode_steps'"),
    ("train", "model: {name: mlp, mlp_hidden: 64}", "'model.mlp_hidden' is retired; write it as "
     "'model.hidden'"),
    ("train", "model: {name: mlp, lstm_layers: 3}", "unknown field 'model.lstm_layers'"),
    ("train", "schedule: steps", "field 'schedule' is retired (an update field of the online"),
    ("train", "episode_steps: 5", "unknown field 'episode_steps'"),
]  # fmt: skip


@pytest.mark.parametrize(("command", "text", "words"), STRICT_SPECS,
                         ids=[f"{c}-{t.split(':')[0]}-{i}" for i, (c, t, _) in
                              enumerate(STRICT_SPECS)])  # fmt: skip
def test_a_spec_with_a_retired_misplaced_or_boolean_field_is_refused(
    command, text, words, tmp_path, capsys
):
    spec = tmp_path / "spec.yaml"
    spec.write_text(text + "\n")
    inputs = {"train": ["--data", str(tmp_path / "data")]}.get(command, [])
    line = _one_line([command, "--spec", str(spec), *inputs, "--out", str(tmp_path / "out")],
                     capsys, [tmp_path])  # fmt: skip
    assert words in line and str(spec) in line


def test_a_runs_own_spec_json_still_reads_its_older_layout(tmp_path):
    """`--spec RUN/spec.json` re-runs a run: the layout its version saved is migrated."""
    from dlocli.models.spec import TrainSpec
    from dlocli.specs import resolve_spec

    saved = tmp_path / "spec.json"
    saved.write_text(json.dumps({"model": {"name": "mlp", "mlp_hidden": 64, "lstm_layers": 2},
                                 "schedule": "epochs"}))  # fmt: skip
    assert resolve_spec(TrainSpec, saved).model.hidden == 64


# ----------------------------------------------------------------------- bench (issue 44)
@pytest.mark.parametrize("option", ["sac.ent_coef=-5", "sac.ent_coef=auto_x", "sac.ent_coef=true"])
def test_a_bad_agent_option_is_refused_before_any_job_runs(option, tmp_path, capsys):
    spec = tmp_path / "bench.json"
    spec.write_text(json.dumps(TINY_BENCH | {"agents": ["zero", "sac"]}))
    line = _one_line(["bench", "--spec", str(spec), "-o", option, "--out", str(tmp_path / "out")],
                     capsys, [tmp_path])  # fmt: skip
    assert "field 'ent_coef'" in line
    assert not (tmp_path / "out").exists()


def test_a_failed_bench_job_is_one_line_in_the_log_too(tmp_path, capsys, monkeypatch):
    def fail(*args: object) -> None:
        raise RuntimeError("the rest state diverged\n  at step 3")

    monkeypatch.setattr("dlocli.bench.run.run_job", fail)
    spec = tmp_path / "bench.json"
    spec.write_text(json.dumps(TINY_BENCH | {"agents": ["zero"]}))
    assert run_dlo(["bench", "--spec", str(spec), "--out", str(tmp_path / "out")]) == 1
    out, err = capsys.readouterr()
    logged = [line for line in out.splitlines() if "zero-s0" in line]
    assert len(logged) == 1 and "zero-s0 failed: RuntimeError: the rest state" in logged[0], out
    assert err.count("\n") == 1 and "zero-s0" in err, err


# ----------------------------------------------------------------------- Gymnasium (issue 44)
@pytest.mark.parametrize("make", ["dlocli", "gymnasium"])
def test_a_render_mode_the_env_cannot_provide_is_refused_at_construction(make):
    """gym.make would wrap it in HumanRendering, a window that fails without a display."""
    import gymnasium as gym

    import dlocli
    from dlocli.env.registration import gym_id
    from dlocli.errors import BadOption

    single = gym_id(MUJOCO_ROD, "single")
    build = {"dlocli": lambda **kw: dlocli.make_env(MUJOCO_ROD, "single", **kw),
             "gymnasium": lambda **kw: gym.make(single, **kw)}[make]  # fmt: skip
    with pytest.raises(BadOption, match="render_mode .* got 'human'"):
        build(render_mode="human", shapes="near-rest")
