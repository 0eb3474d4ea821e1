"""`dlo online --executor ray` on a local Ray cluster of 2 CPUs: the same trials as the local
executor bit for bit; a cluster lost midway keeps the finished trials and says how to go on;
the resumed run ends as the uninterrupted one, and so does a run whose driver was killed; an
address that does not answer is one line; on CUDA the driver updates there, trials plan on
their CPUs."""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import pytest
import torch
from typer.testing import CliRunner

from dlocli.cli import app
from dlocli.data import load_dataset
from dlocli.io import run_dir_entries, written_by_dlo
from dlocli.models.checkpoints import read_checkpoint

ray = pytest.importorskip("ray")
runner = CliRunner()
TINY = ["--iters", "2", "--trials", "2", "--steps", "15", "--epochs", "1",
        "--initial-episodes", "2", "--hidden", "16", "--seed", "3"]  # fmt: skip
TRIALS = [(k, j) for k in (1, 2) for j in (1, 2)]
#: Ray's command line beside this Python: a suite run without its venv's bin on PATH finds it
RAY_CLI = shutil.which("ray", path=os.path.dirname(sys.executable)) or "ray"


@pytest.fixture(scope="module")
def local_run(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("local") / "run"
    online("--executor", "local", "--out", str(out))
    return out


def online(*args: str, code: int = 0) -> str:
    res = runner.invoke(app, ["online", *TINY, *args, "--json"])
    assert res.exit_code == code, res.output
    return res.output


def assert_same_trials(run: Path, reference: Path, trials=TRIALS) -> None:
    """Every array of every trial file equal bit for bit, and the same references."""
    for k, j in trials:
        name = f"iter_{k:02d}/trial_{j:03d}.h5"
        got, want = load_dataset(run / "data" / name), load_dataset(reference / "data" / name)
        for field in ("positions", "quaternions", "actions", "rewards"):
            assert np.array_equal(getattr(got, field), getattr(want, field)), (name, field)
    if trials == TRIALS:
        summary, expected = (json.loads((r / "summary.json").read_text()) for r in (run, reference))
        assert summary["curve"] == expected["curve"]
        for name in ("zero_final_error_mm", "random_final_error_mm", "transitions"):
            assert summary[name] == expected[name], name


def assert_same_model(run: Path, reference: Path) -> None:
    """The final models' weights equal bit for bit."""
    got, want = (read_checkpoint(r / "checkpoints" / "final.pt")["state_dict"]
                 for r in (run, reference))  # fmt: skip
    assert got.keys() == want.keys()
    for name in got:
        assert torch.equal(got[name], want[name]), name


def test_ray_trials_equal_the_local_executors(cluster, local_run, tmp_path):
    out = tmp_path / "ray"
    online("--executor", "ray", "--workers", "2", "--out", str(out))
    assert_same_trials(out, local_run)
    assert json.loads((out / "spec.json").read_text())["executor"] == "ray"


def _lose_the_cluster_in_iteration_2(
    spec_json: str, model: object, k: int, j: int, cancel: object = None
) -> object:
    """A trial that takes its Ray worker down in iteration 2 (as a node that dies would)."""
    from dlocli.runs.online import trials

    if k == 2:
        os._exit(1)
    return trials.run_trial(spec_json, model, k, j, cancel)


def test_a_cluster_lost_midway_keeps_finished_trials_and_resume_ends_the_same(
    cluster, local_run, tmp_path, monkeypatch
):
    from ray import cloudpickle

    from dlocli.runs.online import trials

    cloudpickle.register_pickle_by_value(sys.modules[__name__])  # the workers lack tests/
    monkeypatch.setattr(trials, "run_trial", _lose_the_cluster_in_iteration_2)
    out = tmp_path / "run"
    output = online("--executor", "ray", "--workers", "2", "--out", str(out), code=1)
    # Ray's own "(raylet) A worker died" notice may come too: ours is the one error line
    errors = [line for line in output.splitlines() if line.startswith("error:")]
    assert len(errors) == 1, output
    line = errors[0]
    assert line.startswith("error: the local Ray instance stopped answering"), line
    assert f"--resume {out}" in line
    assert "ray start" in line and "--executor local" in line
    assert_same_trials(out, local_run, [(1, 1), (1, 2)])  # iteration 1's trials kept
    assert not (out / "data" / "iter_02").is_dir() or not any((out / "data" / "iter_02").iterdir())

    monkeypatch.undo()
    res = runner.invoke(app, ["online", "--resume", str(out), "--executor", "ray", "--json"])
    assert res.exit_code == 0, res.output
    assert_same_trials(out, local_run)


@pytest.mark.parametrize("address", ["127.0.0.1:1", "ray://127.0.0.1:1"])
def test_an_address_that_does_not_answer_is_one_line_and_nothing_written(address, tmp_path):
    out = tmp_path / "run"
    res = runner.invoke(app, ["online", *TINY, "--executor", "ray", "--ray-address", address,
                              "--out", str(out)])  # fmt: skip
    assert res.exit_code == 2, res.output
    line = res.output.strip()
    assert line.count("\n") == 0 and address in line and "ray start --head" in line
    assert not out.exists()


#: an HTTP/2 server's first frame: an empty SETTINGS frame
SETTINGS = bytes([0, 0, 0, 4, 0, 0, 0, 0, 0])


@pytest.mark.parametrize("reply", [b"", b"HTTP/1.1 400 Bad Request\r\n\r\n", SETTINGS],
                         ids=["silent", "http1", "greets-then-silent"])  # fmt: skip
def test_an_address_that_listens_but_is_not_ray_is_one_line_within_its_timeout(reply, tmp_path):
    """A server that accepts and stays silent (or speaks another protocol, or answers the
    HTTP/2 preface and then nothing: ray.init waited forever) used to hang the run until
    killed."""
    import socket
    import threading
    import time

    server = socket.create_server(("127.0.0.1", 0))
    accepted = []

    def serve() -> None:
        while True:
            try:
                connection, _ = server.accept()
            except OSError:  # closed at the end
                return
            accepted.append(connection)
            if reply:
                connection.sendall(reply)

    threading.Thread(target=serve, daemon=True).start()
    address = f"127.0.0.1:{server.getsockname()[1]}"
    out = tmp_path / "run"
    start = time.monotonic()
    res = runner.invoke(app, ["online", *TINY, "--executor", "ray", "--ray-address", address,
                              "--out", str(out)])  # fmt: skip
    assert time.monotonic() - start < 20
    assert res.exit_code == 2, res.output
    line = res.output.strip()
    assert line.count("\n") == 0 and address in line and "within 3 s" in line
    assert not out.exists()
    server.close()


def test_a_cluster_that_wants_its_token_is_one_line_naming_it(cluster, tmp_path):
    """A driver started without the cluster's authentication token is refused by Ray; the
    line says so (not "does not answer"), exit 2, nothing written."""
    if os.environ.get("RAY_AUTH_MODE") != "token":
        pytest.skip("this Ray's clusters take drivers without a token")
    out = tmp_path / "run"
    env = {k: v for k, v in os.environ.items() if not k.startswith("RAY_")}
    command = [sys.executable, "-m", "dlocli", "online", *TINY, "--executor", "ray",
               "--ray-address", cluster, "--out", str(out)]  # fmt: skip
    res = subprocess.run(command, env=env, capture_output=True, text=True, timeout=120)
    assert res.returncode == 2, res.stderr
    line = res.stderr.strip()
    assert line.count("\n") == 0 and cluster in line and "RAY_AUTH_MODE=token" in line, line
    assert not out.exists()


def _free_port() -> int:
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_a_head_that_dies_midway_is_one_line_naming_it_and_trials_are_kept(local_run, tmp_path):
    """A cluster (`ray start --head`, in its own session) killed once iteration 1's trials are
    written, under a driver on its node: Ray's core ends the driver outright; the line names
    the address and the --resume to run, exit 1, iteration 1's trials kept."""
    import re
    import tempfile

    env = {k: v for k, v in os.environ.items() if k != "RAY_ADDRESS"}
    env |= {"OMP_NUM_THREADS": "1", "RAY_AUTH_MODE": "token"}  # older Rays ignore the mode
    temp = tempfile.mkdtemp(prefix="dlo-ray-", dir="/tmp")  # Ray's socket paths must be short
    head = subprocess.run(
        [RAY_CLI, "start", "--head", "--port", str(_free_port()), "--num-cpus", "2",
         "--include-dashboard", "false", "--ray-client-server-port", str(_free_port()),
         "--dashboard-agent-listen-port", str(_free_port()), "--temp-dir", temp],
        env=env, capture_output=True, text=True, timeout=120, start_new_session=True,
    )  # fmt: skip
    sid = _session_of(head) if head.returncode == 0 else None
    try:
        assert head.returncode == 0, head.stdout + head.stderr
        address = re.search(r"--address='([^']+)'", head.stdout + head.stderr).group(1)
        out, log = tmp_path / "run", tmp_path / "driver.log"
        command = [sys.executable, "-m", "dlocli", "online", *TINY, "--executor", "ray",
                   "--ray-address", address, "--out", str(out)]  # fmt: skip
        with log.open("w") as sink:
            driver = subprocess.Popen(command, env=env, stdout=subprocess.DEVNULL, stderr=sink)
        _wait_for([out / "data" / "iter_01" / f"trial_{j:03d}.h5" for j in (1, 2)], driver,
                  log, timeout=300)  # fmt: skip
        os.killpg(sid, signal.SIGKILL)
        assert driver.wait(timeout=120) == 1
        time.sleep(3)  # the watch's line follows the driver's end
    finally:
        for pid in _alive(_session(sid)) if sid is not None else ():
            os.kill(pid, signal.SIGKILL)
        shutil.rmtree(temp, ignore_errors=True)
    errors = [line for line in log.read_text().splitlines() if line.startswith("error:")]
    assert len(errors) == 1, log.read_text()
    assert f"the Ray cluster at {address} stopped answering" in errors[0]
    assert f"--resume {out}" in errors[0]
    assert_same_trials(out, local_run, [(1, 1), (1, 2)])


# ----------------------------------------------------------------------------- devices
def test_ray_trials_plan_on_the_cpu_and_local_ones_on_the_updates_device():
    """A Ray task sees no GPU unless it asks for one: its trials get the CPU, whatever device
    the driver updates the model on; the local pool's processes see the driver's GPUs."""
    from dlocli.executors import LocalExecutor, RayExecutor
    from dlocli.runs.online import OnlineRun, OnlineSpec

    for device in ("cuda", "auto", "cpu"):
        spec = OnlineSpec(fit={"device": device})
        assert OnlineRun(spec, executor=RayExecutor()).trial_spec().fit.device == "cpu"
        assert OnlineRun(spec, executor=LocalExecutor(2)).trial_spec().fit.device == device


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_ray_online_on_cuda_updates_on_the_gpu_and_plans_on_the_cpus(cluster, tmp_path):
    out = tmp_path / "cuda"
    summary = json.loads(online("--executor", "ray", "--workers", "2", "--device", "cuda",
                                "--out", str(out)).strip().splitlines()[-1])  # fmt: skip
    assert summary["iterations_done"] == 2 and np.isfinite(summary["final_error_mm"])
    for k in (1, 2):
        assert read_checkpoint(out / "checkpoints" / f"iter_{k:02d}.pt")["device"] == "cuda:0"
    for k, j in TRIALS:
        trial = load_dataset(out / "data" / f"iter_{k:02d}" / f"trial_{j:03d}.h5")
        assert np.isfinite(trial.positions).all() and trial.attrs["threads"] == 1


# ----------------------------------------------------------------------------- a killed driver
def _session(sid: int) -> set[int]:
    """The processes of session ``sid``: a driver started in its own session, and everything
    it started (Ray's local instance: its GCS, raylet and workers)."""
    pids = set()
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            after_name = stat.read_text().rsplit(")", 1)[1].split()
        except OSError:  # ended meanwhile
            continue
        if int(after_name[3]) == sid:  # state, ppid, pgrp, session
            pids.add(int(stat.parent.name))
    return pids


def _session_of(head: subprocess.CompletedProcess) -> int:
    """The session `ray start` left its processes in: its GCS server's."""
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            text = stat.read_text()
            command = (stat.parent / "cmdline").read_bytes()
        except OSError:
            continue
        if b"gcs_server" in command and head.args[-1].encode() in command:
            return int(text.rsplit(")", 1)[1].split()[3])
    raise AssertionError("no GCS server of this head")


def _alive(pids: set[int]) -> set[int]:
    return {pid for pid in pids if Path(f"/proc/{pid}").exists()
            and "Z" not in Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1][:3]}  # fmt: skip


