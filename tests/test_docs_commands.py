"""Every indented `dlo` line of the documentation (docs/*.md), and every `dlo` command of the
README's feature table, runs as written, read from the pages themselves, page by page (and the
table row by row) in order in a fresh directory, with only their counts cut to seconds and a
cell's address and a Ray head filled in by the test. No data but what the lines make: a page
that reads a recording makes it first (`dlo sample`), so a missing prerequisite, or two lines
writing one `--out`, fails the test. The pages that start from the quickstart's goal and model
say so with a link, and get them. A count this test does not know how to cut fails it, never
silently a long run; so does a page whose commands no test runs."""

from __future__ import annotations

import os
import re
import shlex
import shutil
import signal
import socket
import subprocess
import sys
from pathlib import Path

import pytest

from tiny import MUJOCO_ROD, run_dlo

ROOT = Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs"
#: pages whose commands another test runs end to end, with checks of its own
RUN_ELSEWHERE = {"own_cable.md": "test_own_cable.py"}
#: a page's count flags and the value they run at here
COUNTS = {"--episodes": "2", "--iters": "1", "--workers": "1", "--num-cpus": "2",
          "--update-steps": "20", "--train": "2", "--eval": "1", "--seconds": "0.4",
          "--cables": "2"}  # fmt: skip
#: numeric flags of the pages that are not counts: kept as written
NOT_COUNTS = {"--seed", "--delay-ms", "--control-hz", "--fill-gaps", "--noise-mm",
              "--latency-steps", "--markers", "--lr", "--rate-hz", "--gripper-markers",
              "--cable-length", "--cable-mass"}  # fmt: skip
#: flags each command gets on top of the page's, by command (and by the form of its data)
CUTS = {
    "collect": ["--steps", "10"],
    "train": ["--epochs", "1", "--hidden", "16", "--device", "cpu"],
    "train markers": ["--update-steps", "20", "--rollout-steps", "4", "--hidden", "16",
                      "--eval-every", "10", "--device", "cpu"],
    "control": ["--steps", "5"],
    "online": ["--iters", "1", "--trials", "1", "--steps", "10", "--epochs", "1",
               "--update-steps", "20", "--initial-episodes", "2", "--hidden", "16"],
    # a marker model's update counts steps (--epochs is refused there)
    "online markers": ["--iters", "1", "--trials", "1", "--steps", "10", "--update-steps",
                       "20", "--initial-episodes", "2", "--hidden", "16"],
    "bench": ["--budget", "40", "--seeds", "1", "--evals", "1", "--eval-trials", "1",
              "--steps", "10", "--epochs", "1", "--hidden", "16"],
    "calibrate": ["--generations", "1", "--population", "2", "--train-trajectories", "1"],
    "sample": ["--train", "2", "--eval", "1", "--seconds", "0.4"],
}  # fmt: skip
#: lines the docs promise that dlocli refuses today (exit 2): each is run and must still be
#: refused, so the day it runs this test fails and the entry goes
KNOWN_REFUSED: dict[str, str] = {}
#: what a page needs from the quickstart before its own lines (a goal, a trained model): the
#: page links to the quickstart where it does
NEEDS_QUICKSTART = {"commands.md", "real-cell.md"}
QUICKSTART_LINK = "getting-started.md#quickstart"


def pages() -> list[str]:
    return sorted(p.name for p in DOCS.glob("*.md") if p.name not in RUN_ELSEWHERE)


def page_commands(page: str) -> list[list[str]]:
    """The page's indented `dlo ...` lines, in order, continuation lines joined, comments
    dropped, as argument lists (a trailing `&` kept as the last word)."""
    text = (DOCS / page).read_text(encoding="utf-8").replace("\\\n", " ")
    lines = re.findall(r"^ {4,}(dlo .+)$", text, re.MULTILINE)
    return [shlex.split(line, comments=True) for line in lines]


def _free_address() -> str:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return f"tcp://127.0.0.1:{probe.getsockname()[1]}"


