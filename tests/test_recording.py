"""`--record RUN.rrd`: a run's 3D recording, read back with Rerun's own API.

Real `dlo control` runs (MuJoCo, a real if untrained torch model for the planner); the
recordings are read by Rerun: its local server and catalog client (the ``catalog`` extra of
rerun-sdk, in the test extra) and its RRD reader (the ``view`` extra alone).
"""

from __future__ import annotations

import csv
import json
import subprocess
import sys
from collections import Counter
from pathlib import Path

import pytest

from tiny import run_dlo

rr = pytest.importorskip("rerun", reason="the 'view' extra (rerun-sdk) is not installed")

#: what every recorded control run holds, whatever its observation and controller
ALWAYS = {"/world/rod", "/world/goal", "/world/grippers", "/world/workspace",
          "/metrics/shape_error_mm", "/metrics/reward", "/envelope/clipped"}  # fmt: skip
MARKERS = {"/world/markers/seen", "/world/markers/hidden"}
PLAN = {"/world/plan/grippers", "/world/plan/predicted"}


def metrics_of(run: Path) -> list[dict[str, str]]:
    with open(run / "metrics.csv", newline="") as f:
        return list(csv.DictReader(f))


def test_a_recorded_run_reads_back_through_the_catalog(near_rest_goal: Path, tmp_path: Path):
    """Markers with occlusions and a speed limit: the recording's entities, one frame per
    step on the `step` timeline, and its values equal the run's metrics.csv and summary."""
    pytest.importorskip("datafusion", reason="rerun-sdk[catalog] reads datasets")
    recording, run = tmp_path / "run.rrd", tmp_path / "run"
    argv = ["control", "--goal", str(near_rest_goal), "--controller", "random", "--steps", "12",
            "--shapes", "near-rest", "--observation", "markers", "--occlusion-probability",
            "0.5", "--max-linear-speed", "0.02", "--record", str(recording), "--out", str(run),
            "--json"]  # fmt: skip
    assert run_dlo(argv) == 0
    metrics = metrics_of(run)
    summary = json.loads((run / "summary.json").read_text())
    assert summary["recording"] == str(recording)
    assert json.loads((run / "spec.json").read_text())["record"] == str(recording)

    with rr.server.Server(host="127.0.0.1", datasets={"run": [recording]}) as server:
        client = server.client()  # held: the reader runs through it
        dataset = client.get_dataset("run")
        table = dataset.reader(index="step").to_arrow_table()
    entities = {name.split(":")[0] for name in table.column_names if name.startswith("/")}
    assert entities >= ALWAYS | MARKERS
    assert not entities & PLAN  # a random controller plans nothing

    rows = dict(zip(table.column("step").to_pylist(), range(table.num_rows), strict=True))
    assert sorted(rows) == list(range(len(metrics) + 1))  # the reset, then every step

    def values(column: str) -> dict[int, object]:
        found = table.column(column).to_pylist()
        return {step: found[row] for step, row in rows.items() if found[row] is not None}

    assert len(values("/world/rod:LineStrips3D:strips")) == len(metrics) + 1
    assert len(values("/world/markers/seen:Points3D:positions")) == len(metrics)
    errors = values("/metrics/shape_error_mm:Scalars:scalars")
    assert sorted(errors) == [int(m["step"]) for m in metrics]
    for m in metrics:  # float32 in the recording
        assert errors[int(m["step"])][0] == pytest.approx(float(m["shape_error_mm"]), rel=1e-6)
    clipped = values("/envelope/clipped:Scalars:scalars")[len(metrics)]
    assert clipped[1] == summary["clipped_speed"] > 0  # the counts' order: envelope.LIMITS
    seen = values("/world/markers/seen:Points3D:positions")
    hidden = values("/world/markers/hidden:Points3D:positions")
    counts = Counter(len(seen[s]) + len(hidden.get(s) or []) for s in seen)
    assert len(counts) == 1  # every marker, seen or hidden, at every observed step
    assert any(hidden.get(s) for s in seen), "the occlusions hid no marker: a vacuous check"


