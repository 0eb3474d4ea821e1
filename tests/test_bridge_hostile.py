"""A cell no message can kill or take over: `dlo serve` and the example robot cell sent what a
hostile or careless client sends, then a good controller, which must get what it gets from
a fresh cell; a second client while a controller runs; keys off loopback; a controller fed
nonsense by its cell. Real ZeroMQ sockets and the real MuJoCo rod throughout."""

from __future__ import annotations

import json
import subprocess
import sys
import threading
import time
from contextlib import contextmanager
from pathlib import Path

import pytest
from cells import (
    EXAMPLE,
    RawClient,
    control_argv,
    example_cell,
    free_port,
    lan_address,
    listening,
    served,
    step_errors,
    stepping_controller,
    summary_of,
)

from tiny import MUJOCO_ROD, run_dlo

zmq = pytest.importorskip("zmq")

CELLS = {"dlo serve": served, "example robot cell": example_cell}
STILL = [[0.0] * 6, [0.0] * 6]


def _hello(client: RawClient, **changes) -> dict:
    from dlocli.bridge import protocol
    from dlocli.specs import BackendSpec

    backend = BackendSpec().model_dump(mode="json")
    hello = {"protocol": protocol.PROTOCOL, "version": protocol.VERSION, "backend": backend,
             "control_dt": 0.02} | changes  # fmt: skip
    return client.ask("hello", **hello)


def _peak_rss_mb(pid: int) -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmHWM:"):
            return int(line.split()[1]) / 1024
    raise AssertionError("no VmHWM")


def _reset_with(token: str, **limits) -> bytes:
    """A reset whose limits are sane but for ``limits``."""
    sane = {"workspace_low": [-1, -1, 0], "workspace_high": [1, 1, 2], "min_separation": 0.1,
            "max_separation": 1.0}  # fmt: skip
    return json.dumps({"type": "reset", "session": token, "limits": sane | limits}).encode()


def _assault(address: str) -> None:
    """Every class of bad request the review found, each answered (or, past the size limit,
    dropped unread) while the cell serves on."""
    client = RawClient(address)
    early = client.ask("step", session="guess", velocities=STILL)  # before any hello
    assert early["type"] == "error" and early["code"] == "no_session", early
    old = _hello(client, version=1)
    assert old["code"] == "bad_request" and "version 2, not dlocli-cell 1" in old["message"]
    welcome = _hello(client)
    assert welcome["type"] == "welcome" and welcome["version"] == 2, welcome
    token = welcome["session"]
    bad = [
        [json.dumps({"type": "set_state", "session": token}).encode()],
        [b"[" * 100_000 + b"]" * 100_000],
        [b"{not json"],
        [b"\xff\xfe"],
        [b'{"type": "step", "session": "%s", ' % token.encode(), b'"velocities": []}'],  # 2 frames
        [b'{"type": "reset", "session": "%s", "seed": 1e999}' % token.encode()],
        [b'{"type": "reset", "session": "%s", "seed": -1}' % token.encode()],
        [_reset_with(token, workspace_low=[float("nan"), 0, 0])],
        [_reset_with(token, workspace_low=[0.0])],
        [_reset_with(token, min_separation=2.0)],
        [json.dumps({"type": "step", "session": token, "velocities": [[1e999] * 6] * 2}).encode()],
        [json.dumps({"type": "step", "session": token, "velocities": [["x"] * 6] * 2}).encode()],
        [json.dumps({"type": "step", "session": token, "velocities": [[True] * 6] * 2}).encode()],
        [json.dumps({"type": "fly", "session": token}).encode()],
    ]
    for frames in bad:
        reply = client.send(*frames)
        assert reply is not None and reply["type"] == "error", (frames[0][:80], reply)
        assert reply["code"] == "bad_request", reply
    capture = client.ask("capture", session=token, seed=1)  # neither cell has a camera
    assert capture["code"] == "refused" and "dlo serve --camera" in capture["message"], capture
    assert client.ask("capture", session=token, seed=-1)["code"] == "bad_request"
    # a foreign token changes nothing
    assert client.ask("reset", session="0" * 32)["code"] == "busy"
    # 50 MB of velocities: past the size limit, dropped unread, the cell's memory untouched
    huge = json.dumps({"type": "step", "session": token, "velocities": [[0.0] * 6] * 4_000_000})
    assert len(huge) > 50e6
    assert client.send(huge.encode(), timeout_ms=2000) is None
    state = client.ask("step", session=token, velocities=STILL)
    assert state["type"] == "state" and state["step"] == 1, state
    assert client.ask("bye", session=token)["type"] == "bye"
    client.close()