def prepared(argv: list[str], places: dict[str, str]) -> list[str]:
    """``argv`` with the repository's files found from anywhere, the placeholders filled in
    and the counts cut; an uncut count on a page is an error, never a long run."""
    words = []
    for word in argv:
        for placeholder, value in places.items():
            word = word.replace(placeholder, value)
        words.append(str(ROOT / word) if word.startswith("examples/") else word)
    for index, (flag, value) in enumerate(zip(words, words[1:], strict=False)):
        if not (flag.startswith("--") and re.fullmatch(r"[0-9.e+-]+", value)):
            continue
        if flag in COUNTS:
            words[index + 1] = COUNTS[flag]
        else:
            assert flag in NOT_COUNTS, f"the docs' {flag} {value}: cut it in COUNTS or list it"
    if "--resume" in words:  # a resumed run keeps the counts it started with
        return words
    # a marker dataset's training: a recipe of examples/real_cables, or gradient steps
    markers = "real_cables" in " ".join(words) or "--update-steps" in words
    observes_markers = words[1] == "online" and bool({"markers", "pointcloud"} & set(words))
    form = " markers" if (words[1] == "train" and markers) or observes_markers else ""
    return words + CUTS.get(words[1] + form, [])


def readme_commands() -> list[list[str]]:
    """The `dlo ...` commands of the README's feature table, row by row, in order."""
    readme = (ROOT / "README.md").read_text(encoding="utf-8")
    table = readme.split("\n## What it does", 1)[1].split("\n## ", 1)[0]
    rows = [line for line in table.splitlines() if line.startswith("| ")]
    return [shlex.split(command) for row in rows for command in re.findall(r"`(dlo [^`]+)`", row)]


def run_page(page: str, folder: Path, places: dict[str, str]) -> list[list[str]]:
    """Run the page's lines (or the README's table's) in ``folder``, in order."""
    commands = readme_commands() if page == "README.md" else page_commands(page)
    return run_lines(page, commands, folder, places)


def run_lines(
    page: str, commands: list[list[str]], folder: Path, places: dict[str, str]
) -> list[list[str]]:
    """Run ``commands`` in ``folder``, in order, each to exit 0; a line ending in `&` serves a
    cell in the background, as on the page, until the lines are done. Returns what ran."""
    ran, cells = [], []
    try:
        for argv in commands:
            words = prepared(argv, places)
            if words[-1] == "&":
                cell = subprocess.Popen(
                    [sys.executable, "-m", "dlocli.cli", *words[1:-1]],
                    cwd=folder, stderr=subprocess.PIPE, text=True,
                )  # fmt: skip
                cells.append(cell)
                assert cell.stderr is not None
                line = cell.stderr.readline()
                assert "serving" in line, line + cell.stderr.read()
            elif shlex.join(argv) in KNOWN_REFUSED:
                assert run_dlo(words[1:]) == 2, f"{page}: {shlex.join(words)} runs now"
            else:
                assert run_dlo(words[1:]) == 0, f"{page}: {shlex.join(words)}"
            ran.append(words)
    finally:
        for cell in cells:
            if cell.poll() is None:
                cell.send_signal(signal.SIGINT)
                cell.wait(timeout=30)
    return ran


def _placeholders() -> dict[str, str]:
    """The pages' placeholders: a free address for the page's cell (no data: the pages make
    their own), and on MuJoCo 3 the composite cable's calibrated rods for the flex rod's (the
    pages name both)."""
    places = {"tcp://127.0.0.1:5555": _free_address()}
    if MUJOCO_ROD == "mujoco":
        places["-mujoco-flex/calibrated.yaml"] = "-mujoco/calibrated.yaml"
    return places


@pytest.fixture(scope="module")
def quickstart(tmp_path_factory) -> Path:
    """The quickstart's first lines (a goal, data, a model), run once for the pages that
    start from its goal and model."""
    folder, here = tmp_path_factory.mktemp("quickstart"), Path.cwd()
    os.chdir(folder)
    try:
        for argv in page_commands("getting-started.md")[:3]:
            assert run_dlo(prepared(argv, {})[1:]) == 0, shlex.join(argv)
    finally:
        os.chdir(here)
    return folder


def test_every_page_with_dlo_lines_is_run_by_a_test() -> None:
    for page, test in RUN_ELSEWHERE.items():
        assert page_commands(page) and (ROOT / "tests" / test).is_file(), page
        assert page in (ROOT / "tests" / test).read_text(encoding="utf-8"), (page, test)
    assert sum(len(page_commands(page)) for page in pages()) >= 20


@pytest.mark.parametrize("page", [p for p in pages() if page_commands(p) and p != "clusters.md"])
def test_the_pages_dlo_lines_run(page: str, tmp_path: Path, monkeypatch, request) -> None:
    pytest.importorskip("zmq")
    monkeypatch.chdir(tmp_path)
    places = _placeholders()
    if page in NEEDS_QUICKSTART:
        assert QUICKSTART_LINK in (DOCS / page).read_text(encoding="utf-8"), page
        shutil.copytree(request.getfixturevalue("quickstart"), tmp_path, dirs_exist_ok=True)
    ran = run_page(page, tmp_path, places)
    assert len(ran) == len(page_commands(page))