@contextmanager
def killed_at_exit(driver: subprocess.Popen) -> Iterator[set[int]]:
    """On leaving: SIGKILL ``driver`` (started in a session of its own) and everything of its
    session (its local Ray instance); the set yielded then holds them, and none may be left
    behind. On an error inside, the session's processes are killed all the same."""
    started: set[int] = set()
    try:
        yield started
        started |= _session(driver.pid)
        os.killpg(driver.pid, signal.SIGKILL)
        driver.wait(timeout=30)
        end = time.monotonic() + 30  # the group's processes are reaped by init
        while _alive(started | _session(driver.pid)) and time.monotonic() < end:
            time.sleep(0.2)
        assert not _alive(started | _session(driver.pid)), "processes left behind"
    finally:
        for pid in _alive(started | _session(driver.pid)):  # never leave a local Ray behind
            os.kill(pid, signal.SIGKILL)


def _wait_for(paths: list[Path], driver: subprocess.Popen, log: Path, timeout: float) -> None:
    end = time.monotonic() + timeout
    while not all(p.is_file() for p in paths):
        assert driver.poll() is None, f"the driver ended first:\n{log.read_text()}"
        assert time.monotonic() < end, f"no {paths} after {timeout} s:\n{log.read_text()}"
        time.sleep(0.2)


