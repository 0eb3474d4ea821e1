"""The robot bridge: `dlo control --cell` against a simulator served by `dlo serve` in another
process, over the dlocli-cell protocol (real ZeroMQ sockets, the real MuJoCo rod)."""

from __future__ import annotations

import subprocess
import sys
import time
from pathlib import Path

import pytest
from cells import control_argv as _control
from cells import example_cell, served, stepping_controller
from cells import step_errors as _errors
from cells import summary_of as _summary

from tiny import run_dlo

pytest.importorskip("zmq")


def test_a_bridged_run_equals_the_in_process_one(near_rest_goal, sac_policy, tmp_path):
    here, there = tmp_path / "here", tmp_path / "there"
    assert run_dlo(_control(near_rest_goal, sac_policy, here)) == 0
    with served() as address:
        assert run_dlo(_control(near_rest_goal, sac_policy, there, "--cell", address)) == 0
    assert _errors(there) == _errors(here)  # the CSV's decimal text: every digit
    assert len(_errors(here)) == 12
    for key in ("initial_error_mm", "final_error_mm", "cumulative_reward"):
        assert _summary(there)[key] == _summary(here)[key]
    assert _summary(there)["cell_late_steps"] == 0
    assert _summary(there)["cell_dropped_commands"] == 0
    assert "cell_late_steps" not in _summary(here)


def test_the_example_robot_cell_speaks_the_protocol(near_rest_goal, sac_policy, tmp_path):
    """The README's robot script, its robot calls left as shipped (dlocli's rod), equals an
    in-process run too."""
    here, there = tmp_path / "here", tmp_path / "there"
    assert run_dlo(_control(near_rest_goal, sac_policy, here)) == 0
    with example_cell() as address:
        # the default timeout: the script builds its rod before it listens
        assert run_dlo(_control(near_rest_goal, sac_policy, there, "--cell", address)) == 0
    assert _errors(there) == _errors(here)


def _through_cell(cell_flags: list[str], argv: list[str]) -> dict:
    """The summary of `dlo` ``argv`` run against a cell served with ``cell_flags``."""
    with served(*cell_flags) as address:
        assert run_dlo([*argv, "--cell", address]) == 0
    return _summary(Path(argv[argv.index("--out") + 1]))


def test_a_delayed_cell_counts_its_late_steps_and_the_run_finishes(
    near_rest_goal, sac_policy, tmp_path
):
    """20 ms of delay at 50 Hz: every reply comes after the next tick."""
    argv = _control(near_rest_goal, sac_policy, tmp_path / "run")
    summary = _through_cell(["--realtime", "--delay-ms", "20"], argv)
    assert summary["steps"] == 12
    assert summary["cell_late_steps"] >= 6, summary


def test_a_realtime_cell_counts_late_steps_from_the_first_step(
    near_rest_goal, sac_policy, tmp_path
):
    """40 steps of a controller that keeps up: no late step, whatever the run did between
    the reset and its first step; the steps' wall time is theirs, about 40 periods. (A 100 ms
    period leaves a busy shared test machine room; a SAC policy keeps up at 20 ms too.)"""
    period = ["--control-dt", "0.1"]
    argv = _control(near_rest_goal, sac_policy, tmp_path / "run", *period, steps=40)
    summary = _through_cell(["--realtime", *period], argv)
    assert summary["steps"] == 40
    assert summary["cell_late_steps"] == 0, summary
    # the clock starts at the first step, so 40 replies span 39 whole periods and a part
    assert 39 * 0.1 <= summary["steps_wall_s"] <= summary["wall_s"], summary


def test_a_command_three_periods_late_counts_late_once():
    """A controller that sleeps three periods before one step: that command is late once;
    the cell stepped the periods it missed with the held command (``step`` counts them)."""
    import json

    import zmq

    from dlocli.bridge import protocol
    from dlocli.specs import BackendSpec

    context = zmq.Context()
    sock = context.socket(zmq.REQ)
    sock.setsockopt(zmq.LINGER, 0)

    def ask(kind: str, **fields) -> dict:
        sock.send(json.dumps({"type": kind, **fields}).encode())
        assert sock.poll(10_000), kind
        return json.loads(sock.recv())

    still, period = [[0.0] * 6, [0.0] * 6], 0.1  # a period a busy test machine keeps up with
    with served("--realtime", "--control-dt", str(period)) as address:
        sock.connect(address)
        welcome = ask("hello", protocol=protocol.PROTOCOL, version=protocol.VERSION,
                      backend=BackendSpec().model_dump(mode="json"), control_dt=period)  # fmt: skip
        token = welcome["session"]
        ask("reset", session=token, seed=0)
        time.sleep(0.5)  # a controller's first plan: no period of the cell's yet
        states = [ask("step", session=token, velocities=still) for _ in range(5)]
        assert [s["step"] for s in states] == [1, 2, 3, 4, 5] and states[-1]["late"] == 0
        time.sleep(3 * period)
        state = ask("step", session=token, velocities=still)
        assert state["late"] == 1 and state["step"] >= 5 + 3, state
        state = ask("step", session=token, velocities=still)
        assert state["late"] == 1, state
        ask("bye", session=token)
    sock.close()
    context.term()


