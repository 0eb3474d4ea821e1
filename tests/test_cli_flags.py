"""The CLI's flags come from the run specs: one name means one thing in every command."""

from __future__ import annotations

import importlib
import re
import subprocess
import sys
from collections import defaultdict
from typing import get_origin

from typer.testing import CliRunner

from dlocli.cli import COMMANDS, app
from dlocli.cli.flags import strip_none
from dlocli.specs import field_info

runner = CliRunner()


def spec_commands():
    for name, target in COMMANDS:
        module, _, attr = target.partition(":")
        command = getattr(importlib.import_module(module), attr)
        if hasattr(command, "spec_fields"):
            yield name, command


def test_every_run_command_offers_its_spec_and_flags_that_reach_its_fields():
    names = {name for name, _ in spec_commands()}
    assert {"goal", "collect", "train", "eval", "control", "online", "bench"} <= names
    for name, command in spec_commands():
        help_text = runner.invoke(app, [name, "--help"], env={"COLUMNS": "200"}).output
        for flag in ("--spec", "--json", "--out"):
            assert flag in help_text, (name, flag)
        for flag, dotted in command.spec_fields.items():
            assert f"--{flag} " in help_text, (name, flag)
            assert field_info(command.spec_cls, dotted).description, (name, dotted)


def test_one_flag_name_one_meaning():
    """A flag means one field of one type everywhere (a repeatable list of a type, as
    `dlo train --data A --data B`, means what the type does)."""
    meanings = defaultdict(set)
    for _, command in spec_commands():
        for flag, dotted in command.spec_fields.items():
            kind = strip_none(field_info(command.spec_cls, dotted).annotation)
            kind = kind.__args__[0] if get_origin(kind) is list else kind
            meanings[flag].add((dotted.split(".")[-1], str(kind)))
    mixed = {flag: sorted(m) for flag, m in meanings.items() if len(m) > 1}
    assert not mixed, mixed
    assert meanings["model"] == {("name", "<class 'str'>")}  # a trained model is --checkpoint


def test_flags_override_spec_fields(tmp_path):
    spec = tmp_path / "s.yaml"
    spec.write_text("task: {episode_steps: 7, shapes: near-rest}\nepisodes: 2\n")
    out = tmp_path / "run"
    res = runner.invoke(
        app, ["collect", "--spec", str(spec), "--steps", "5", "--out", str(out), "--json"]
    )
    assert res.exit_code == 0, res.output
    import json

    saved = json.loads((out / "spec.json").read_text())
    assert saved["task"]["episode_steps"] == 5 and saved["task"]["shapes"] == "near-rest"
    assert saved["episodes"] == 2


def test_version_and_python_dash_m():
    assert runner.invoke(app, ["--version"]).output.startswith("dlocli ")
    res = subprocess.run([sys.executable, "-m", "dlocli", "--version"], capture_output=True)
    assert res.returncode == 0 and res.stdout.decode().startswith("dlocli ")


def test_version_and_help_import_no_torch_or_simulator():
    """`dlo --version` and `dlo --help` load no command module (torch alone takes seconds)."""
    heavy = ["torch", "mujoco", "pybullet", "dlocli.cli.online"]
    for flag in ("--version", "--help"):
        script = (
            "import sys\n"
            f"sys.argv = ['dlo', '{flag}']\n"
            "from dlocli.cli import main\n"
            "try:\n    main()\nexcept SystemExit:\n    pass\n"
            f"print([m for m in {heavy!r} if m in sys.modules])\n"
        )
        res = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True)
        assert res.returncode == 0, res.stderr
        assert res.stdout.strip().splitlines()[-1] == "[]", (flag, res.stdout)
    help_text = runner.invoke(app, ["--help"]).output
    assert "online" in help_text and "Learn the dynamics model online" in help_text


def test_every_command_help_imports_no_torch_simulator_or_agents():
    """`python -m dlocli COMMAND --help` (each in turn, in one interpreter) imports none of
    the heavy libraries: flags, model options and controller options come from torch-free
    specs."""
    from dlocli.cli import ALIASES, COMMANDS

    heavy = ["torch", "mujoco", "pybullet", "ray", "stable_baselines3"]
    commands = [name for name, _ in COMMANDS] + list(ALIASES)
    script = (
        "import runpy, sys\n"
        f"for command in {commands!r}:\n"
        "    sys.argv = ['dlo', command, '--help']\n"
        "    try:\n        runpy.run_module('dlocli', run_name='__main__')\n"
        "    except SystemExit as exit:\n        assert exit.code in (0, None), command\n"
        f"print([m for m in {heavy!r} if m in sys.modules])\n"
    )
    res = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True)
    assert res.returncode == 0, res.stderr
    assert "--dataset-id" in res.stdout and "--hidden" in res.stdout  # the helps were shown
    assert res.stdout.strip().splitlines()[-1] == "[]", res.stdout[-300:]


def test_fields_that_moved_still_load():
    """Spec files and saved runs written before a field moved keep their meaning."""
    from dlocli.runs.control import ControlSpec
    from dlocli.specs import TaskSpec

    task = TaskSpec(goal_file="g.npy")
    spec = ControlSpec(task=task, model="m.pt", steps=30)
    assert spec.checkpoint.name == "m.pt" and spec.task.episode_steps == 30
    assert spec.task.goal_file.name == "g.npy" and task.episode_steps == 200


def test_os_errors_are_one_line(tmp_path):
    """A path the system refuses is one line and exit 2, never a traceback."""
    from dlocli.cli.common import os_error_line

    blocked = tmp_path / "file"
    blocked.write_text("not a directory")
    res = runner.invoke(app, ["collect", "--episodes", "1", "--out", str(blocked / "run")])
    assert res.exit_code == 2 and "Traceback" not in res.output, res.output
    assert len(res.output.strip().splitlines()) == 1
    assert "free space" in os_error_line(OSError(28, "No space left on device", "x.h5"))


def test_written_files_get_the_usual_permissions(tmp_path):
    """Atomic writes follow the umask like any other file (mkstemp alone gives 0600)."""
    import os

    from dlocli.io import write_text_atomic

    before = os.umask(0o022)
    try:
        write_text_atomic(tmp_path / "a.txt", "x")
    finally:
        os.umask(before)
    assert (tmp_path / "a.txt").stat().st_mode & 0o777 == 0o644


def help_of(*argv: str) -> str:
    return " ".join(runner.invoke(app, [*argv, "--help"], env={"COLUMNS": "200"}).output.split())


def test_help_tells_the_truth():
    """-o lists every option of every controller spec; required inputs say so, defaults show
    as Click shows them (factories' too); metavars are plain words; aliases are not listed."""
    from dlocli.controllers.mpc import MPCSpec
    from dlocli.controllers.mppi import MPPISpec

    control = help_of("control")
    for spec in (MPCSpec(), MPPISpec()):
        for key, value in spec.model_dump(mode="json").items():
            assert f"{key}={value}" in control, key
    assert "--goal PATH Goal shape" in control and "[required]" in control
    assert "[default: mpc]" in control
    assert "[required]" in help_of("train").split("--model")[0], "--data is required"
    assert "[default: zero,random," in help_of("bench"), "a factory default is shown"
    for name, _ in COMMANDS:
        text = help_of(name)
        assert "spec default" not in text and "(default:" not in text, name
        assert not re.search(r"-[\w-]+ <", text), f"{name}: a Python type as metavar"
    assert "[default: True]" not in help_of("collect")
    listing = help_of()
    assert " bench " in listing and "benchmark" not in listing
    assert runner.invoke(app, ["benchmark", "--help"]).exit_code == 0
