"""The specs of models, their fitting and evaluation (torch-free: the CLI builds its --help
without importing torch)."""

from __future__ import annotations

from pathlib import Path
from typing import Any, Literal

from pydantic import Field

from dlocli.limits import MAX_COUNT, MAX_SEED
from dlocli.specs import Spec


class ModelSpec(Spec):
    """Which dynamics model, and its sizes (paper defaults)."""

    name: str = Field("in-bilstm", description="Dynamics model (see `dlo list`).")
    velocity_input: bool = Field(
        True,
        description="Also give the model each segment's change over the previous control step "
        "(a finite-difference velocity): the rod has inertia, so position and orientation "
        "alone do not determine its next state.",
    )
    absolute_position: bool = Field(
        True,
        description="in-bilstm: give f_e and f_v each segment's absolute position (the paper's "
        "encoding). Off, the segments' own features are orientation and velocity, and "
        "positions enter only as neighbour differences: the model is then exactly "
        "translation-invariant, as a rod without contacts is.",
    )
    hidden: int = Field(
        150, gt=0, le=8192, description="Width of every hidden layer and of the LSTM."
    )
    edge_layers: int = Field(
        4, gt=0, le=64, description="Layers of the relation-centric network f_e."
    )
    node_layers: int = Field(
        4, gt=0, le=64, description="Layers of the object-centric network f_v."
    )
    lstm_layers: int = Field(
        2, gt=0, le=64, description="Layers of the bidirectional LSTM along the rod."
    )
    mlp_layers: int = Field(4, gt=0, le=64, description="Hidden layers of the `mlp` baseline.")
    mlp_hidden: int = Field(
        512, gt=0, le=65536, description="Width of the `mlp` baseline's hidden layers."
    )
    length_projection: int = Field(
        0, ge=0, le=50,
        description="Marker form (recorded cables): sweeps projecting every predicted frame "
        "onto the distances between neighbouring markers of the rollout's first frame (a "
        "cable does not stretch); 0: none.",
    )  # fmt: skip


class FitSpec(Spec):
    """How to fit a model (also used by the online loop to continue training)."""

    schedule: Literal["epochs", "steps"] = Field(
        "epochs",
        description='How a model update trains. "epochs" (the paper\'s): `epochs` passes over '
        'all the data, so in the online loop each update costs more than the last. "steps": '
        "`update_steps` gradient steps on mini-batches drawn from all the data, "
        "`recent_fraction` of each from the episodes added since the previous update, "
        "continuing from the previous weights and Adam state, stopped early on the validation "
        "split (the best weights are kept): a fixed cost per update, whatever the data's size. "
        "`dlo train` trains by epochs.",
    )
    epochs: int = Field(
        50, ge=0, le=MAX_COUNT, description='Passes over the training transitions (schedule "epochs").'
    )
    update_steps: int = Field(
        2000, gt=0, le=MAX_COUNT, description='Schedule "steps": most gradient steps per model update.'
    )
    recent_fraction: float = Field(
        0.5, ge=0, le=1,
        description="Schedule \"steps\": share of each mini-batch drawn from the transitions "
        "added since the previous update (when there are any; the rest is drawn from all).",
    )  # fmt: skip
    eval_every: int = Field(
        100, gt=0, le=MAX_COUNT, description='Schedule "steps": gradient steps between validations.'
    )
    patience: int = Field(
        5, ge=0, le=MAX_COUNT,
        description="Schedule \"steps\": stop after this many validations without a lower "
        "validation loss, and keep the best weights (0: never stop early).",
    )  # fmt: skip
    val_transitions: int = Field(
        4096, gt=0, le=MAX_COUNT,
        description="Schedule \"steps\": most validation transitions per validation (a fixed "
        "random subset per update), so validating costs the same as the data grows.",
    )  # fmt: skip
    lr: float = Field(1e-4, gt=0, description="Adam learning rate.")
    batch_size: int = Field(64, gt=0, le=MAX_COUNT, description="Transitions per gradient step.")
    input_noise: float = Field(
        0.1, ge=0,
        description="Std of Gaussian noise on the input state (paper Sec. IV-C), in units of "
        "each feature's one-step change std; the target is the change from the noisy state.",
    )  # fmt: skip
    # small: noise on the state also corrupts the velocity input read from it
    val_fraction: float = Field(
        0.1, ge=0, lt=1, description="Fraction of trajectories held out for validation."
    )
    device: str = Field("auto", description="Torch device: auto, cpu, cuda or cuda:K.")
    seed: int = Field(
        0, ge=0, le=MAX_SEED, description="Seed of initialisation, shuffling and noise."
    )
    mirror: bool = Field(
        True,
        description="Also train on every training transition's mirrored twin: the same motion "
        "with the other end of the rod acting (a half turn about the vertical axis, ends "
        "swapped; see dlocli/models/mirror.py). Teaches a model learned with one gripper what "
        "the other one does (it then controls two: examples/bimanual_transfer); validation "
        "stays on the recorded data. Doubles an epoch's rows (the steps schedule: same cost). "
        "Not applied to data whose right end is free (held_ends=left): its twin would be "
        "another rod.",
    )
    rollout_steps: int = Field(
        1, ge=1, le=1000,
        description="Train through k-step open-loop rollouts (k = this; 1: one-step, the "
        "paper's). Marker datasets (recorded cables) only: a model that must predict seconds "
        "open loop learns to keep its own errors small. Marker training counts gradient "
        "steps (`update_steps`), validating every `eval_every`.",
    )  # fmt: skip
    rollout_start: int = Field(
        4, ge=1, le=1000, description="k of the first gradient step; it grows geometrically."
    )
    rollout_ramp: float = Field(
        0.5, ge=0, le=1,
        description="Share of the gradient steps over which k grows from rollout_start to "
        "rollout_steps.",
    )  # fmt: skip