def test_the_cluster_pages_lines_run_on_a_local_ray_head(
    tmp_path: Path, monkeypatch, capsys
) -> None:
    pytest.importorskip("cma")
    monkeypatch.chdir(tmp_path)
    ran = run_page_on_a_ray_head("clusters.md", tmp_path)
    assert [words[1] for words in ran] == ["online", "online", "sample", "calibrate"]
    errors = [line for line in capsys.readouterr().err.splitlines() if line.startswith("error:")]
    assert errors == [f"error: {why}" for why in KNOWN_REFUSED.values()], errors


def test_the_readme_and_the_getting_started_page_hold_the_same_two_commands() -> None:
    """CI reads the two commands from the README; the page repeats them, unchanged."""
    sys.path.insert(0, str(ROOT / "benchmarks"))
    try:
        from readme_commands import commands
    finally:
        sys.path.remove(str(ROOT / "benchmarks"))
    page = (DOCS / "getting-started.md").read_text(encoding="utf-8")
    for command in commands():
        assert f"\n    {command}\n" in page, command


def test_each_readme_feature_command_is_a_docs_line_the_suite_runs() -> None:
    readme = (ROOT / "README.md").read_text(encoding="utf-8")
    quoted = re.findall(r"`(dlo [^`]+)`", readme)
    assert len(quoted) >= 6
    lines = {
        shlex.join(argv) for page in [*pages(), *RUN_ELSEWHERE] for argv in page_commands(page)
    }
    for command in quoted:
        assert shlex.join(shlex.split(command)) in lines, command


@pytest.mark.slow  # about a minute: every row, the cluster's included
def test_the_readme_feature_tables_commands_run_in_order_in_one_folder(
    tmp_path: Path, monkeypatch
) -> None:
    """Row by row, as a newcomer copies them: each row makes what it reads (a goal, a model,
    a recording), and no row writes another's --out."""
    pytest.importorskip("zmq")
    pytest.importorskip("cma")
    monkeypatch.chdir(tmp_path)
    ran = run_page_on_a_ray_head("README.md", tmp_path)
    assert len(ran) == len(readme_commands()) >= 15


def run_page_on_a_ray_head(page: str, folder: Path) -> list[list[str]]:
    """:func:`run_page` with HEAD:6379 a local Ray head of 2 CPUs, shut down after."""
    ray = pytest.importorskip("ray")
    places = _placeholders()
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
    try:
        places["HEAD:6379"] = ray.get_runtime_context().gcs_address
        return run_page(page, folder, places)
    finally:
        ray.shutdown()


def _outs(commands: list[list[str]]) -> list[str]:
    return [argv[argv.index("--out") + 1] for argv in commands if "--out" in argv]


def test_no_two_lines_of_a_page_or_of_the_readme_table_write_one_out() -> None:
    """Run in order in one folder, the second of two lines with one --out would be refused
    (or, with --overwrite, undo the first); `--resume` lines name no --out."""
    for name, commands in [("README.md", readme_commands())] + [
        (page, page_commands(page)) for page in [*pages(), *RUN_ELSEWHERE]
    ]:
        outs = _outs(commands)
        assert len(outs) == len(set(outs)), (name, sorted(o for o in outs if outs.count(o) > 1))
    assert _outs([["dlo", "x", "--out", "a"], ["dlo", "y", "--out", "a"]]) == ["a", "a"]


def test_a_missing_prerequisite_or_a_shared_out_fails_the_run(tmp_path: Path, monkeypatch):
    """What the runs above rely on: a line whose input no earlier line made, or a second line
    writing an earlier one's --out, exits 2, and the run stops there."""
    monkeypatch.chdir(tmp_path)
    control = "dlo control --goal shape.npy --checkpoint runs/model --out runs/ctl"
    with pytest.raises(AssertionError, match="runs/model"):
        run_lines("missing", [shlex.split(control)], tmp_path, {})
    twice = [shlex.split("dlo goal --seed 0 --out shape.npy")] * 2
    with pytest.raises(AssertionError, match="shape.npy"):
        run_lines("shared", twice, tmp_path, {})
    assert (tmp_path / "shape.npy").is_file() and not (tmp_path / "runs").exists()
