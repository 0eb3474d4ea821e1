"""A corpus of bad inputs and faults across every command (issue 18): each ends with the
documented exit code, one line on stderr, no traceback, and every file that existed before
is unchanged. Run in-process through `dlocli.cli.main` (the `dlo` entry point itself), on
real data, a real trained model and real simulators."""

from __future__ import annotations

import json
import os
import pickle
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import h5py
import numpy as np
import pytest
import torch

from tiny import (
    MUJOCO_ROD,
    built_once,
    dlo_import,
    file_digests,
    lock_held_elsewhere,
    run_dlo,
    write_cable,
)

# ----------------------------------------------------------------------------- fixtures


@pytest.fixture(scope="module")
def world(tmp_path_factory: pytest.TempPathFactory, small_dataset_dir: Path) -> dict[str, Path]:
    """Real inputs (dataset, trained model, goal, finished runs) and crafted bad files: built
    once per test session, each test process its own copy."""
    root = built_once(tmp_path_factory, "corpus", lambda to: _build_world(to, small_dataset_dir))
    names = {"data": "data", "train": "train", "goal": "goal.npy", "collect": "collect",
             "cable": "cable", "markers": "markers", "keys": "keys"}  # fmt: skip
    return {"root": root} | {key: root / name for key, name in names.items()}


def _build_world(root: Path, dataset: Path) -> None:
    shutil.copytree(dataset, root / "data")
    _dlo("train", "--data", str(root / "data"), "--epochs", "1", "--hidden", "8",
         "--out", str(root / "train"), "--json")  # fmt: skip
    _dlo("goal", "--out", str(root / "goal.npy"), "--shapes", "near-rest", "--json")
    _dlo("collect", "--episodes", "2", "--steps", "3", "--shapes", "near-rest",
         "--out", str(root / "collect"), "--json")  # fmt: skip
    bad = root / "bad"
    bad.mkdir()
    _write_bad_specs(bad)
    _write_bad_goals(bad)
    _write_bad_datasets(bad, dataset)
    _write_bad_checkpoints(bad, root / "train" / "checkpoints" / "final.pt")
    (root / "a_file").write_text("not a directory\n")
    (root / "edited").mkdir()
    write_cable(root / "cable", n_train=2, n_eval=1, frames=8)  # recordings, and their dataset
    assert dlo_import(root / "cable", root / "markers") == 0
    _dlo("keys", "--out", str(root / "keys"))
    (root / "keys" / "cell.key_secret").chmod(0o644)  # a secret others can read


def _dlo(*args: str) -> None:
    code = run_dlo(list(args))
    assert code == 0, args


def _write_bad_specs(bad: Path) -> None:
    levels = ["a: &a [x, x, x, x, x, x, x, x, x]"]
    for i, name in enumerate("bcdefgh"):
        prev = "abcdefg"[i]
        levels.append(f"{name}: &{name} [" + ", ".join([f"*{prev}"] * 9) + "]")
    (bad / "bomb.yaml").write_text("\n".join(levels) + "\nseed: [" + ", ".join(["*h"] * 9) + "]\n")
    (bad / "inf_length.yaml").write_text("backend:\n  rod:\n    length: .inf\n")
    (bad / "nan_lr.yaml").write_text("fit:\n  lr: .nan\n")
    (bad / "nan_damping.yaml").write_text("mpc:\n  damping: .nan\n")
    (bad / "inf_lr.json").write_text('{"lr": Infinity}')
    (bad / "list.yaml").write_text("- 1\n- 2\n")
    (bad / "broken.yaml").write_text("seed: [1, 2\n")
    (bad / "unknown_field.yaml").write_text("seeds: 3\n")
    (bad / "python_tag.yaml").write_text("seed: !!python/object/apply:os.system ['true']\n")
    (bad / "huge.yaml").write_text("# " + "x" * 1_100_000 + "\n")
    (bad / "bad_net_arch.yaml").write_text("options:\n  sac:\n    net_arch: [64, -1]\n")
    (bad / "bench_inf_lr.yaml").write_text("fit:\n  lr: .inf\n")
    (bad / "workspace_excludes_rest.yaml").write_text(
        "task:\n  workspace_low: [0.6, 0.4, 1.2]\n  workspace_high: [0.8, 0.6, 1.4]\n"
        "  shapes: near-rest\n"
    )


