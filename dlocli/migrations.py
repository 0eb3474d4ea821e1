"""Saved runs, checkpoints and bench jobs keep their meaning when a spec changes: every value
and layout that rebuilds what was saved before a change, in one place.

A field added to a spec that enters a bench job's fingerprint needs an entry in
:data:`LEGACY_VALUES`: the value that does what runs did before the field existed. A saved
spec that lacks the field is completed with it, and a job whose spec holds it keeps its
fingerprint (the field is left out). ``tests/test_migrations.py`` fails on a field added
without one.

Applied only where saved data is read: run spec.json, resumed or given with ``--spec``
(:meth:`dlocli.specs.Spec.saved_layout`, :func:`dlocli.resume.saved_spec`), checkpoints
(:func:`dlocli.models.checkpoints.checkpoint_spec`) and bench fingerprints
(:func:`dlocli.bench.spec.fingerprint`); validating a spec migrates nothing, and a spec the
user writes (:data:`dlocli.specs.GIVEN`) is told a retired field's replacement instead.
"""

from __future__ import annotations

from typing import Any

#: per spec kind (the bench spec's field, or an agent's name for its options), the fields
#: added after runs were first saved, with the value that rebuilds what a saved run did before
LEGACY_VALUES: dict[str, dict[str, Any]] = {
    "bench": {"planner": "mpc"},
    "model": {
        "velocity_input": False,
        "absolute_position": True,
        "length_projection": 0,
        "members": 1,
        "cable_code": 0,
    },
    "fit": {
        "mirror": False,
        "schedule": "epochs",
        "update_steps": 2000,
        "recent_fraction": 0.5,
        "eval_every": 100,
        "patience": 5,
        "val_transitions": 4096,
        "rollout_steps": 1,
        "rollout_start": 4,
        "rollout_ramp": 0.5,
    },
    "task": {
        "shapes": "near-rest",
        "recorded_poses": None,
        "observe_velocity": False,
        "envelope": {
            "max_linear_speed": None,
            "max_angular_speed": None,
            "max_linear_acceleration": None,
            "max_angular_acceleration": None,
            "stop_after_lost_s": None,
            "left_low": None,
            "left_high": None,
            "right_low": None,
            "right_high": None,
        },
        "observation": {
            "kind": "full",
            "markers": 10,
            "marker_arc_lengths": None,
            "gripper_markers": 0.05,
            "noise_mm": 0.0,
            "latency_steps": 0,
            "dropout": 0.0,
            "occlusion_probability": 0.0,
            "occlusion_markers": 3,
            "occlusion_steps": 10,
            "camera": None,
            "tracker": None,
        },
    },
    "rod": {
        "clamp_compliance": "rigid",
        "bending_damping": None,
        "twist_damping": None,
        "air_damping": None,
    },
    "backend": {"gravity": 9.81},
    "mpc": {
        "refresh": "inline",
        "tracking": "estimate",
        "settle_steps": 0,
        "motion_cost": 0.0,
        "damping": 0.01,
        "jacobian": "full",
        "disturbance": "none",
        "disturbance_gain": 0.2,
        "servo_cost": 0.0,
        "roll_search": 0,
        "servo_above_mm": 0.0,
        "rest_roll": False,
    },
    "mppi": {
        "motion_cost": 0.0,
        "disturbance": "none",
        "disturbance_gain": 0.2,
        "servo_cost": 0.0,
        "roll_search": 0,
        "servo_above_mm": 0.0,
        "rest_roll": False,
    },
    "pilco": {"policy_scale_floor": 0.01},
}

#: the one model spec every model shared before each model owned its options: its fields in
#: their order, at their defaults (a model's fingerprint is still computed in this layout)
FLAT_MODEL_FIELDS: dict[str, Any] = {
    "name": "in-bilstm",
    "velocity_input": True,
    "absolute_position": True,
    "hidden": 150,
    "edge_layers": 4,
    "node_layers": 4,
    "lstm_layers": 2,
    "mlp_layers": 4,
    "mlp_hidden": 512,
    "length_projection": 0,
}

#: the fit fields in the order fingerprints hold them (that of the fit spec before the online
#: loop's update fields moved to a spec of their own)
FIT_FIELD_ORDER = (
    "schedule", "epochs", "update_steps", "recent_fraction", "eval_every", "patience",
    "val_transitions", "lr", "batch_size", "input_noise", "val_fraction", "device", "seed",
    "mirror", "rollout_steps", "rollout_start", "rollout_ramp",
)  # fmt: skip

#: fields of the online loop's update that `dlo train` specs held, without effect there, before
#: it offered only the fields it uses (dropped from its saved specs when schedule is "epochs")
RETIRED_TRAIN_FIELDS = ("schedule", "recent_fraction", "patience", "val_transitions")


def completed(kind: str, saved: dict[str, Any]) -> dict[str, Any]:
    """``saved`` (a spec of ``kind`` as data) with the fields it predates at their legacy
    values."""
    return {**LEGACY_VALUES.get(kind, {}), **saved}


def at_legacy_values(kind: str, data: dict[str, Any]) -> set[str]:
    """The fields of ``data`` (a spec of ``kind`` as data) that hold their legacy value."""
    legacy = LEGACY_VALUES.get(kind, {})
    return {k for k, v in data.items() if k in legacy and v == legacy[k]}


def without_legacy_values(kind: str, data: dict[str, Any]) -> dict[str, Any]:
    """``data`` less the fields at their legacy value: what a fingerprint holds."""
    dropped = at_legacy_values(kind, data)
    return {k: v for k, v in data.items() if k not in dropped}


def model_data(data: dict[str, Any], fields: set[str], moved: dict[str, str]) -> dict[str, Any]:
    """A saved model spec for a model whose own spec has ``fields`` (and renames ``moved``):
    without the other models' fields of the flat spec, which had no effect on it."""
    return {
        k: v for k, v in data.items() if k in fields or k in moved or k not in FLAT_MODEL_FIELDS
    }


def model_fingerprint_form(data: dict[str, Any], moved: dict[str, str]) -> dict[str, Any]:
    """A model spec (as data, of the model whose spec renames ``moved``) in the flat layout
    fingerprints were first computed in, less its fields at legacy values; fields no flat
    spec had follow."""
    own = dict(data)
    taken = set(moved.values())
    flat = {}
    for key, default in FLAT_MODEL_FIELDS.items():
        source = moved.get(key, None if key in taken else key)
        flat[key] = own.pop(source) if source in own else default
    return without_legacy_values("model", {**flat, **own})


def fit_fingerprint_form(data: dict[str, Any]) -> dict[str, Any]:
    """A fit spec (as data) in the field order fingerprints hold, less its fields at legacy
    values; fields added since follow."""
    ordered = {k: data[k] for k in FIT_FIELD_ORDER if k in data}
    return without_legacy_values("fit", {**ordered, **data})


def without_retired_train_fields(data: Any) -> Any:
    """A `dlo train` spec (as data) without the online loop's fields it once held."""
    if not isinstance(data, dict) or data.get("schedule", "epochs") != "epochs":
        return data
    return {k: v for k, v in data.items() if k not in RETIRED_TRAIN_FIELDS}
