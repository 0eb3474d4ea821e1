"""The registries: every plugin kind registers its built-ins in its own package, and the
light stand-ins that answer without importing an entry tell the truth about it."""

from __future__ import annotations

import pytest

from dlocli import registry
from dlocli.backends.facts import BackendFacts
from dlocli.calibration.parameters import start_value
from dlocli.controllers.base import is_planner, references
from dlocli.errors import BadInput, UnknownName
from dlocli.runs.online import OnlineSpec
from dlocli.specs import BackendSpec, RodSpec

REGISTRIES = {"backends": registry.backends, "models": registry.models,
              "controllers": registry.controllers, "tasks": registry.tasks,
              "observers": registry.observers, "cells": registry.cells}  # fmt: skip


@pytest.mark.parametrize("kind", sorted(REGISTRIES))
def test_every_entry_is_what_its_stand_ins_say(kind):
    """An entry inherits its facts class, and its registered spec is its own."""
    found = REGISTRIES[kind]
    for name in found.names():
        entry = found.get(name)
        assert issubclass(entry, found.facts(name)), name
        if hasattr(entry, "spec_cls"):
            assert found.spec_cls(name) is entry.spec_cls, name


def test_controllers_say_what_they_are():
    assert list(references()) == ["zero", "random", "held-end"]
    assert [n for n in registry.controllers.names() if is_planner(n)] == ["mpc", "mppi"]


def test_a_run_spec_plans_with_a_registered_planner_only():
    assert type(OnlineSpec(planner="mppi").mpc).__name__ == "MPPISpec"
    with pytest.raises(UnknownName, match="controller 'sac' does not plan"):
        OnlineSpec(planner="sac")
    with pytest.raises(UnknownName, match="did you mean 'mpc'"):
        OnlineSpec(planner="mpx")


def test_the_backends_take_the_cell_client_from_the_registry(monkeypatch):
    """A run naming a cell gets the client the bridge registers for its protocol (the backends
    import no bridge)."""
    from dlocli.backends import CELL_PROTOCOL, make_backend
    from dlocli.bridge.protocol import PROTOCOL
    from dlocli.cell_spec import CellChoice

    assert CELL_PROTOCOL == PROTOCOL and registry.cells.names() == [PROTOCOL]
    assert registry.cells.get(PROTOCOL).__name__ == "RemoteCell"
    monkeypatch.setattr(registry.cells, "get", lambda name: lambda *args: (name, *args))
    made = make_backend(BackendSpec(), 0.02, CellChoice(cell="tcp://127.0.0.1:5555"))
    assert made[:4] == (PROTOCOL, BackendSpec(), 0.02, "tcp://127.0.0.1:5555")


def test_the_env_takes_its_observer_from_the_registry(monkeypatch):
    """The pointcloud observation's tracker is the observer registered for its kind (the env
    imports no tracker); the markers observation keeps the env's own faulty-marker tracker."""
    from dlocli.env.observation import Tracker, marker_tracker
    from dlocli.specs import ObservationSpec

    assert registry.observers.names() == ["pointcloud"]
    assert registry.observers.get("pointcloud").__name__ == "CloudObserver"

    class Stub:
        def __init__(self, *args):
            self.args = args

    monkeypatch.setattr(registry.observers, "get", lambda name: Stub)
    layout = [0, 1, 2]
    made = marker_tracker(ObservationSpec(kind="pointcloud"), layout, "backend", 0.02)
    assert isinstance(made, Stub) and made.args[1:4] == ("backend", layout, 0.02)
    assert isinstance(marker_tracker(ObservationSpec(kind="markers"), layout, None, 0.02), Tracker)


def test_a_backends_segment_limit_is_its_fact():
    assert registry.backends.facts("pybullet").max_segments == 31
    BackendSpec(name="pybullet", rod=RodSpec(n_segments=31))
    with pytest.raises(ValueError, match="at most 31 rod segments"):
        BackendSpec(name="pybullet", rod=RodSpec(n_segments=32))


def test_calibration_starts_from_what_the_backend_says_a_none_stands_for(monkeypatch):
    rod = RodSpec(air_damping=None)
    assert start_value("air_damping", rod, "pybullet") == 5.0
    monkeypatch.setattr(registry.backends, "facts", lambda name: BackendFacts)
    with pytest.raises(BadInput, match="does not say what rod.air_damping None stands for"):
        start_value("air_damping", rod, "mujoco")