def _write_bad_goals(bad: Path) -> None:
    (bad / "empty.npy").write_bytes(b"")
    (bad / "text.npy").write_text("0.1 0.2 0.3\n")
    np.save(bad / "complex.npy", np.zeros((20, 3), dtype=complex))
    np.save(bad / "shape.npy", np.zeros((5, 3)))
    nan = np.zeros((20, 3))
    nan[3, 1] = np.nan
    np.save(bad / "nan.npy", nan)
    np.save(bad / "strings.npy", np.full((20, 3), "a"))
    np.save(bad / "objects.npy", np.array([{"a": 1}] * 3, dtype=object), allow_pickle=True)
    np.save(bad / "far.npy", np.linspace([0, 0, 0], [40, 0, 0], 20))
    (bad / "goal.txt").write_text("0 0 0\n")


def _write_bad_datasets(bad: Path, good: Path) -> None:
    (bad / "text.h5").write_text("not hdf5\n")
    with h5py.File(bad / "noformat.h5", "w") as f:
        f["positions"] = np.zeros((3, 20, 3))
    for name, change in [
        ("nan_positions.h5", lambda f: f["positions"].__setitem__((0, 0, 0), np.nan)),
        ("string_positions.h5", _positions_as_strings),
        ("missing_actions.h5", lambda f: f.__delitem__("actions")),
        ("bad_shapes.h5", _truncate_goals),
    ]:
        target = bad / name
        target.write_bytes((good / "dataset.h5").read_bytes())
        with h5py.File(target, "r+") as f:
            change(f)


def _positions_as_strings(f: h5py.File) -> None:
    shape = f["positions"].shape
    del f["positions"]
    f["positions"] = np.full(shape, b"x", dtype="S1")


def _truncate_goals(f: h5py.File) -> None:
    goals = f["goals"][()]
    del f["goals"]
    f["goals"] = goals[:1]


def _write_bad_checkpoints(bad: Path, good: Path) -> None:
    (bad / "text.pt").write_text("not a checkpoint\n")
    payload = torch.load(good, weights_only=True)
    huge = dict(payload, model_spec={**payload["model_spec"], "hidden": 10_000_000})
    torch.save(huge, bad / "huge_hidden.pt")
    nan = dict(payload)
    nan["state_dict"] = {k: v * float("nan") for k, v in payload["state_dict"].items()}
    torch.save(nan, bad / "nan_weights.pt")
    (bad / "evil.pt").write_bytes(pickle.dumps(_Evil()))
    torch.save({"format": "something else"}, bad / "other.pt")


class _Evil:
    def __reduce__(self):  # runs `touch` if anything unpickles it unsafely
        return (os.system, ("touch /tmp/dlocli_corpus_pwned",))