def test_a_planner_run_records_its_plan_in_chunks(near_rest_goal: Path, tmp_path: Path):
    """The gradient MPC through a (tiny, untrained) model: its planned gripper path and
    predicted shapes at each re-plan, read with Rerun's RRD reader (the 'view' extra only)."""
    import torch

    from dlocli.models import build_model, save_checkpoint
    from dlocli.models.spec import model_spec

    torch.manual_seed(0)
    tiny = model_spec({"hidden": 8, "edge_layers": 1, "node_layers": 1, "lstm_layers": 1})
    checkpoint = save_checkpoint(build_model(tiny, 20), tmp_path / "tiny.pt")
    recording, run = tmp_path / "plan.rrd", tmp_path / "run"
    argv = ["control", "--goal", str(near_rest_goal), "--checkpoint", str(checkpoint),
            "--steps", "5", "--shapes", "near-rest", "-o", "iterations=1", "-o",
            "replan_every=2", "-o", "horizon=4", "--record", str(recording), "--out", str(run),
            "--json"]  # fmt: skip
    assert run_dlo(argv) == 0
    metrics = metrics_of(run)
    replans = [int(m["step"]) - 1 for m in metrics if float(m["replanned"]) == 1.0]
    assert replans == [0, 2, 4]  # the plan made from the observation of each step

    from rerun.chunk import RrdReader

    steps: dict[str, list[int]] = {}
    sizes: dict[str, list[int]] = {}
    for chunk in RrdReader(recording).stream().to_chunks():
        if chunk.is_static:
            continue
        batch = chunk.to_record_batch()
        steps.setdefault(chunk.entity_path, []).extend(batch.column("step").to_pylist())
        data = [c for c in batch.column_names if c.endswith(("strips", "scalars"))]
        if data:
            sizes.setdefault(chunk.entity_path, []).extend(
                len(row) for row in batch.column(data[0]).to_pylist()
            )
    assert set(steps) >= ALWAYS - {"/world/workspace"} | PLAN
    assert not set(steps) & MARKERS  # the full observation: no markers
    assert sorted(steps["/world/rod"]) == list(range(len(metrics) + 1))
    assert sorted(steps["/world/plan/predicted"]) == replans
    assert set(sizes["/world/plan/predicted"]) == {4}  # one predicted shape per horizon step
    assert set(sizes["/world/plan/grippers"]) == {1}  # the single task moves one gripper


def test_an_unwritable_recording_is_refused_before_the_run(near_rest_goal: Path, tmp_path: Path):
    """One line, exit 2, nothing written: a directory, a wrong suffix, an existing file."""
    existing = tmp_path / "old.rrd"
    existing.write_bytes(b"kept")
    (tmp_path / "dir.rrd").mkdir()
    for path, says in ((tmp_path / "dir.rrd", "is a directory"),
                       (tmp_path / "run.mp4", "must end in .rrd"),
                       (existing, "exists; pass --overwrite")):  # fmt: skip
        out = tmp_path / "out"
        result = subprocess.run(
            [sys.executable, "-m", "dlocli", "control", "--goal", str(near_rest_goal),
             "--controller", "zero", "--record", str(path), "--out", str(out)],
            capture_output=True, text=True, timeout=120,
        )  # fmt: skip
        assert result.returncode == 2, result.stderr
        lines = result.stderr.strip().splitlines()
        assert len(lines) == 1 and says in lines[0] and "--record" in lines[0], result.stderr
        assert not out.exists()
    assert existing.read_bytes() == b"kept"


@pytest.mark.parametrize(("flag", "name"), [("--record", "x.rrd"), ("--video", "x.gif")])
@pytest.mark.parametrize("holds_out", [False, True])
def test_a_recording_or_video_at_the_run_directory_is_refused_before_the_run(
    flag: str, name: str, holds_out: bool, near_rest_goal: Path, tmp_path: Path, capsys
):
    """`--out C/x.rrd --record C/x.rrd` (or a --video, or an --out inside it) would run every
    step, then fail writing the file where the run directory is: refused first, one line,
    exit 2, nothing written."""
    path = tmp_path / "C" / name
    out = path / "run" if holds_out else path
    code = run_dlo(["control", "--goal", str(near_rest_goal), "--controller", "zero",
                    flag, str(path), "--out", str(out)])  # fmt: skip
    lines = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(lines) == 1, lines
    assert f"{flag} {path} is where --out" in lines[0] and f"another {flag}" in lines[0], lines
    assert not (tmp_path / "C").exists()


