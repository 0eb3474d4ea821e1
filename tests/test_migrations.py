"""Saved runs keep their meaning (dlocli.migrations): committed bench jobs are still finished
for `dlo bench --resume`, saved model specs of every layout build the model they built, and a
field added to a fingerprinted spec without a legacy value fails here."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch

from dlocli import migrations
from dlocli.bench.run import BenchRun
from dlocli.bench.spec import FREE_FIELDS, BenchSpec
from dlocli.controllers.mpc import MPCSpec
from dlocli.models.base import build_model
from dlocli.models.checkpoints import load_model, save_checkpoint
from dlocli.models.spec import TrainSpec, UpdateSpec, model_spec_classes
from dlocli.resume import load_saved_spec
from dlocli.specs import BackendSpec, RodSpec, TaskSpec, resolve_spec

from tiny import committed_bench

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"
#: committed benches whose jobs match the spec they were run with (bench_medium's jobs were
#: run before earlier changes of the mpc defaults: no fingerprint of them matched before
#: dlocli.migrations existed either)
BENCHES = ["bench_paper", "bench_bimanual", "bench_paper_mirror"]

#: the fields of each fingerprinted spec that have held since fingerprints were first
#: computed; any other field needs a legacy value (dlocli.migrations.LEGACY_VALUES)
ORIGINAL: dict[str, set[str]] = {
    "bench": {"backend", "task", "seed", "budget", "evals", "eval_trials", "options", "model",
              "fit", "mpc", "noise_probability", "noise_std", "transfer", "threads"},
    "backend": {"name", "physics_dt", "held_ends", "rod"},
    "rod": {"length", "n_segments", "radius", "density", "young_tension", "young_bending",
            "poisson"},
    "task": {"name", "goal", "goal_file", "episode_steps", "control_dt", "max_linear_velocity",
             "max_angular_velocity", "max_separation", "min_separation", "workspace_low",
             "workspace_high", "pose_offset_low", "pose_offset_high", "pose_max_rotation",
             "reset_motion_steps", "reset_settle_steps"},
    "fit": set(migrations.FIT_FIELD_ORDER) - set(migrations.LEGACY_VALUES["fit"]),
    "mpc": {"horizon", "replan_every", "action_cost", "warm_start", "iterations", "step_size",
            "optimizer", "max_step", "exact_gradient", "curvature_every", "restarts",
            "tolerance"},
    "pilco": {"n_keypoints", "action_repeat", "horizon", "initial_random_episodes",
              "max_gp_points", "gp_iterations", "n_basis", "policy_iterations", "policy_lr",
              "cost_width"},
    "sac": {"batch_size", "buffer_size", "device", "ent_coef", "gamma", "gradient_steps",
            "learning_rate", "learning_starts", "log_std_init", "net_arch", "sde_sample_freq",
            "tau", "train_freq", "use_sde"},
    "td3": {"action_noise", "batch_size", "buffer_size", "device", "gamma", "gradient_steps",
            "learning_rate", "learning_starts", "net_arch", "policy_delay", "target_noise_clip",
            "target_policy_noise", "tau", "train_freq"},
}  # fmt: skip


def fingerprinted_specs() -> dict[str, type]:
    """Every spec whose fields enter a bench job's fingerprint, by its kind in
    dlocli.migrations: the bench's own parts and the options of every agent that takes any."""
    from dlocli.bench.spec import option_agents
    from dlocli.registry import controllers

    own = {"bench": BenchSpec, "backend": BackendSpec, "rod": RodSpec, "task": TaskSpec,
           "fit": UpdateSpec, "mpc": MPCSpec}  # fmt: skip
    return own | {agent: controllers.get(agent).spec_cls for agent in option_agents()}


@pytest.mark.parametrize("bench", BENCHES)
def test_committed_bench_jobs_are_still_finished(bench, tmp_path):
    committed = committed_bench(bench, tmp_path / bench)
    spec = load_saved_spec(BenchSpec, committed / "spec.json")
    run = BenchRun(spec.model_copy(update={"out": committed}))
    jobs = sorted((committed / "jobs").glob("*.json"))
    assert jobs and run.jobs() == []  # --resume reruns none of them
    for job in jobs:
        saved = json.loads(job.read_text())
        assert run.finished(saved["agent"], saved["seed"]) is not None, job.name