# ----------------------------------------------------------------------------- the corpus
# (id, argv with {placeholders}, exit code); {out} is a fresh path per case
CORPUS: list[tuple[str, str, int]] = [
    # usage errors (Click's own)
    ("no-such-command", "frobnicate", 2),
    ("no-such-flag", "train --frobnicate 1", 2),
    ("flag-not-int", "train --epochs many", 2),
    ("flag-not-float", "train --lr fast", 2),
    ("flag-missing-value", "collect --episodes", 2),
    # numbers out of range, infinite or NaN
    ("lr-inf", "train --data {data} --lr inf --out {out}", 2),
    ("lr-nan", "train --data {data} --lr nan --out {out}", 2),
    ("lr-negative", "train --data {data} --lr -1 --out {out}", 2),
    ("epochs-negative", "train --data {data} --epochs -1 --out {out}", 2),
    ("hidden-zero", "train --data {data} --hidden 0 --out {out}", 2),
    ("hidden-huge", "train --data {data} --hidden 10000000 --out {out}", 2),
    ("episodes-zero", "collect --episodes 0 --out {out}", 2),
    ("steps-zero", "collect --steps 0 --out {out}", 2),
    ("online-lr-inf", "online --lr inf --out {out}", 2),
    ("online-iters-zero", "online --iters 0 --out {out}", 2),
    ("bench-budget-tiny", "bench --budget 10 --out {out}", 2),
    # unknown names
    ("unknown-backend", "collect --backend gazebo --out {out}", 2),
    ("unknown-task", "collect --task juggle --out {out}", 2),
    ("unknown-shapes", "collect --shapes spiral --out {out}", 2),
    ("unknown-model", "train --data {data} --model transformer --out {out}", 2),
    ("unknown-controller", "control --goal {goal} --controller ppo --out {out}", 2),
    ("unknown-agent", "bench --agents sac,ppo --out {out}", 2),
    ("empty-agents", "bench --agents , --out {out}", 2),
    ("duplicate-agent", "bench --agents sac,sac --out {out}", 2),
    ("bad-control-option", "control --goal {goal} -o horizon=-3 --out {out}", 2),
    ("bad-bench-option", "bench -o sac.net_arch=[64,-1] --out {out}", 2),
    ("option-not-key-value", "bench -o sac --out {out}", 2),
    # spec files
    ("spec-missing", "train --spec {root}/nope.yaml --out {out}", 2),
    ("spec-alias-bomb", "train --spec {bad}/bomb.yaml --out {out}", 2),
    ("spec-inf-length", "collect --spec {bad}/inf_length.yaml --out {out}", 2),
    ("spec-nan-lr", "online --spec {bad}/nan_lr.yaml --out {out}", 2),
    ("spec-nan-gauss-newton-damping", "online --spec {bad}/nan_damping.yaml --out {out}", 2),
    ("motion-cost-nan", "online --motion-cost nan --out {out}", 2),
    ("motion-cost-inf", "online --motion-cost inf --out {out}", 2),
    ("motion-cost-negative", "online --motion-cost -1 --out {out}", 2),
    ("servo-cost-nan", "online --servo-cost nan --out {out}", 2),
    ("servo-cost-inf", "online --servo-cost inf --out {out}", 2),
    ("servo-cost-negative", "online --servo-cost -1 --out {out}", 2),
    ("servo-cost-huge", "online --servo-cost 1e9 --out {out}", 2),
    ("roll-search-negative", "online --roll-search -1 --out {out}", 2),
    ("roll-search-huge", "online --roll-search 1000 --out {out}", 2),
    ("roll-search-without-pull", "online --roll-search 10 --servo-cost 0 --out {out}", 2),
    ("servo-above-negative", "online --servo-above-mm -1 --out {out}", 2),
    ("servo-above-nan", "online --servo-above-mm nan --out {out}", 2),
    ("servo-above-huge", "online --servo-above-mm 1e9 --out {out}", 2),
    ("marker-online-epochs", "online --observation markers --epochs 10 --out {out}", 2),
    ("motion-cost-huge", "online --motion-cost 1e9 --out {out}", 2),
    ("motion-cost-text", "online --motion-cost abc --out {out}", 2),
    ("spec-json-infinity", "train --spec {bad}/inf_lr.json --data {data} --out {out}", 2),
    ("spec-not-mapping", "collect --spec {bad}/list.yaml --out {out}", 2),
    ("spec-broken-yaml", "collect --spec {bad}/broken.yaml --out {out}", 2),
    ("spec-unknown-field", "collect --spec {bad}/unknown_field.yaml --out {out}", 2),
    ("spec-python-tag", "collect --spec {bad}/python_tag.yaml --out {out}", 2),
    ("spec-huge-file", "collect --spec {bad}/huge.yaml --out {out}", 2),
    ("bench-spec-net-arch", "bench --spec {bad}/bad_net_arch.yaml --out {out}", 2),
    ("bench-spec-inf-lr", "bench --spec {bad}/bench_inf_lr.yaml --out {out}", 2),
    # goal files
    ("goal-missing", "control --goal {root}/nope.npy --out {out}", 2),
    ("goal-empty-file", "control --goal {bad}/empty.npy --out {out}", 2),
    ("goal-text-as-npy", "control --goal {bad}/text.npy --out {out}", 2),
    ("goal-complex", "control --goal {bad}/complex.npy --out {out}", 2),
    ("goal-wrong-shape", "control --goal {bad}/shape.npy --out {out}", 2),
    ("goal-nan", "control --goal {bad}/nan.npy --out {out}", 2),
    ("goal-strings", "control --goal {bad}/strings.npy --out {out}", 2),
    ("goal-pickled-objects", "control --goal {bad}/objects.npy --out {out}", 2),
    ("goal-unreachable", "control --goal {bad}/far.npy --out {out}", 2),
    ("goal-not-npy", "control --goal {bad}/goal.txt --out {out}", 2),
    ("no-goal", "control --out {out}", 2),
    # datasets
    ("data-missing", "train --data {root}/nope.h5 --out {out}", 2),
    ("data-none", "train --out {out}", 2),
    ("data-text-file", "train --data {bad}/text.h5 --out {out}", 2),
    ("data-no-format", "train --data {bad}/noformat.h5 --out {out}", 2),
    ("data-nan-positions", "train --data {bad}/nan_positions.h5 --out {out}", 2),
    ("data-string-positions", "train --data {bad}/string_positions.h5 --out {out}", 2),
    ("data-missing-array", "train --data {bad}/missing_actions.h5 --out {out}", 2),
    ("data-bad-shapes", "train --data {bad}/bad_shapes.h5 --out {out}", 2),
    ("eval-bad-data", "eval --checkpoint {train} --data {bad}/text.h5", 2),
    # checkpoints
    ("ckpt-missing", "control --goal {goal} --checkpoint {root}/nope.pt --out {out}", 2),
    ("ckpt-text", "control --goal {goal} --checkpoint {bad}/text.pt --out {out}", 2),
    ("device-missing", "train --data {data} --device cuda:99 --epochs 1 --out {out}", 2),
    ("ckpt-is-a-goal", "control --goal {goal} --checkpoint {goal} --out {out}", 2),
    (
        "ckpt-huge-hidden",
        "control --goal {goal} --checkpoint {bad}/huge_hidden.pt --out {out}",
        2,
    ),
    (
        "ckpt-nan-weights",
        "control --goal {goal} --checkpoint {bad}/nan_weights.pt --out {out}",
        2,
    ),
    ("ckpt-pickle", "control --goal {goal} --checkpoint {bad}/evil.pt --out {out}", 2),
    ("ckpt-other-format", "eval --checkpoint {bad}/other.pt --data {data}", 2),
    ("ckpt-run-dir-without-model", "eval --checkpoint {collect} --data {data}", 2),
    ("init-from-text", "train --data {data} --init-from {bad}/text.pt --out {out}", 2),
    # a marker model whose training cannot fit (rod models were already checked)
    (
        "train-marker-mlp-too-big",
        "train --data {markers} --model mlp --hidden 8192 --members 64 --out {out}",
        2,
    ),
    (
        "init-from-other-members",
        "train --data {data} --init-from {train} --members 3 --out {out}",
        2,
    ),
    # a goal whose workspace excludes the grippers' rest (they were pulled into the box)
    (
        "goal-workspace-excludes-rest",
        "goal --spec {bad}/workspace_excludes_rest.yaml --out {out}.npy",
        2,
    ),
    ("serve-secret-key-readable", "serve --keys {keys}", 2),
    ("control-untrained-sac", "control --goal {goal} --controller sac --out {out}", 2),
    ("control-policy-for-mpc", "control --goal {goal} --policy {root} --out {out}", 2),
    (
        "control-unused-model",
        "control --goal {goal} --controller zero --checkpoint {train} --out {out}",
        2,
    ),
    (
        "control-not-a-policy",
        "control --goal {goal} --controller td3 --policy {root}/edited --out {out}",
        2,
    ),
    # output paths
    ("out-is-file", "collect --out {root}/a_file", 2),
    ("out-not-empty", "collect --out {train}", 2),
    ("out-unwritable", "collect --out /proc/dlocli-corpus/run", 2),
    ("goal-out-is-dir", "goal --out {root}/edited", 2),
    ("goal-out-not-npy", "goal --out {out}.txt", 2),
    ("goal-out-exists", "goal --out {goal}", 2),
    ("video-bad-suffix", "control --goal {goal} --video {out}.avi --out {out}", 2),
    ("video-unwritable", "control --goal {goal} --video /proc/dlocli/v.gif --out {out}", 2),
    ("record-bad-suffix", "control --goal {goal} --record {out}.mp4 --out {out}", 2),
    ("record-unwritable", "control --goal {goal} --record /proc/dlocli/r.rrd --out {out}", 2),
    ("plot-bad-suffix", "eval --checkpoint {train} --data {data} --plot {out}.jpg", 2),
    ("plot-unwritable", "eval --checkpoint {train} --data {data} --plot /proc/x/p.png", 2),
    ("record-rod-eval", "eval --checkpoint {train} --data {data} --record {out}.rrd", 2),
    ("bench-out-is-collect-run", "bench --out {collect}", 2),
    # an --out inside a folder the command reads
    (
        "out-inside-calibrate-source",
        "calibrate --source {cable} --cable-length 1 --cable-mass 0.1 --out {cable}/fit",
        2,
    ),
    ("out-inside-import-source", "import --source {cable} --out {cable}/train/data", 2),
    (
        "out-inside-policy",
        "control --goal {goal} --controller td3 --policy {root}/edited --out {root}/edited/run",
        2,
    ),
    (
        "out-inside-cell-keys",
        "control --goal {goal} --cell tcp://127.0.0.1:1 --cell-keys {keys} --out {keys}/run",
        2,
    ),
    ("out-inside-data-run", "train --data {markers} --out {markers}/train", 2),
    # resume
    ("resume-missing-dir", "train --resume {root}/nope", 2),
    ("resume-not-a-run", "online --resume {root}/edited", 2),
    ("resume-wrong-kind", "train --resume {collect}", 2),
    ("resume-conflicting-flag", "train --resume {train} --lr 0.5", 2),
    ("resume-collect-conflict", "collect --resume {collect} --seed 5", 2),
    ("resume-bench-not-bench", "bench --resume {train}", 2),
    ("resume-with-spec", "train --resume {train} --spec {bad}/nan_lr.yaml", 2),
    ("resume-with-overwrite", "collect --resume {collect} --overwrite", 2),
    ("online-resume-with-spec", "online --resume {train} --spec {bad}/nan_lr.yaml", 2),
]


