"""A backend's planner defaults: the options its rod's motion asks of a planner, taken by
every run that plans on it unless the run sets them, and saved in its resolved spec."""

from __future__ import annotations

import json

import pytest

from dlocli.backends.facts import SERVO_COST, BackendFacts, FlexFacts, MujocoFacts
from dlocli.bench.spec import BenchSpec
from dlocli.controllers.base import controller_spec
from dlocli.controllers.specs import MPCSpec
from dlocli.registry import backends
from dlocli.runs.online.spec import OnlineSpec

FIELDS = ("motion_cost", "damping", "servo_cost", "rest_roll")
PAPER = {field: getattr(MPCSpec(), field) for field in FIELDS}
FLEX = dict(FlexFacts.planner_defaults["mpc"])
CABLE = {**PAPER, **MujocoFacts.planner_defaults["mpc"]}


def planned(spec_cls: type, data: dict) -> dict[str, float]:
    spec = spec_cls.model_validate(data)
    return {field: getattr(spec.mpc, field) for field in FIELDS}


@pytest.mark.parametrize("spec_cls", [OnlineSpec, BenchSpec])
def test_each_rod_plans_with_its_defaults_pybullet_with_the_papers(spec_cls):
    assert FLEX == {
        "motion_cost": 32.0, "damping": 1.0, "servo_cost": SERVO_COST, "rest_roll": True,
    } != PAPER  # fmt: skip
    assert CABLE == {
        "motion_cost": 0.0, "damping": 0.01, "servo_cost": SERVO_COST, "rest_roll": False,
    }  # fmt: skip
    assert PAPER == {"motion_cost": 0.0, "damping": 0.01, "servo_cost": 0.0, "rest_roll": False}
    assert planned(spec_cls, {"backend": {"name": "mujoco-flex"}}) == FLEX
    assert planned(spec_cls, {"backend": {"name": "mujoco"}}) == CABLE
    assert planned(spec_cls, {"backend": {"name": "pybullet"}}) == PAPER


def test_what_a_run_sets_is_kept_and_the_resolved_spec_saves_it():
    spec = OnlineSpec.model_validate({"backend": {"name": "mujoco-flex"},
                                      "mpc": {"motion_cost": 0.0}})  # fmt: skip
    assert (spec.mpc.motion_cost, spec.mpc.damping) == (0.0, FLEX["damping"])
    saved = json.loads(spec.model_dump_json())
    assert saved["mpc"]["motion_cost"] == 0.0 and saved["mpc"]["damping"] == FLEX["damping"]
    again = OnlineSpec.model_validate(saved)
    assert again.mpc == spec.mpc
    # a spec saved on one rod, read for another, keeps what it saved
    saved["backend"]["name"] = "mujoco"
    assert OnlineSpec.model_validate(saved).mpc.damping == FLEX["damping"]


def test_a_planner_without_defaults_on_the_rod_gets_none():
    spec = OnlineSpec.model_validate({"backend": {"name": "mujoco-flex"}, "planner": "mppi"})
    assert spec.mpc.motion_cost == 0.0


def test_dlo_controls_options_take_the_backends_defaults():
    assert controller_spec("mpc", {}, "mujoco-flex").model_dump().items() >= FLEX.items()
    assert controller_spec("mpc", {"damping": 0.1}, "mujoco-flex").damping == 0.1
    assert controller_spec("mpc", {}, "mujoco").model_dump().items() >= CABLE.items()
    assert controller_spec("mpc", {}, "pybullet").model_dump().items() >= PAPER.items()
    assert controller_spec("zero", {}, "mujoco-flex") is None


def test_every_registered_backend_names_planner_options_that_exist():
    for name in backends.names():
        facts = backends.facts(name)
        assert issubclass(facts, BackendFacts)
        for planner, options in facts.planner_defaults.items():
            spec_cls = controller_spec(planner).__class__
            assert set(options) <= set(spec_cls.model_fields), (name, planner)
            spec_cls.model_validate(options)


def test_dlo_list_names_each_backends_planner_defaults():
    from typer.testing import CliRunner

    from dlocli.cli import app

    result = CliRunner().invoke(app, ["list", "--json"])
    assert result.exit_code == 0, result.output
    listed = json.loads(result.output)["backends"]
    assert listed["mujoco-flex"].endswith(
        "mpc plans with motion_cost 32, damping 1, servo_cost 0.001, rest_roll true unless a "
        "run sets them"
    )
    assert listed["mujoco"].endswith("mpc plans with servo_cost 0.001 unless a run sets them")
    assert "plans with" not in listed["pybullet"]


def test_make_controller_gives_unnamed_options_the_envs_defaults():
    import dlocli
    from dlocli.controllers.base import make_controller
    from dlocli.models import build_model
    from dlocli.models.spec import model_spec

    from tiny import MUJOCO_ROD

    model = build_model(model_spec({"hidden": 8, "edge_layers": 1, "node_layers": 1,
                                    "lstm_layers": 1}), 20)  # fmt: skip
    env = dlocli.make_env(MUJOCO_ROD, "single", seed=0, episode_steps=5)
    try:
        expected = CABLE if MUJOCO_ROD == "mujoco" else FLEX
        made = make_controller("mpc", env, model=model).spec
        assert {field: getattr(made, field) for field in FIELDS} == expected
        named = make_controller("mpc", env, options={"damping": 0.5}, model=model).spec
        assert (named.motion_cost, named.damping) == (expected["motion_cost"], 0.5)
        whole = make_controller("mpc", env, options=MPCSpec(), model=model).spec
        assert {field: getattr(whole, field) for field in FIELDS} == PAPER
    finally:
        env.close()


def test_help_says_a_backend_may_set_the_option():
    from dlocli.cli.flags import shown_default
    from dlocli.specs import field_info

    for field in FIELDS:
        shown = shown_default(field_info(MPCSpec, field), field, False)
        assert shown.endswith(", or the backend's planner default]"), shown
    assert shown_default(field_info(MPCSpec, "horizon"), "horizon", False) == "  [default: 5]"
