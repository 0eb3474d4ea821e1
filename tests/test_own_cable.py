"""docs/own_cable.md runs as written: its `dlo` lines, read from the page itself, on the
cable its first line simulates (`dlo sample`: a motion-capture CSV in mm at 120 Hz), with only
their counts cut, end to end: import, calibrate, train, evaluate, a served cell and control
through it; for a cable held by one marker at each end, as the page's line says, and by two
(DEFORM's layout)."""

from __future__ import annotations

import json
import re
import shlex
import signal
import socket
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
import yaml

from dlocli.data import load_dataset

from tiny import run_dlo

pytest.importorskip("cma")
pytest.importorskip("zmq")

ROOT = Path(__file__).resolve().parents[1]
PAGE = ROOT / "docs" / "own_cable.md"
MARKERS, RATE_HZ = 6, 120.0
#: flags each command gets on top of the page's: the counts cut to seconds
CUTS = {
    "calibrate": ["--generations", "1", "--population", "2", "--train-trajectories", "1",
                  "--workers", "1"],
    "train": ["--update-steps", "20", "--rollout-steps", "4", "--hidden", "16",
              "--eval-every", "10", "--device", "cpu"],
    "control": ["--steps", "5"],
    "sample": ["--train", "3", "--eval", "1", "--seconds", "0.6"],
}  # fmt: skip
#: numeric flags of the page that are not counts (a new count must be cut above)
NOT_COUNTS = {"--control-hz", "--cable-length", "--cable-mass", "--seed", "--markers",
              "--gripper-markers", "--rate-hz"}  # fmt: skip


def page_commands() -> list[list[str]]:
    """The page's indented `dlo ...` lines, in order, as argument lists (a trailing `&`
    kept as the last word)."""
    lines = re.findall(r"^ {4}(dlo .+)$", PAGE.read_text(encoding="utf-8"), re.MULTILINE)
    return [shlex.split(line.split("#")[0]) for line in lines]


def recording(seed: int, seconds: float = 1.5) -> tuple[np.ndarray, np.ndarray]:
    """Times (s) and markers (frames, V, 3) in mm: a sagging cable swung by both ends."""
    rng = np.random.default_rng(seed)
    t = np.arange(int(seconds * RATE_HZ) + 1) / RATE_HZ
    s, tt = np.linspace(0, 1, MARKERS)[None, :], t[:, None]
    phase, amp = rng.uniform(0, 6), rng.uniform(0.02, 0.06)
    x = 0.8 * s + amp * np.sin(2 * np.pi * tt + phase)
    y = 0.05 * np.sin(np.pi * s) * np.cos(3 * tt + phase)
    z = 0.5 - 0.2 * np.sin(np.pi * s) + amp * np.sin(5 * tt) * s
    return t, 1000 * np.stack([x, y, z], -1)


def write_recordings(folder: Path) -> None:
    """folder/train and folder/eval of motion-capture CSVs, as step 1 of the page says."""
    header = ["frame", "time"] + [f"m{j}_{a}" for j in range(MARKERS) for a in "xyz"]
    for split, seeds in (("train", (0, 1, 2)), ("eval", (100, 101))):
        (folder / split).mkdir(parents=True)
        for i, seed in enumerate(seeds):
            t, markers = recording(seed)
            rows = [",".join(header)] + [
                ",".join([str(k), f"{t[k]:.6f}", *(f"{v:.3f}" for v in markers[k].ravel())])
                for k in range(len(t))
            ]
            (folder / split / f"take{i}.csv").write_text("\n".join(rows) + "\n")


def _free_address() -> str:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return f"tcp://127.0.0.1:{probe.getsockname()[1]}"


def _prepared(argv: list[str], address: str, page_address: str) -> list[str]:
    """``argv`` with the repository's files found from anywhere, the test's own cell address
    and the counts cut; an uncut count on the page is an error, never a long run."""
    words = [
        str(ROOT / w) if w.startswith("examples/") else address if w == page_address else w
        for w in argv
    ]
    for flag, value in zip(words, words[1:], strict=False):
        if flag.startswith("--") and re.fullmatch(r"[0-9.e+-]+", value):
            assert flag in NOT_COUNTS, f"the page's {flag} {value}: cut it in CUTS or list it"
    return words + CUTS.get(words[1], [])


def _announced(cell: subprocess.Popen) -> None:
    """Waits for the cell's "serving" line. Only warnings may come before it (Python's: the
    warning, then the source line that raised it, indented): on the flex rod a calibrated
    bending damping above the twist damping is warned of."""
    assert cell.stderr is not None
    before: list[str] = []
    for line in cell.stderr:  # ends when the cell exits: never waits on a cell that runs on
        if "serving" in line:
            return
        before.append(line)
        assert "Warning: " in line or line.startswith(" "), "".join(before)
    raise AssertionError("the cell ended before serving: " + "".join(before))