def _format(argv: str, world: dict[str, Path], out: Path) -> list[str]:
    values = {k: str(v) for k, v in world.items()} | {
        "out": str(out),
        "bad": f"{world['root']}/bad",
    }
    return [part.format(**values) for part in argv.split()]


def test_a_check_across_fields_says_what_to_change_not_the_whole_spec(tmp_path, capsys):
    """A refusal from a check across a spec's fields is its own message, without the spec it
    was given echoed after it."""
    out = tmp_path / "out"
    assert run_dlo(["online", "--observation", "markers", "--epochs", "10", "--out", str(out)]) == 2
    (line,) = capsys.readouterr().err.splitlines()
    assert "--epochs" in line and "--update-steps" in line and "{" not in line
    assert not out.exists()


def test_corpus_is_large_enough():
    assert len(CORPUS) >= 60
    assert len({case[0] for case in CORPUS}) == len(CORPUS)


@pytest.mark.parametrize(("case", "argv", "code"), CORPUS, ids=[c[0] for c in CORPUS])
def test_bad_input(case, argv, code, world, tmp_path, capsys):
    before = file_digests(world["root"], world["data"])
    exit_code = run_dlo(_format(argv, world, tmp_path / "out"))
    captured = capsys.readouterr()
    lines = captured.err.splitlines()
    assert exit_code == code, captured.err
    assert len(lines) == 1 and lines[0].startswith("error: "), captured.err  # no blank line
    assert len(lines[0]) < 600, lines[0][:200]
    assert "Traceback" not in captured.err + captured.out
    # our own whole message, not a library's advice (numpy's allow_pickle, torch's tutorial)
    assert "allow_pickle" not in lines[0] and "PyTorch 2.6" not in lines[0], lines[0]
    assert file_digests(world["root"], world["data"]) == before
    out = tmp_path / "out"
    assert not (out.is_dir() and [p.name for p in out.iterdir()] == [".dlo.lock"]), "lock left"
    assert not Path("/tmp/dlocli_corpus_pwned").exists()