def test_dropped_commands_are_counted_and_the_run_finishes(near_rest_goal, sac_policy, tmp_path):
    argv = _control(near_rest_goal, sac_policy, tmp_path / "run")
    summary = _through_cell(["--drop-probability", "0.5", "--seed", "3"], argv)
    assert summary["steps"] == 12
    # counted since the reset: the start shape's motion goes through the cell too
    assert summary["cell_dropped_commands"] >= 1, summary


def test_a_cell_that_loses_tracking_stops_the_grippers(near_rest_goal, sac_policy, tmp_path):
    argv = _control(near_rest_goal, sac_policy, tmp_path / "run", "--stop-after-lost-s", "0.03")
    argv[argv.index("--steps") + 1] = "40"
    summary = _through_cell(["--frame-loss-probability", "0.6", "--seed", "1"], argv)
    assert summary["steps"] == 40 and 1 <= summary["clipped_tracking_lost"] < 40, summary


def test_a_killed_cell_ends_the_run_in_one_line_with_its_steps_kept(
    near_rest_goal, sac_policy, tmp_path
):
    out = tmp_path / "run"
    argv = _control(near_rest_goal, sac_policy, out, "--cell-timeout-s", "1")
    argv[argv.index("--steps") + 1] = "200"
    argv.remove("--json")  # its progress lines say when the steps have begun
    with served("--delay-ms", "20", kill=True) as address:  # ~25 ms a step: outlives the cell
        control = stepping_controller(argv, address)
    _, stderr = control.communicate(timeout=60)
    assert control.returncode == 1, stderr
    assert "Traceback" not in stderr
    last = stderr.strip().splitlines()[-1]
    assert "stopped answering" in last and "1 s" in last, stderr
    summary = _summary(out)
    assert 1 <= summary["steps"] < 200 and "stopped answering" in summary["stopped"]
    assert len(_errors(out)) == summary["steps"]


def test_no_cell_at_the_address_is_one_line_naming_the_timeout(
    near_rest_goal, sac_policy, tmp_path
):
    out = tmp_path / "run"
    argv = _control(near_rest_goal, sac_policy, out, "--cell", "tcp://127.0.0.1:9",
                    "--cell-timeout-s", "0.3")  # fmt: skip
    result = subprocess.run(
        [sys.executable, "-m", "dlocli.cli", *argv], capture_output=True, text=True, timeout=60
    )
    assert result.returncode == 2, result.stderr
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and "0.3 s" in lines[0] and "--cell-timeout-s" in lines[0]
    assert not out.exists()


def test_a_cell_of_another_rod_refuses_the_controller(near_rest_goal, sac_policy, tmp_path):
    out = tmp_path / "run"
    with served("--backend-rod-n-segments", "10") as address:
        argv = _control(near_rest_goal, sac_policy, out, "--cell", address)
        assert run_dlo(argv) == 2
    assert not out.exists()


@pytest.mark.parametrize(
    "flags, problem",
    [(["--cell", "localhost:5555"], "--cell: 'localhost:5555' is not a cell address"),
     (["--cell", "http://127.0.0.1:5555"], "--cell: 'http://127.0.0.1:5555' is not a cell"),
     (["--cell", "tcp://127.0.0.1:*"], "--cell: 'tcp://127.0.0.1:*' names no port"),
     (["--cell", "tcp://127.0.0.1:70000"], "a port is a number from 1 to 65535"),
     (["--cell", "tcp://127.0.0.1:1", "--cell-timeout-s", "0"], "--cell-timeout-s")],
)  # fmt: skip
def test_bad_cell_flags_are_one_line(near_rest_goal, sac_policy, tmp_path, flags, problem, capsys):
    out = tmp_path / "run"
    assert run_dlo(_control(near_rest_goal, sac_policy, out, *flags)) == 2
    assert problem in capsys.readouterr().err
    assert not out.exists()