def test_a_killed_driver_resumes_to_the_uninterrupted_result(cluster, local_run, tmp_path):
    """`dlo online --executor ray` in its own session, with its own local Ray instance, killed
    (SIGKILL, the whole process group) once iteration 1's trials are written; --resume ends
    with the uninterrupted run's trials, references and model, and every file is dlo's."""
    out, log = tmp_path / "run", tmp_path / "driver.log"
    env = {k: v for k, v in os.environ.items() if k != "RAY_ADDRESS"}  # not the module's Ray
    env["OMP_NUM_THREADS"] = "1"  # the reference's update ran with this process's one thread
    command = [sys.executable, "-m", "dlocli", "online", *TINY, "--executor", "ray",
               "--workers", "2", "--out", str(out)]  # fmt: skip
    with log.open("w") as sink:
        driver = subprocess.Popen(command, env=env, stdout=sink, stderr=subprocess.STDOUT,
                                  start_new_session=True)  # fmt: skip
    with killed_at_exit(driver) as started:
        _wait_for([out / "data" / "iter_01" / f"trial_{j:03d}.h5" for j in (1, 2)], driver,
                  log, timeout=300)  # fmt: skip
    assert len(started) > 1  # the driver and its Ray instance were killed, not the driver alone

    res = runner.invoke(app, ["online", "--resume", str(out), "--executor", "ray", "--json"])
    assert res.exit_code == 0, res.output
    assert_same_trials(out, local_run)
    assert_same_model(out, local_run)
    assert run_dir_entries(out) <= written_by_dlo(out)  # an --overwrite later may replace all