class TrainSpec(FitSpec):
    """`dlo train`: fit a dynamics model to a dataset; write a run directory."""

    data: Path | None = Field(None, description="Dataset file or collect run directory.")
    model: ModelSpec = Field(default_factory=ModelSpec, description="Model and sizes.")
    init_from: Path | None = Field(
        None, description="Checkpoint or run directory to continue training from."
    )
    out: Path = Field(Path("runs/train"), description="Run directory for the results.")
    # smaller than the online loop's: at lr 1e-4 the deep f_e -> LSTM -> f_v path needs the
    # extra steps within 50 epochs (README, model accuracy)
    batch_size: int = Field(16, gt=0, le=MAX_COUNT, description="Transitions per gradient step.")


class EvalSpec(Spec):
    """`dlo eval`: a trained model's one-step and open-loop errors on a dataset."""

    checkpoint: Path | None = Field(
        None, description="Trained dynamics model: a .pt file or a `dlo train` run directory."
    )
    data: Path | None = Field(
        None, description="Dataset file or collect run directory; every episode is evaluated."
    )
    device: str = Field("auto", description="Torch device: auto, cpu, cuda or cuda:K.")
    max_starts: int = Field(
        512, gt=0, le=MAX_COUNT, description="Most start states per rollout horizon (evenly spread)."
    )
    plot: Path | None = Field(
        None, description="Also write a PNG of the predicted vs true rod over a rollout of the "
        "first episode.",
    )  # fmt: skip
    out: Path | None = Field(
        None, description="Run directory for spec.json and summary.json (none: print only)."
    )


#: ModelSpec fields added after models and runs were first saved, with the value that
#: rebuilds what was saved before the field existed
LEGACY_VALUES: dict[str, Any] = {
    "velocity_input": False,
    "absolute_position": True,
    "length_projection": 0,
}
#: FitSpec fields added after runs were first saved, with the value that rebuilds what a saved
#: run did before the field existed
FIT_LEGACY_VALUES: dict[str, Any] = {
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
}


def with_legacy_fields(saved: Any) -> Any:
    """A saved model spec (dict) with the fields it predates set to their legacy values."""
    if not isinstance(saved, dict):
        return saved
    return {**{k: v for k, v in LEGACY_VALUES.items() if k not in saved}, **saved}