@pytest.mark.parametrize("kind", sorted(fingerprinted_specs()))
def test_a_fingerprinted_field_needs_a_legacy_value(kind):
    fields = set(fingerprinted_specs()[kind].model_fields)
    fields -= FREE_FIELDS if kind == "bench" else set()
    missing = fields - ORIGINAL.get(kind, set()) - set(migrations.LEGACY_VALUES.get(kind, {}))
    assert not missing, (
        f"{kind} fields {sorted(missing)} enter bench fingerprints: give each the value that "
        "does what runs did before it existed in dlocli/migrations.py LEGACY_VALUES"
    )


#: the models registered after the flat layout, with the options they came with (no saved
#: spec of theirs lacks one); an option added to them later needs a legacy value
ORIGINAL_OPTIONS_OF_NEWER_MODELS: dict[str, set[str]] = {
    "attention": {"encoder_layers", "heads"},
    "arc-mlp": {"points"},
}


@pytest.mark.parametrize("name", sorted(model_spec_classes()))
def test_a_model_option_needs_a_legacy_value(name):
    """Model specs are fingerprinted in the flat layout of the one spec every model shared:
    an option outside it (or its new name) is new."""
    cls = model_spec_classes()[name]
    known = {*migrations.FLAT_MODEL_FIELDS, *cls.moved.values(), *migrations.LEGACY_VALUES["model"],
             *ORIGINAL_OPTIONS_OF_NEWER_MODELS.get(name, set())}  # fmt: skip
    assert set(cls.model_fields) <= known, (name, set(cls.model_fields) - known)


#: the model of each recipe as its real-cable runs' spec.json saved it: the flat layout
FLAT_SAVED_MODELS = {
    "in-bilstm.yaml": {"name": "in-bilstm", "velocity_input": True, "absolute_position": True,
                       "hidden": 64, "edge_layers": 2, "node_layers": 2, "lstm_layers": 1,
                       "mlp_layers": 4, "mlp_hidden": 512, "length_projection": 3},
    "mlp.yaml": {"name": "mlp", "velocity_input": True, "absolute_position": True, "hidden": 150,
                 "edge_layers": 4, "node_layers": 4, "lstm_layers": 2, "mlp_layers": 2,
                 "mlp_hidden": 256, "length_projection": 3},
}  # fmt: skip


@pytest.mark.parametrize(
    ("file", "expected"),
    [
        ("in-bilstm.yaml", {"hidden": 64, "lstm_layers": 1, "edge_layers": 2, "node_layers": 2}),
        ("mlp.yaml", {"hidden": 256, "layers": 2}),
    ],
)
def test_real_cable_specs_build_the_models_they_built(file, expected, tmp_path):
    """The spec files, given as a user gives them (today's names: a retired one is refused),
    build the models that the real-cable runs' spec.json built: theirs is the flat layout
    (`mlp_hidden`, `mlp_layers`, and the other models' fields), migrated where it is read."""
    spec = resolve_spec(TrainSpec, EXAMPLES / "real_cables" / file)
    assert {k: getattr(spec.model, k) for k in expected} == expected
    assert spec.model.length_projection == 3
    saved = tmp_path / "spec.json"
    saved.write_text(json.dumps({**spec.model_dump(mode="json"), "model": FLAT_SAVED_MODELS[file]}))
    assert load_saved_spec(TrainSpec, saved).model == spec.model


def test_a_checkpoint_of_the_flat_layout_loads(tmp_path):
    """An mlp saved when every model shared one spec: its width was `mlp_hidden`."""
    torch.manual_seed(0)
    model = build_model({"name": "mlp", "hidden": 12, "layers": 2}, 6)
    path = save_checkpoint(model, tmp_path / "m.pt")
    payload = torch.load(path, weights_only=True)
    flat = {**migrations.FLAT_MODEL_FIELDS, "name": "mlp", "mlp_hidden": 12, "mlp_layers": 2}
    payload["model_spec"] = flat
    torch.save(payload, path)
    again = load_model(path)
    assert again.spec == model.spec
    weights = zip(model.state_dict().values(), again.state_dict().values(), strict=True)
    assert all(torch.equal(a, b) for a, b in weights)


def test_validation_migrates_no_layout():
    """Migrations run where saved data is read (run spec.json, checkpoints), not on
    every validation: a flat-layout field given to a spec directly is an unknown field."""
    from pydantic import ValidationError

    with pytest.raises(ValidationError, match="mlp_hidden"):
        TrainSpec.model_validate({"model": {"name": "in-bilstm", "mlp_hidden": 512}})
    with pytest.raises(ValidationError, match="recent_fraction"):
        TrainSpec.model_validate({"recent_fraction": 0.5})
    flat = {"model": {"name": "in-bilstm", "mlp_hidden": 512}, "recent_fraction": 0.5}
    assert TrainSpec.model_validate(TrainSpec.saved_layout(flat)).model == TrainSpec().model