# ----------------------------------------------------------------------------- faults
def test_resume_refuses_an_edited_spec_unless_accepted(world, tmp_path, capsys):
    run = tmp_path / "run"
    _dlo("train", "--data", str(world["data"]), "--epochs", "1", "--hidden", "8",
         "--out", str(run), "--json")  # fmt: skip
    spec = json.loads((run / "spec.json").read_text())
    spec["lr"] = 0.5
    (run / "spec.json").write_text(json.dumps(spec))
    capsys.readouterr()
    assert run_dlo(["train", "--resume", str(run)]) == 2
    assert "spec.json changed" in capsys.readouterr().err
    assert run_dlo(["train", "--resume", str(run), "--accept-changes", "--json"]) == 0


def test_resume_refuses_a_replaced_dataset(world, tmp_path, capsys):
    data = tmp_path / "data.h5"
    data.write_bytes((world["data"] / "dataset.h5").read_bytes())
    run = tmp_path / "run"
    _dlo("train", "--data", str(data), "--epochs", "1", "--hidden", "8", "--out", str(run),
         "--json")  # fmt: skip
    with h5py.File(data, "r+") as f:
        f["rewards"][0] = 0.0 if f["rewards"][0] != 0 else -1.0
    capsys.readouterr()
    assert run_dlo(["train", "--resume", str(run)]) == 2
    assert "data changed" in capsys.readouterr().err