#: the page's --held, and DEFORM's two held markers at each end in its place
LAYOUTS = {"page": None, "two-per-end": "0,1,-2,-1"}


@pytest.mark.parametrize("layout", LAYOUTS)
def test_the_own_cable_page_runs_end_to_end(tmp_path: Path, monkeypatch, layout: str) -> None:
    assert "docs/own_cable.md" in (ROOT / "README.md").read_text(encoding="utf-8")
    commands = page_commands()
    steps = [argv[1] for argv in commands]
    assert steps == ["sample", "import", "calibrate", "train", "eval", "goal", "serve", "control"]
    sampled, imported = commands[0], commands[1]
    held_flag = imported.index("--held") + 1
    held = imported[held_flag] if LAYOUTS[layout] is None else LAYOUTS[layout]
    imported[held_flag] = held
    if LAYOUTS[layout] is not None:  # the simulated cable with a marker on each gripper
        at = sampled.index("--gripper-markers")
        del sampled[at : at + 2]
    monkeypatch.chdir(tmp_path)
    serve = commands[steps.index("serve")]
    page_address = serve[serve.index("--address") + 1]
    address = _free_address()
    cell = None
    try:
        for argv in commands:
            words = _prepared(argv, address, page_address)
            if words[-1] == "&":  # the cell, in the background as on the page
                cell = subprocess.Popen(
                    [sys.executable, "-m", "dlocli.cli", *words[1:-1]],
                    stderr=subprocess.PIPE, text=True,
                )  # fmt: skip
                _announced(cell)
                continue
            assert run_dlo([*words[1:], "--json"]) == 0, shlex.join(words)
    finally:
        if cell is not None and cell.poll() is None:
            cell.send_signal(signal.SIGINT)
            cell.wait(timeout=30)
    data = load_dataset(tmp_path / "runs" / "mycable")
    markers = data.n_markers  # 10 along the rod (and one on each gripper: 12)
    assert data.rate_hz == 100.0 and markers == (10 if LAYOUTS[layout] is None else 12)
    held_markers = [int(i) % markers for i in held.split(",")]
    assert np.flatnonzero(data.held).tolist() == sorted(held_markers)
    calibrated = yaml.safe_load((tmp_path / "runs/mycable-sim/calibrated.yaml").read_text())
    assert calibrated["task"]["control_dt"] == pytest.approx(1 / data.rate_hz)
    arcs = calibrated["task"]["observation"]["marker_arc_lengths"]
    assert len(arcs) == markers and sum(a < 0 or a > 1 for a in arcs) == len(held_markers) - 2
    model = torch.load(tmp_path / "runs/mycable-model/checkpoints/final.pt", weights_only=True)
    assert model["control_dt"] == pytest.approx(1 / data.rate_hz)
    assert model["state_dict"]["held"].tolist() == data.held.tolist()
    evaluation = json.loads((tmp_path / "runs/mycable-eval/summary.json").read_text())
    assert np.isfinite(evaluation["model_score_cm"])
    control = json.loads((tmp_path / "runs/mycable-control/summary.json").read_text())
    assert control["steps"] == 5 and not control["diverged"]
    assert control["cell_dropped_commands"] == 0


def test_the_pages_seconds_are_its_recipes_steps_at_its_import_rate() -> None:
    """The recipe counts its rollouts in steps; the page states them in seconds at the rate
    its import line resamples to."""
    commands = {argv[1]: argv for argv in page_commands()}
    imported, train = commands["import"], commands["train"]
    hz = float(imported[imported.index("--control-hz") + 1])
    recipe = yaml.safe_load((ROOT / train[train.index("--spec") + 1]).read_text())
    k = recipe["rollout_steps"]
    text = " ".join(PAGE.read_text(encoding="utf-8").split())
    assert f"up to {k} steps, {k / hz:g} s at the import's {hz:g} Hz" in text


def test_calibrate_reads_an_import_at_its_rate_or_refuses_another(tmp_path: Path, capsys) -> None:
    write_recordings(tmp_path / "mycable")
    imported = tmp_path / "imported"
    flags = ["--units", "mm", "--control-hz", "50", "--out", str(imported)]
    assert run_dlo(["import", "--source", str(tmp_path / "mycable"), *flags]) == 0
    spec = tmp_path / "calibrate.json"
    spec.write_text(json.dumps({"rate_hz": 100, "cable_length": 1.0, "cable_mass": 0.03}))
    out = tmp_path / "sim"
    argv = ["calibrate", "--spec", str(spec), "--source", str(imported), "--out", str(out)]
    assert run_dlo(argv) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "imported at 50 Hz" in err, err
    assert not out.exists()
