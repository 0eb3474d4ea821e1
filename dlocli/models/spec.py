"""The specs of models, their fitting and evaluation (torch-free: the CLI builds its --help
without importing torch)."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Any, ClassVar, Literal

from pydantic import (
    BeforeValidator,
    Field,
    SerializeAsAny,
    ValidationInfo,
    field_validator,
    model_validator,
)

from dlocli.limits import MAX_COUNT, MAX_SEED
from dlocli.migrations import RETIRED_TRAIN_FIELDS, model_data, without_retired_train_fields
from dlocli.registry import models
from dlocli.specs import MODEL_OPTIONS, Device, RetiredField, Spec, is_given, new_default


class ModelSpec(Spec):
    """What every dynamics model has; a model's own options are the fields of its spec, a
    subclass of this one (the model class's ``spec_cls``)."""

    name: str = Field("in-bilstm", description="Dynamics model (see `dlo list`).")
    velocity_input: bool = Field(
        True,
        description="Also give the model each segment's change over the previous control step "
        "(a finite-difference velocity): the rod has inertia, so position and orientation "
        "alone do not determine its next state.",
    )
    hidden: int = Field(150, gt=0, le=8192, description="Width of every hidden layer of the model.")
    members: int = Field(
        1, ge=1, le=64,
        description="Independently trained copies of the network (seeds seed, seed+1, ...), "
        "their predictions averaged: an ensemble holds long rollouts closer than one network. "
        "`dlo train` on marker or rod datasets (not the online loop); the copies train in "
        "parallel, one per core.",
    )  # fmt: skip
    cable_code: int = Field(
        0, ge=0, le=64,
        description="Marker form: width of a code learned per training cable (0: none). Trained "
        "on several cables, the model learns each one's code beside its weights (a cable's "
        "shape does not tell its stiffness and mass); `--init-from` on a new cable learns its "
        "code; a cable it never saw gets the mean code. In an ensemble each member learns its "
        "own codes.",
    )  # fmt: skip
    length_projection: int = Field(
        0, ge=0, le=50,
        description="Marker form (recorded cables): sweeps projecting every predicted frame "
        "onto the distances between neighbouring markers of the rollout's first frame (a "
        "cable does not stretch); 0: none.",
    )  # fmt: skip

    @classmethod
    def saved_layout(cls, data: Any) -> Any:
        """A saved model spec (as data) without the fields of other models that the flat
        layout, one spec shared by every model, saved with it."""
        name = data.get("name", cls.model_fields["name"].default) if isinstance(data, dict) else 0
        if not isinstance(name, str) or name not in models:
            return data  # validation names the problem
        own = model_spec_class(name)
        return model_data(data, set(own.model_fields), own.moved)

    @classmethod
    def field_of(cls, name: str) -> Any:
        """The field ``name`` of this spec, or else of the first registered model's spec
        that has it (a flag of a model's own option)."""
        if name in cls.model_fields:
            return cls.model_fields[name]
        for spec_cls in model_spec_classes().values():
            if name in spec_cls.model_fields:
                return spec_cls.model_fields[name]
        raise KeyError(name)


# the built-in models' own options (a plugin model may define its spec in its own module)
class INBiLSTMSpec(ModelSpec):
    """The sizes of the paper's model (its defaults); ``hidden`` is the width of f_e, f_v
    and the LSTM."""

    absolute_position: bool = Field(
        True,
        description="Give f_e and f_v each segment's absolute position (the paper's encoding). "
        "Off, the segments' own features are orientation and velocity, and positions enter "
        "only as neighbour differences: the model is then exactly translation-invariant, as a "
        "rod without contacts is.",
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


class MLPSpec(ModelSpec):
    """The baseline's sizes: ``layers`` hidden layers, ``hidden`` wide."""

    #: its options' names when every model shared one spec
    moved: ClassVar[dict[str, str]] = {"mlp_hidden": "hidden", "mlp_layers": "layers"}

    hidden: int = Field(512, gt=0, le=65536, description=ModelSpec.field_of("hidden").description)
    layers: int = Field(4, gt=0, le=64, description="Hidden layers of the MLP.")


class ArcMLPSpec(MLPSpec):
    """The MLP's sizes and the grid along the cable it reads and writes."""

    points: int = Field(
        16, ge=2, le=1024,
        description="Positions along the cable the MLP reads and writes; the nodes are "
        "interpolated onto them by arc position, so one network serves any node count "
        "(at least the largest count loses nothing).",
    )  # fmt: skip


class AttentionSpec(ModelSpec):
    """The attention model's sizes: ``encoder_layers`` layers of width ``hidden`` with
    ``heads`` heads."""

    hidden: int = Field(64, gt=0, le=4096, description=ModelSpec.field_of("hidden").description)
    encoder_layers: int = Field(3, gt=0, le=64, description="Transformer encoder layers.")
    heads: int = Field(4, gt=0, le=64, description="Attention heads per encoder layer.")

    @model_validator(mode="after")
    def _heads_divide_width(self) -> AttentionSpec:
        if self.hidden % self.heads:
            raise ValueError(f"hidden ({self.hidden}) must be a multiple of heads ({self.heads})")
        return self


def model_spec_classes() -> dict[str, type[ModelSpec]]:
    """The spec class of every registered model, by name."""
    return {name: model_spec_class(name) for name in models.names()}


def model_spec_class(name: str) -> type[ModelSpec]:
    """The spec class of the registered model ``name`` (UnknownName if there is none)."""
    return models.spec_cls(name) or ModelSpec


def model_spec(data: Any = None, context: dict[str, Any] | None = None) -> ModelSpec:
    """The spec of the model ``data`` names (a dict or spec; none: the default model), as
    its own spec class, options validated (ValidationError). With the context
    :data:`~dlocli.specs.GIVEN` (a spec the user gives) a renamed option is refused as retired."""
    if isinstance(data, ModelSpec):
        if type(data) is model_spec_class(data.name):
            return data
        data = data.model_dump(exclude_unset=True) | {"name": data.name}
    data = dict(data or {})
    name = data.get("name", ModelSpec.model_fields["name"].default)
    if not isinstance(name, str):
        return ModelSpec.model_validate(data)  # the error names the field
    cls = model_spec_class(name)
    return cls.model_validate(data, context=context)


def _as_model_spec(value: Any, info: ValidationInfo) -> Any:
    # an unknown name is not a ValueError: it leaves validation as UnknownName, whole
    return model_spec(value, info.context) if isinstance(value, dict | ModelSpec) else value


#: a field holding a model spec: validated as the spec of the model it names, saved whole
ModelField = Annotated[SerializeAsAny[ModelSpec], BeforeValidator(_as_model_spec)]


def model_field(description: str) -> Any:
    """The ``model`` field of a run spec (default: the default model at its defaults)."""
    return Field(default_factory=model_spec, description=description)


class FitSpec(Spec):
    """How to fit a model, by `dlo train` and by the online loop's updates."""

    epochs: int = Field(
        50,
        ge=0,
        le=MAX_COUNT,
        description="Passes over the training transitions: of `dlo train` on a rod dataset, and of "
        'each online update under schedule "epochs".',
    )
    update_steps: int = Field(
        2000,
        gt=0,
        le=MAX_COUNT,
        description="Gradient steps: of `dlo train` on a marker dataset, and most of each online "
        'update under schedule "steps".',
    )
    eval_every: int = Field(
        100,
        gt=0,
        le=MAX_COUNT,
        description="Gradient steps between validations, when training counts steps.",
    )
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
    device: Device = "auto"
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


class UpdateSpec(FitSpec):
    """How the online loop updates its model: a fit, and the schedule of each update."""

    schedule: Literal["epochs", "steps"] = Field(
        "epochs",
        description='How a model update trains. "epochs" (the paper\'s): `epochs` passes over '
        'all the data, so in the online loop each update costs more than the last. "steps": '
        "`update_steps` gradient steps on mini-batches drawn from all the data, "
        "`recent_fraction` of each from the episodes added since the previous update, "
        "continuing from the previous weights and Adam state, stopped early on the validation "
        "split (the best weights are kept): a fixed cost per update, whatever the data's size.",
    )
    recent_fraction: float = Field(
        0.5, ge=0, le=1,
        description="Schedule \"steps\": share of each mini-batch drawn from the transitions "
        "added since the previous update (when there are any; the rest is drawn from all).",
    )  # fmt: skip
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

    @property
    def unit(self) -> Literal["epoch", "step"]:
        """What an update counts: epochs or gradient steps."""
        return "step" if self.schedule == "steps" else "epoch"

    @property
    def length(self) -> int:
        """Epochs or gradient steps per update."""
        return self.update_steps if self.schedule == "steps" else self.epochs

    def times(self, updates: int) -> UpdateSpec:
        """This schedule, as long as ``updates`` updates."""
        field = "update_steps" if self.schedule == "steps" else "epochs"
        return self.model_copy(update={field: self.length * updates})


class TrainSpec(FitSpec):
    """`dlo train`: fit a dynamics model to a dataset; write a run directory."""

    cli_flags: ClassVar[tuple[str, ...]] = (
        "data", MODEL_OPTIONS, "epochs", "lr", "batch_size", "input_noise", "val_fraction",
        "mirror", "device", "seed", "init_from", "out", "update_steps", "rollout_steps",
        "rollout_start", "eval_every", "fine_tune",
    )  # fmt: skip
    cli_required: ClassVar[tuple[str, ...]] = ("data",)

    data: list[Path] | None = Field(
        None,
        description="Dataset file or collect run directory; repeat --data to train one model "
        "on several recorded cables (marker datasets from `dlo import`).",
    )
    model: ModelField = model_field("Model and sizes.")
    init_from: Path | None = Field(
        None, description="Checkpoint or run directory to continue training from."
    )
    fine_tune: Literal["all", "code"] = Field(
        "all",
        description='With --init-from on a model with cable codes: "all" trains its weights and '
        'the cable\'s code, "code" the code alone (a few numbers: a recording or two of a new '
        "cable suffice, and nothing else the model learned moves).",
    )
    out: Path = Field(Path("runs/train"), description="Run directory for the results.")
    # smaller than the online loop's: at lr 1e-4 the deep f_e -> LSTM -> f_v path needs the
    # extra steps within 50 epochs
    batch_size: int = Field(16, gt=0, le=MAX_COUNT, description="Transitions per gradient step.")

    @field_validator("data", mode="before")
    @classmethod
    def _one_or_more(cls, value: Any) -> Any:
        # one dataset, as runs saved before several could be given
        return [value] if isinstance(value, str | Path) else value

    @classmethod
    def saved_layout(cls, data: Any) -> Any:
        return super().saved_layout(without_retired_train_fields(data))

    @model_validator(mode="before")
    @classmethod
    def _retired_fields(cls, data: Any, info: ValidationInfo) -> Any:
        # saved runs drop them at the load boundary (saved_layout); a given spec is told why
        names = [k for k in RETIRED_TRAIN_FIELDS if isinstance(data, dict) and k in data]
        if names and is_given(info):
            why = (
                "an update field of the online loop, without effect in dlo train: it runs --epochs"
            )
            raise RetiredField(names[0], why=why)
        return data


class EvalSpec(Spec):
    """`dlo eval`: a trained model's one-step and open-loop errors on a dataset."""

    cli_flags: ClassVar[tuple[str, ...]] = (
        "checkpoint", "data", "device", "max_starts", "plot", "out",
    )  # fmt: skip
    cli_required: ClassVar[tuple[str, ...]] = ("checkpoint", "data")

    checkpoint: Path | None = Field(
        None, description="Trained dynamics model: a .pt file or a `dlo train` run directory."
    )
    data: Path | None = Field(
        None, description="Dataset file or collect run directory; every episode is evaluated."
    )
    device: Device = "auto"
    max_starts: int = Field(
        512,
        gt=0,
        le=MAX_COUNT,
        description="Most start states per rollout horizon (evenly spread).",
    )
    plot: Path | None = Field(
        None, description="Also write a PNG of the predicted vs true rod over a rollout of the "
        "first episode.",
    )  # fmt: skip
    out: Path | None = Field(
        None, description="Run directory for spec.json and summary.json (none: print only)."
    )


class AdaptSpec(FitSpec):
    """`dlo adapt`: a model with cable codes given a new cable's code from a few of its
    recordings; write a run directory with the adapted model."""

    cli_flags: ClassVar[tuple[str, ...]] = (
        "checkpoint", "data", "recordings", "fine_tune", "update_steps", "seconds", "lr",
        "rollout_steps", "batch_size", "eval_every", "device", "seed", "out",
    )  # fmt: skip
    cli_required: ClassVar[tuple[str, ...]] = ("checkpoint", "data")

    checkpoint: Path | None = Field(
        None,
        description="The model to adapt: a .pt file or `dlo train` run directory of a marker "
        "model with cable codes (--cable-code).",
    )
    data: Path | None = Field(
        None, description="The new cable: a marker dataset (`dlo import`); its train split is read."
    )
    recordings: int = Field(
        1, ge=1, le=MAX_COUNT,
        description="How many of the new cable's train recordings (its first ones) pick the "
        "code, and train it with --fine-tune.",
    )  # fmt: skip
    fine_tune: Literal["all", "code"] | None = Field(
        None,
        description='After the pick (none: the pick alone, no gradient step): "code" learns '
        'the new cable\'s code alone, "all" fine-tunes the whole model, within --update-steps '
        "and --seconds; the best weights on the recordings read stand (the pick among them).",
    )
    update_steps: int = Field(
        200, gt=0, le=MAX_COUNT,
        description="With --fine-tune: most gradient steps (it also stops at --seconds).",
    )  # fmt: skip
    seconds: float | None = Field(
        None, gt=0, le=86_400,
        description="With --fine-tune: also stop after this many seconds of training (none: "
        "--update-steps alone).",
    )  # fmt: skip
    lr: float | None = Field(
        None, gt=0,
        description="Adam learning rate of --fine-tune (none: 1e-2 for the code alone, 3e-4 for "
        "the whole model).",
    )  # fmt: skip
    rollout_steps: int = new_default(FitSpec, "rollout_steps", 64)
    rollout_start: int = new_default(FitSpec, "rollout_start", 64)
    batch_size: int = new_default(FitSpec, "batch_size", 32)
    eval_every: int = new_default(FitSpec, "eval_every", 50)
    out: Path = Field(Path("runs/adapt"), description="Run directory for the results.")

    @property
    def init_from(self) -> Path | None:
        """The model a fine-tune starts from: the fit keeps it where no step does better."""
        return self.checkpoint

    def fit_lr(self) -> float:
        """The learning rate of the fine-tune: ``lr``, else the default of its kind."""
        return self.lr if self.lr is not None else (1e-2 if self.fine_tune == "code" else 3e-4)

    @model_validator(mode="after")
    def _budget_needs_a_fine_tune(self) -> AdaptSpec:
        default = type(self).model_fields["update_steps"].default
        if self.fine_tune is None and (self.seconds is not None or self.update_steps != default):
            raise ValueError(
                "--update-steps and --seconds budget a fine-tune: add --fine-tune code (or "
                "all), or drop them"
            )
        return self