def test_locked_run_directory_is_refused_naming_the_holder(world, tmp_path, capsys):
    run = tmp_path / "busy"
    _dlo("collect", "--episodes", "1", "--steps", "2", "--shapes", "near-rest",
         "--out", str(run), "--json")  # fmt: skip
    with lock_held_elsewhere(run / ".dlo.lock") as holder:
        before = file_digests(run)
        capsys.readouterr()
        model = str(world["train"] / "checkpoints" / "final.pt")
        eval_into_run = ["eval", "--checkpoint", model, "--data", str(world["data"]),
                         "--out", str(run), "--overwrite"]  # fmt: skip
        for argv in (
            ["collect", "--episodes", "1", "--steps", "2", "--out", str(run), "--overwrite"],
            ["collect", "--resume", str(run)],
            eval_into_run,
        ):
            assert run_dlo(argv) == 2
            err = capsys.readouterr().err
            assert f"PID {holder.pid}" in err and len(err.strip().splitlines()) == 1
        assert file_digests(run) == before
    # the holder died: its stale lock is taken over
    assert run_dlo(["collect", "--resume", str(run), "--json"]) == 0


def test_sigterm_saves_finished_work_and_exits_143(world, tmp_path):
    run = tmp_path / "run"
    cmd = [sys.executable, "-m", "dlocli", "train", "--data", str(world["data"]), "--hidden",
           "8", "--epochs", "500", "--out", str(run), "--json"]  # fmt: skip
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    deadline = time.monotonic() + 120
    while not (run / "checkpoints" / "last.pt").is_file() and time.monotonic() < deadline:
        time.sleep(0.2)
    proc.send_signal(signal.SIGTERM)
    out, err = proc.communicate(timeout=60)
    assert proc.returncode == 143, err.decode()
    lines = [line for line in err.decode().splitlines() if line.strip()]
    assert "Traceback" not in err.decode() and lines[-1].startswith("terminated")
    rows = (run / "metrics.csv").read_text().strip().splitlines()
    assert len(rows) >= 2  # a header and at least the finished epoch
    assert torch.load(run / "checkpoints" / "last.pt", weights_only=True)["epoch"] >= 1


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc")
def test_workers_end_when_their_parent_is_killed(tmp_path):
    # the online loop's trial workers (spawned, as issue 18's reproducer); 300-step trials
    cmd = [sys.executable, "-m", "dlocli", "online", "--iters", "1", "--trials", "2",
           "--workers", "2", "--initial-episodes", "2", "--steps", "300", "--epochs", "1",
           "--hidden", "8", "--shapes", "near-rest", "--out", str(tmp_path / "r")]  # fmt: skip
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    deadline = time.monotonic() + 120
    children: list[int] = []
    while len(children) < 3 and time.monotonic() < deadline:  # 2 workers, 1 resource tracker
        time.sleep(0.2)
        children = _children(proc.pid)
    assert len(children) >= 3, "the pool never started"
    time.sleep(5.0)  # the workers are running trials
    proc.kill()
    proc.wait()
    deadline = time.monotonic() + 20
    while any(_alive(pid) for pid in children) and time.monotonic() < deadline:
        time.sleep(0.2)
    assert not any(_alive(pid) for pid in children)