@pytest.mark.parametrize("saved", ["dataset.h5", "data/iter_01/trial_001.h5"])
def test_view_writes_a_runs_recording_from_its_episodes_and_says_where_it_is(
    saved: str, small_dataset_dir: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
):
    """`dlo view` on a run of saved episodes (a collect run's dataset, an online run's
    trials) writes RUN/recording.rrd, one frame per saved state with the datasets' own
    errors; with no display it says where, in one line."""
    import shutil

    import numpy as np
    from rerun.chunk import RrdReader

    from dlocli.data import load_dataset
    from dlocli.env.metrics import shape_error_mm

    run = tmp_path / "run"
    (run / saved).parent.mkdir(parents=True)
    shutil.copy(small_dataset_dir / "dataset.h5", run / saved)
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    result = subprocess.run([sys.executable, "-m", "dlocli", "view", str(run)],
                            capture_output=True, text=True, timeout=120)  # fmt: skip
    assert result.returncode == 0, result.stderr
    lines = result.stdout.strip().splitlines()
    assert len(lines) == 1 and f"the recording is {run / 'recording.rrd'}" in lines[0]

    dataset = load_dataset(run / saved)
    first = dataset.episode(0)
    rows: dict[str, list] = {}
    for chunk in RrdReader(run / "recording.rrd").stream().to_chunks():
        batch = chunk.to_record_batch()
        for column in batch.column_names:
            if not chunk.is_static and column.endswith(("strips", "scalars")):
                steps = batch.column("step").to_pylist()
                values = batch.column(column).to_pylist()
                rows.setdefault(chunk.entity_path, []).extend(zip(steps, values, strict=True))
    assert len(rows["/world/rod"]) == sum(len(dataset.episode(e)) + 1 for e in range(6))
    errors = dict(rows["/metrics/shape_error_mm"])
    expected = shape_error_mm(first.positions[len(first)], first.goal)
    assert np.isclose(errors[len(first)][0], expected, rtol=1e-6)


def test_view_without_the_extra_is_one_line(tmp_path: Path):
    """Rerun hidden (as if never installed): `dlo view` names the extra, exit 2, writes nothing."""
    program = ("import sys; sys.modules['rerun'] = None\n"
               f"sys.argv = ['dlo', 'view', {str(tmp_path)!r}]\n"
               "from dlocli.cli import main; main()\n")  # fmt: skip
    result = subprocess.run([sys.executable, "-c", program], capture_output=True, text=True,
                            timeout=120)  # fmt: skip
    assert result.returncode == 2, result.stderr
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and "-e '.[view]'" in lines[0], result.stderr
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize(
    ("content", "says"), [(b"", "is empty"), (b"not a recording\n", "not a Rerun recording")]
)
def test_view_refuses_a_file_that_is_not_a_recording_in_one_line(
    content: bytes, says: str, tmp_path: Path, capsys: pytest.CaptureFixture
):
    """A text or empty file named .rrd: one line naming the file and what to pass, exit 2,
    the file kept."""
    fake = tmp_path / "x.rrd"
    fake.write_bytes(content)
    assert run_dlo(["view", str(fake)]) == 2
    lines = capsys.readouterr().err.strip().splitlines()
    assert len(lines) == 1 and str(fake) in lines[0] and says in lines[0], lines
    assert "--record" in lines[0]
    assert fake.read_bytes() == content


def test_eval_records_recorded_markers_beside_the_prediction(marker_run, tmp_path: Path):
    """`dlo eval --record` on a marker dataset: each eval trajectory and the model's open-loop
    prediction, frame by frame, whose free markers' error is the run's error_by_frame.json."""
    import numpy as np
    from rerun.chunk import RrdReader

    from dlocli.data import load_dataset

    data, checkpoint = marker_run
    recording, out = tmp_path / "eval.rrd", tmp_path / "eval"
    argv = ["eval", "--checkpoint", str(checkpoint), "--data", str(data), "--record",
            str(recording), "--out", str(out), "--json"]  # fmt: skip
    assert run_dlo(argv) == 0
    episodes = load_dataset(data).episodes("eval")
    rows: dict[str, dict[int, list]] = {}
    for chunk in RrdReader(recording).stream().to_chunks():
        batch = chunk.to_record_batch()
        for column in batch.column_names:
            if not chunk.is_static and column.endswith(("strips", "scalars")):
                steps, values = batch.column("step").to_pylist(), batch.column(column).to_pylist()
                rows.setdefault(chunk.entity_path, {}).update(zip(steps, values, strict=True))
    frames = sum(len(e) for e in episodes)
    assert sorted(rows["/world/recorded"]) == list(range(frames))
    assert sorted(rows["/world/predicted"]) == list(range(frames))
    second = len(episodes[0])  # the second trajectory's first frame
    assert np.allclose(rows["/world/recorded"][second][0], episodes[1][0], atol=1e-6)
    errors = np.array([rows["/metrics/prediction_error_mm"][t][0] for t in range(frames)])
    by_frame = np.mean([errors[:second], errors[second:]], axis=0)
    curves = json.loads((out / "error_by_frame.json").read_text())["free_error_mm"]["model"]
    assert np.allclose(by_frame, curves, atol=2e-3)  # the curve is rounded to 1e-3 mm
    assert by_frame[0] == by_frame[1] == 0.0 and by_frame[-1] > 0.0  # frames 0-1 are given