@pytest.mark.parametrize("cell", list(CELLS))
def test_a_cell_refuses_every_bad_request_and_then_serves_a_controller_as_a_fresh_one(
    cell, near_rest_goal, sac_policy, tmp_path
):
    fresh, after = tmp_path / "fresh", tmp_path / "after"
    with CELLS[cell]() as address:
        assert run_dlo(control_argv(near_rest_goal, sac_policy, fresh, "--cell", address)) == 0
    with CELLS[cell]() as address:
        _assault(address)
        assert run_dlo(control_argv(near_rest_goal, sac_policy, after, "--cell", address)) == 0
    assert step_errors(after) == step_errors(fresh)
    assert summary_of(after)["final_error_mm"] == summary_of(fresh)["final_error_mm"]


def test_a_message_past_the_size_limit_costs_the_cell_no_memory():
    from dlocli.bridge import protocol

    argv = [sys.executable, "-m", "dlocli.cli", "serve", "--address", "tcp://127.0.0.1:*"]
    with listening(argv, r" at (tcp://\S+);") as (address, cell):
        client = RawClient(address)
        welcome = _hello(client)
        before = _peak_rss_mb(cell.pid)
        size = 8 * protocol.MAX_MESSAGE_BYTES
        started = time.perf_counter()
        assert client.send(b"[" + b"0," * (size // 2) + b"0]", timeout_ms=1000) is None
        state = client.ask("step", session=welcome["session"], velocities=STILL)
        answered = time.perf_counter() - started
        grown = _peak_rss_mb(cell.pid) - before
        client.close()
    assert state["type"] == "state"
    assert grown < size / 2**20 / 4, f"the cell grew {grown:.0f} MB for a {size >> 20} MB message"
    assert answered < 10.0  # the next request is served at once (the 1 s is the sender's wait)


def test_an_intruder_gets_busy_and_the_running_controller_its_own_result(
    near_rest_goal, sac_policy, tmp_path
):
    here, there = tmp_path / "here", tmp_path / "there"
    argv = control_argv(near_rest_goal, sac_policy, there, steps=200)
    argv.remove("--json")  # its progress lines say when the steps have begun
    assert run_dlo(control_argv(near_rest_goal, sac_policy, here, steps=200)) == 0
    with served("--delay-ms", "20") as address:  # lockstep: the delay changes no number
        control = stepping_controller(argv, address)
        intruder = RawClient(address)
        replies = [_hello(intruder), intruder.ask("reset", session="x" * 32, seed=3)]
        replies += [intruder.ask("step", session="x" * 32, velocities=[[0.1] * 6] * 2)
                    for _ in range(25)]  # fmt: skip
        running = control.poll() is None
        intruder.close()
        _, stderr = control.communicate(timeout=120)
    assert running, "the controller ended before the intruder was done: lengthen the run"
    assert control.returncode == 0, stderr
    assert [r["code"] for r in replies] == ["busy"] * 27, replies
    assert step_errors(there) == step_errors(here)


def test_a_session_that_idled_out_ends_its_controllers_run_in_one_line():
    """A controller silent past the cell's idle time loses the cell: the next client may take
    it, and the old controller stops instead of driving a rod someone else reset."""
    from dlocli import make_env
    from dlocli.bridge.remote import CellLost

    with served("--session-idle-s", "0.5") as address:
        env = make_env(MUJOCO_ROD, "single", seed=0, render_mode=None, episode_steps=5,
                       reset_motion_steps=2, reset_settle_steps=2, cell=address)  # fmt: skip
        try:
            env.reset(seed=0)
            time.sleep(1.0)
            newcomer = RawClient(address)
            token = _hello(newcomer)["session"]
            assert newcomer.ask("reset", session=token)["type"] == "state"
            with pytest.raises(CellLost, match="no longer this controller's.*busy"):
                env.step(env.action_space.sample())
            newcomer.ask("bye", session=token)
            newcomer.close()
        finally:
            env.close()


# --------------------------------------------------------------------------- keys
def test_a_cell_off_loopback_needs_keys_on_both_sides(near_rest_goal, sac_policy, tmp_path, capsys):
    port = free_port()
    assert run_dlo(["serve", "--address", f"tcp://0.0.0.0:{port}"]) == 2
    line = capsys.readouterr().err.strip()
    assert len(line.splitlines()) == 1 and "dlo keys" in line, line
    # each side is told its own flag and the other side's: they differ
    assert "pass --keys DIR here" in line and "--cell-keys DIR to the controller" in line, line
    out = tmp_path / "run"
    argv = control_argv(near_rest_goal, sac_policy, out, "--cell", f"tcp://{lan_address()}:{port}")
    assert run_dlo(argv) == 2
    line = capsys.readouterr().err.strip()
    assert len(line.splitlines()) == 1, line
    assert "pass --cell-keys DIR here" in line and "--keys DIR to the cell" in line, line
    assert not out.exists()
    example = subprocess.run([sys.executable, str(EXAMPLE), "--address", f"tcp://0.0.0.0:{port}"],
                             capture_output=True, text=True, timeout=120)  # fmt: skip
    assert example.returncode == 2 and "dlo keys" in example.stderr, example.stderr


def test_with_keys_a_bridged_run_off_loopback_equals_the_in_process_one(
    near_rest_goal, sac_policy, tmp_path, capsys
):
    keys, strangers = tmp_path / "keys", tmp_path / "strangers"
    assert run_dlo(["keys", "--out", str(keys)]) == 0
    assert run_dlo(["keys", "--out", str(strangers)]) == 0
    assert (keys / "controller.key_secret").stat().st_mode & 0o077 == 0
    here, there, refused = tmp_path / "here", tmp_path / "there", tmp_path / "refused"
    assert run_dlo(control_argv(near_rest_goal, sac_policy, here)) == 0
    with served("--keys", str(keys), address="tcp://0.0.0.0:*") as bound:
        address = f"tcp://{lan_address()}:{bound.rsplit(':', 1)[1]}"
        flags = ("--cell", address, "--cell-keys", str(keys))
        assert run_dlo(control_argv(near_rest_goal, sac_policy, there, *flags)) == 0
        flags = ("--cell", address, "--cell-keys", str(strangers), "--cell-timeout-s", "1")
        capsys.readouterr()
        assert run_dlo(control_argv(near_rest_goal, sac_policy, refused, *flags)) == 2
        assert "--cell-keys is the folder it was given as --keys" in capsys.readouterr().err
    assert step_errors(there) == step_errors(here)
    assert not refused.exists()


@pytest.mark.parametrize("mode", [0o644, 0o640, 0o604])
def test_a_secret_key_others_can_read_is_refused_on_both_sides(
    mode, near_rest_goal, sac_policy, tmp_path, capsys
):
    keys = tmp_path / "keys"
    assert run_dlo(["keys", "--out", str(keys)]) == 0
    (keys / "cell.key_secret").chmod(mode)
    (keys / "controller.key_secret").chmod(mode)
    capsys.readouterr()
    assert run_dlo(["serve", "--keys", str(keys)]) == 2
    line = capsys.readouterr().err.strip()
    assert len(line.splitlines()) == 1 and "readable by others" in line, line
    assert f"chmod 600 {keys / 'cell.key_secret'}" in line, line
    out = tmp_path / "run"
    argv = control_argv(near_rest_goal, sac_policy, out, "--cell", "tcp://127.0.0.1:1",
                        "--cell-keys", str(keys))  # fmt: skip
    assert run_dlo(argv) == 2
    line = capsys.readouterr().err.strip()
    assert len(line.splitlines()) == 1 and "--cell-keys" in line, line
    assert f"chmod 600 {keys / 'controller.key_secret'}" in line and not out.exists(), line


def test_the_banner_says_what_an_operator_needs_and_the_log_names_each_refusal(tmp_path):
    """`dlo serve`'s first line states the address, keys, camera and the session idle time;
    a client without the keys, one whose key the folder does not hold, and a busy client are
    logged one line each (repeats of one failure within seconds are counted, not logged)."""
    import zmq.auth

    keys, strangers = tmp_path / "keys", tmp_path / "strangers"
    assert run_dlo(["keys", "--out", str(keys)]) == 0
    assert run_dlo(["keys", "--out", str(strangers)]) == 0
    argv = [sys.executable, "-m", "dlocli.cli", "serve", "--address", "tcp://0.0.0.0:*",
            "--keys", str(keys), "--camera", "--session-idle-s", "7"]  # fmt: skip
    with listening(argv, r"(.*)") as (banner, cell):
        port = banner.split(" at tcp://0.0.0.0:")[1].split(";")[0]
        address = f"tcp://{lan_address()}:{port}"
        keyless = RawClient(address, timeout_ms=1500)
        assert keyless.ask("bye", session="x") is None  # no keys: never answered
        keyless.close()
        context = zmq.Context()
        sock = context.socket(zmq.REQ)
        sock.setsockopt(zmq.LINGER, 0)
        public, secret = zmq.auth.load_certificate(strangers / "controller.key_secret")
        sock.curve_publickey, sock.curve_secretkey = public, secret
        sock.curve_serverkey = zmq.auth.load_certificate(keys / "cell.key")[0]
        sock.connect(address)
        sock.send(b"{}")
        assert not sock.poll(1500)  # a key the folder does not hold: never answered
        sock.close()
        context.term()
    log = cell.stderr.read()
    assert f"at tcp://0.0.0.0:{port}; keys on ({keys}); camera on (160 x 120 px)" in banner
    assert "a session ends after 7 s without a request" in banner
    failures = [line for line in log.splitlines() if "a handshake failed" in line]
    # the keyless client's, then the stranger's (the first may be told as a hang-up)
    assert "without this cell's keys" in failures[0], log
    assert any("does not hold" in line for line in failures[1:]), log
    assert len(failures) <= 4, log  # each client's retries are counted, not logged

    with listening([sys.executable, "-m", "dlocli.cli", "serve"], r"(.*)") as (banner, cell):
        address = banner.split(" at ")[1].split(";")[0]
        assert "keys off (loopback only); camera off" in banner
        client = RawClient(address)
        token = _hello(client)["session"]
        assert _hello(client)["code"] == "busy"
        # a token of non-ASCII characters: busy, not a fault of the cell
        assert client.ask("reset", session="\u00e9" * 32, seed=0)["code"] == "busy"
        lone = client.ask("reset", session="\ud800" * 32, seed=0)  # not UTF-8: not JSON
        assert lone["code"] == "bad_request", lone
        assert client.ask("bye", session=token)["type"] == "bye"
        client.close()
    log = cell.stderr.read()
    assert log.count("refused a hello: busy") == 1, log
    assert log.count("refused a request: busy") == 1, log
    assert "cell_fault" not in log and "failed" not in log, log


# --------------------------------------------------------------------------- the controller
@contextmanager
def lying_cell(state_changes: dict):
    """A cell in a thread that welcomes properly, then answers every request with a state
    changed by ``state_changes``: the controller must not believe it."""
    from dlocli.bridge import protocol
    from dlocli.specs import BackendSpec

    context = zmq.Context()
    sock = context.socket(zmq.REP)
    port = sock.bind_to_random_port("tcp://127.0.0.1")
    n = BackendSpec().rod.n_segments
    state = {"type": "state", "step": 0, "time": 0.0, "diverged": False, "tracked": True,
             "positions": [[0.05 * i, 0.0, 0.5] for i in range(n)],
             "quaternions": [[1.0, 0.0, 0.0, 0.0]] * n,
             "grippers": [[0.0, 0.0, 0.5, 1, 0, 0, 0], [0.9, 0.0, 0.5, 1, 0, 0, 0]],
             "late": 0, "dropped": 0} | state_changes  # fmt: skip
    welcome = {"type": "welcome", "protocol": protocol.PROTOCOL, "version": protocol.VERSION,
               "session": "s" * 32, "session_idle_s": 30.0,
               "cell": {"name": "liar", "backend": None, "control_dt": 0.02, "realtime": False,
                        "n_segments": n}}  # fmt: skip
    stop = threading.Event()

    def answer() -> None:
        while not stop.is_set():
            if sock.poll(50):
                kind = json.loads(sock.recv())["type"]
                sock.send(json.dumps(welcome if kind == "hello" else state).encode())

    thread = threading.Thread(target=answer, daemon=True)
    thread.start()
    try:
        yield f"tcp://127.0.0.1:{port}"
    finally:
        stop.set()
        thread.join()
        sock.close()
        context.term()


@pytest.mark.parametrize(
    "changes, problem",
    [({"late": "many"}, "late"), ({"positions": [[0.0, 0.0, float("nan")]] * 20}, "positions"),
     ({"positions": [[0.0, 0.0, 0.0]] * 3}, "3 positions"), ({"step": 7}, "someone else"),
     ({"type": "snapshot", "state": [1.0]}, "snapshot where a state belongs")],
)  # fmt: skip
def test_a_controller_believes_no_reply_that_breaks_the_protocol(changes, problem):
    from dlocli import make_env
    from dlocli.bridge.remote import CellLost

    with lying_cell(changes) as address, pytest.raises(CellLost, match=problem):
        make_env(MUJOCO_ROD, "single", seed=0, render_mode=None, episode_steps=5,
                 reset_motion_steps=2, reset_settle_steps=2, cell=address)  # fmt: skip


def test_a_controller_killed_mid_run_frees_its_cell_after_the_idle_time(
    near_rest_goal, sac_policy, tmp_path, capsys
):
    here, there = tmp_path / "here", tmp_path / "there"
    assert run_dlo(control_argv(near_rest_goal, sac_policy, here)) == 0
    killed = control_argv(near_rest_goal, sac_policy, tmp_path / "killed", steps=400)
    killed.remove("--json")  # its progress lines say when the steps have begun
    # long enough for the controller's imports between its hello and its first reset
    with served("--session-idle-s", "8", "--delay-ms", "10") as address:
        control = stepping_controller(killed, address)
        control.kill()
        control.communicate(timeout=60)
        started = time.monotonic()
        argv = control_argv(near_rest_goal, sac_policy, there, "--cell", address)
        assert run_dlo(argv) == 2  # the dead controller's session still owns the cell
        line = capsys.readouterr().err.strip()
        assert "is busy" in line and "wait" in line and len(line.splitlines()) == 1, line
        assert not there.exists()
        time.sleep(max(0.0, 8.5 - (time.monotonic() - started)))
        assert run_dlo(argv) == 0  # the cell freed itself (and stopped the grippers)
    assert step_errors(there) == step_errors(here)


def test_a_robot_whose_own_code_fails_answers_cell_fault_and_serves_on():
    """The robot's driver raising inside a request is the cell's fault, said in one reply:
    the serving loop (the one the example and `dlo serve` share) goes on."""
    import runpy

    from dlocli.bridge.server import CellServer, Logged

    robot_cell = runpy.run_path(str(EXAMPLE))["RobotCell"]

    class Jammed(robot_cell):
        jam = True

        def move(self, velocities):
            if self.jam:
                raise RuntimeError("joint 3 over torque")
            super().move(velocities)

    robot = Jammed()
    events = []
    server = CellServer(robot, progress=events.append)

    def ask(kind: str, **fields) -> dict:
        return json.loads(server.answer([json.dumps({"type": kind, **fields}).encode()]))

    from dlocli.bridge import protocol

    token = ask("hello", protocol=protocol.PROTOCOL, version=protocol.VERSION,
                backend=robot.backend, control_dt=robot.control_dt)["session"]  # fmt: skip
    assert ask("reset", session=token, seed=0)["step"] == 0
    fault = ask("step", session=token, velocities=STILL)
    assert fault["code"] == "cell_fault" and "joint 3 over torque" in fault["message"], fault
    faults = [e.line for e in events if isinstance(e, Logged) and "failed on a Step" in e.line]
    assert len(faults) == 1 and "joint 3 over torque" in faults[0], events  # the log says it
    robot.jam = False
    assert ask("step", session=token, velocities=STILL)["step"] == 1
    assert ask("set_state", session=token, state=[0.0])["code"] == "refused"
    assert ask("bye", session=token)["type"] == "bye"
    assert ask("stop", session=token)["code"] == "no_session"