def _children(pid: int) -> list[int]:
    found = []
    for status in Path("/proc").glob("[0-9]*/status"):
        try:
            text = status.read_text()
        except OSError:
            continue
        if f"\nPPid:\t{pid}\n" in text:
            found.append(int(status.parent.name))
    return found


def _alive(pid: int) -> bool:
    try:
        state = Path(f"/proc/{pid}/status").read_text().split("State:\t")[1][0]
    except (OSError, IndexError):
        return False
    return state != "Z"


SWALLOWED_STOP = f"""
import os, signal
import dlocli
from dlocli.processes import handle_stop_signals, signal_token
handle_stop_signals()
# as the commands do: the env is handed the process's stop token
env = dlocli.make_env(backend={MUJOCO_ROD!r}, task="single", seed=0, cancel=signal_token())
env.reset()
class Destructor:
    def __del__(self):
        os.kill(os.getpid(), signal.SIGINT)
        for _ in range(100000):  # the handler runs in here: Python ignores what it raises
            pass
d = Destructor()
del d
print("swallowed", flush=True)
try:
    env.step(env.action_space.sample())
except KeyboardInterrupt:
    print("stopped at the next step", flush=True)
"""


def test_a_stop_swallowed_by_a_destructor_stops_at_the_next_step():
    # CI once sent Ctrl-C while a weakref callback ran: the collect went on for 100,000 episodes
    proc = subprocess.run(
        [sys.executable, "-c", SWALLOWED_STOP], capture_output=True, text=True, timeout=120
    )
    assert proc.stdout.split("\n")[:2] == ["swallowed", "stopped at the next step"], proc.stderr
    assert "Exception ignored" in proc.stderr  # the stop really was swallowed first


def _refuse_big_files(limit: int) -> None:
    """A subprocess's file-size limit: any write past ``limit`` bytes fails with EFBIG, as a
    full disk fails with ENOSPC (SIGXFSZ ignored, so the write returns the error). Unlike a
    small tmpfs it needs no root, so the test runs everywhere."""
    resource = pytest.importorskip("resource")
    signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
    resource.setrlimit(resource.RLIMIT_FSIZE, (limit, limit))


@pytest.mark.skipif(not hasattr(signal, "SIGXFSZ"), reason="POSIX file-size limits")
@pytest.mark.parametrize(
    "command",
    [
        # each episode file (~17 kB) fits, the assembled dataset does not
        ["collect", "--episodes", "4", "--steps", "20", "--shapes", "near-rest"],
        # the metrics fit, the checkpoint does not
        ["train", "--epochs", "1", "--hidden", "8", "--data", "{data}"],
    ],
    ids=["collect", "train"],
)
def test_a_full_disk_ends_in_one_line_and_resumes(world, tmp_path, command):
    # HDF5 and torch once wrote straight to the failing disk: tracebacks, then a segfault
    run = tmp_path / "run"
    argv = [a.format(data=world["data"]) for a in command]
    cmd = [sys.executable, "-m", "dlocli", *argv, "--out", str(run), "--json"]
    proc = subprocess.run(
        cmd,
        capture_output=True,
        text=True,
        timeout=300,
        preexec_fn=lambda: _refuse_big_files(24_000),
    )
    lines = [line for line in proc.stderr.splitlines() if line.strip()]
    assert proc.returncode == 1, proc.stderr
    assert "Traceback" not in proc.stderr and len(lines) == 1, proc.stderr
    assert lines[0].startswith("error: File too large"), lines
    assert not list(run.rglob("*.tmp")), "a partial file was left behind"
    assert not (run / "dataset.h5").exists() and not (run / "checkpoints" / "final.pt").exists()
    if command[0] == "collect":  # the finished episodes are kept; resume assembles the dataset
        assert run_dlo(["collect", "--resume", str(run), "--json"]) == 0
        assert (run / "dataset.h5").is_file()


SWALLOWED_AT_THE_END = """
import os, signal, typer
from dlocli.cli.common import handle_errors
from dlocli.processes import handle_stop_signals
handle_stop_signals()
class Destructor:
    def __del__(self):
        os.kill(os.getpid(), signal.SIGINT)
        for _ in range(100000):
            pass
@handle_errors
def command():
    d = Destructor()
    del d  # the stop lands here and is swallowed; the command then returns normally
    return "finished"
try:
    print(command(), flush=True)
except typer.Exit as exc:
    print("exit", exc.exit_code, flush=True)
"""


def test_a_stop_swallowed_in_a_command_that_then_returns_exits_130():
    proc = subprocess.run(
        [sys.executable, "-c", SWALLOWED_AT_THE_END], capture_output=True, text=True, timeout=120
    )
    assert "Exception ignored" in proc.stderr  # the stop really was swallowed
    assert proc.stdout.strip() == "exit 130", proc.stdout + proc.stderr


SIGTERM_TO_THE_WATCHER = """
import os, signal, threading, time, multiprocessing as mp
from dlocli.processes import exit_with_parent, handle_stop_signals
handle_stop_signals()  # the dlo process; the worker below is forked from it
def worker(parent):
    exit_with_parent(parent)
    watcher = next(t for t in threading.enumerate() if t.name == "exit-with-parent")
    lock = mp.get_context("fork").Lock()
    lock.acquire()
    threading.Timer(0.5, signal.pthread_kill, (watcher.ident, signal.SIGTERM)).start()
    lock.acquire()  # the main thread waits in C, as on a pool's queue lock
proc = mp.get_context("fork").Process(target=worker, args=(os.getpid(),))
proc.start()
proc.join(30)
print("alive" if proc.is_alive() else proc.exitcode, flush=True)
proc.kill()
"""


@pytest.mark.skipif(not hasattr(signal, "pthread_kill"), reason="POSIX threads")
def test_a_pool_worker_ends_on_sigterm_whichever_thread_receives_it():
    # Pool.terminate once waited forever for a collect worker: SIGTERM reached its watcher
    # thread while the main thread waited on the queue's lock, and the Python handler never ran
    proc = subprocess.run(
        [sys.executable, "-c", SIGTERM_TO_THE_WATCHER], capture_output=True, text=True, timeout=120
    )
    assert proc.stdout.strip() == str(-signal.SIGTERM), proc.stdout + proc.stderr
