"""Model checkpoints: the one module that writes them, reads them and tells their forms apart.

A checkpoint (``.pt``, or a run directory's ``checkpoints/final.pt``) is a dict written by
``torch.save`` and read back with ``torch.load(weights_only=True)`` (nothing in it is
unpickled as code): ``format``/``format_version``, the model's spec (older layouts migrated
where it is read, :func:`dlocli.migrations.completed`), its segment or marker count, its
weights and normalisation buffers (``state_dict``), the versions that wrote it, the control
period of its training data (``control_dt``, absent in older ones) and what its writer adds
(an optimizer's state, an epoch, ...). Its ``form`` (:mod:`dlocli.data.format`) says which
view it holds its network in: ``"rod"`` (a :class:`~dlocli.models.base.DynamicsModel`;
checkpoints without the tag hold one) or ``"markers"`` (a
:class:`~dlocli.models.marker_model.MarkerModel`); it is written from the model and read in
:func:`checkpoint_form` only. Checkpoints written before the views held one network (format
version 3 and older) have their weights renamed and laid out for it where they are read
(:func:`current_weights`).

Loading refuses, in one line each: a file that is not a readable dlocli checkpoint, a form
the caller cannot use, a spec that is not a model's, weights that are not finite or do not
fit, and a marker model's scale that is not positive.
"""

from __future__ import annotations

import io
import pickle
import zipfile
from pathlib import Path
from typing import Any

import torch

from dlocli.data.format import MARKERS, ROD
from dlocli.errors import BadInput
from dlocli.io import versions, write_bytes_atomic
from dlocli.migrations import completed
from dlocli.models.base import ACTION_DIM, STATE_DIM, build_model, resolve_device, valid_model_spec
from dlocli.models.cable_codes import no_codes
from dlocli.models.marker_model import SCALES, build_marker_model
from dlocli.models.spec import ModelSpec

CHECKPOINT_FORMAT = "dlocli-checkpoint"
#: 2: model specs have velocity_input; 3: absolute_position; 4: one network inside a view
#: (weights under ``network.``)
CHECKPOINT_VERSION = 4
FINAL_CHECKPOINT = Path("checkpoints") / "final.pt"
#: the payload key of the control period (s) of the data a model learned from: one model step
#: is one such period (checkpoints written before it have none, and are taken as they are)
CONTROL_DT = "control_dt"
#: the payload key of the rod's rest states an online run's model learned beside
#: (:mod:`dlocli.controllers.rest_roll`): {"grippers": (R, 2, 7), "positions": (R, N, 3)}
REST_STATES = "rest_states"
#: the payload key of a marker model's cable keys, one per row of its codes (in order)
CABLE_KEYS = "cable_keys"
#: the payload key of the model's form, and the forms a checkpoint may hold
FORM_KEY = "form"
FORMS = (ROD, MARKERS)
#: how errors name a checkpoint read from bytes
IN_MEMORY = "the model checkpoint in memory"
#: why a checkpoint of one form is refused where the other is needed
_WRONG_FORM = {
    ROD: "{path} is a marker-form model (trained on recorded markers); use it with "
    "`dlo eval` on a marker dataset",
    MARKERS: "{path} is a rod model; evaluate it on a rod dataset (`dlo collect`)",
}


# ---------------------------------------------------------------------- writing
def save_checkpoint(
    model: torch.nn.Module, path: Path, extra: dict[str, Any] | None = None
) -> Path:
    """Write weights, model spec, form, normalisation and versions atomically to ``path``.

    ``extra`` must hold only what ``torch.load(weights_only=True)`` accepts (tensors, numbers,
    strings, lists, dicts: e.g. an optimizer's ``state_dict()``).
    """
    payload = {
        **(extra or {}),
        "format": CHECKPOINT_FORMAT,
        "format_version": CHECKPOINT_VERSION,
        FORM_KEY: model_form(model),
        "model_spec": model.spec.model_dump(mode="json"),
        "n_segments": model.n_segments,
        "state_dict": {k: v.detach().cpu() for k, v in model.state_dict().items()},
        "versions": versions(),
    }
    image = io.BytesIO()  # serialise in memory: a full disk is then one clean OSError
    torch.save(payload, image)
    path = Path(path)
    write_bytes_atomic(path, image.getbuffer())  # a view: no second copy
    return path


def model_form(model: torch.nn.Module) -> str:
    """The form of ``model``: its class's ``form`` (a marker model's), else the rod's."""
    return getattr(model, "form", ROD)


# ---------------------------------------------------------------------- reading
def checkpoint_path(path: Path) -> Path:
    """A checkpoint file, or a run directory's ``checkpoints/final.pt``."""
    path = Path(path)
    if path.is_dir():
        final = path / FINAL_CHECKPOINT
        if not final.is_file():
            raise BadInput(f"run directory {path} has no {FINAL_CHECKPOINT}; run `dlo train`")
        return final
    if not path.is_file():
        raise BadInput(f"model checkpoint {path} does not exist; pass a .pt file or run directory")
    return path


def read_checkpoint(path: Path) -> dict[str, Any]:
    """The checkpoint's payload (CPU tensors), loaded with ``weights_only=True``; BadInput if
    it is not a dlocli checkpoint."""
    path = checkpoint_path(path)
    return _checked_payload(path, path)


def read_checkpoint_bytes(checkpoint: bytes) -> dict[str, Any]:
    """:func:`read_checkpoint` of a checkpoint file's bytes."""
    return _checked_payload(io.BytesIO(checkpoint), IN_MEMORY)


def _checked_payload(source: Path | io.BytesIO, path: Path | str) -> dict[str, Any]:
    """The payload of the checkpoint in ``source`` (a file, or its bytes), named ``path`` in
    errors."""
    try:
        if not zipfile.is_zipfile(source):  # what torch.save writes; a text file fed to
            raise zipfile.BadZipFile  # torch's loader for older checkpoints fails unforeseen
        if isinstance(source, io.BytesIO):
            source.seek(0)  # is_zipfile read it
        payload = torch.load(source, map_location="cpu", weights_only=True)
    except (RuntimeError, pickle.UnpicklingError, EOFError, OSError, ValueError,
            zipfile.BadZipFile) as exc:  # fmt: skip
        # torch's text is pages long (a weights_only tutorial); ours says what to pass instead
        raise BadInput(
            f"{path} is not a readable model checkpoint (torch.load with weights_only=True "
            "refused it); pass a .pt file written by `dlo train`, or its run directory"
        ) from exc
    if not isinstance(payload, dict) or payload.get("format") != CHECKPOINT_FORMAT:
        raise BadInput(f"{path} is not a dlocli model checkpoint; pass one written by `dlo train`")
    if not isinstance(payload.get("state_dict"), dict) or not isinstance(
        payload.get("n_segments"), int
    ):
        raise BadInput(f"checkpoint {path} lacks weights or segment count; retrain it")
    return payload


def checkpoint_form(payload: dict[str, Any], path: Path | str) -> str:
    """The form of the model a checkpoint's payload holds (the rod's where it has no tag:
    written before marker models existed); BadInput for a tag this dlocli does not know."""
    form = payload.get(FORM_KEY, ROD)
    if form not in FORMS:
        raise BadInput(
            f"checkpoint {path} holds a model of form {str(form)[:40]!r}, not one of "
            f"{', '.join(FORMS)}; pass one written by this dlocli's `dlo train`"
        )
    return form


def checkpoint_spec(payload: dict[str, Any], path: Path | str) -> ModelSpec:
    """The model spec a checkpoint's payload holds (older ones' layout migrated, their
    missing fields at their legacy values); BadInput if it is not one."""
    saved = payload.get("model_spec")
    if not isinstance(saved, dict):
        raise BadInput(f"checkpoint {path} holds no model spec; retrain it")
    saved = ModelSpec.saved_layout(completed("model", saved))
    return valid_model_spec(saved, f"checkpoint {path} model spec")


# ---------------------------------------------------------------------- loading models
def load_model(
    source: Path | bytes,
    device: str | torch.device = "cpu",
    expect: ModelSpec | None = None,
    form: str | None = ROD,
) -> Any:
    """A trained model from a checkpoint or run directory (or a checkpoint file's bytes), in
    eval mode on ``device``.

    Its parameters are frozen (``requires_grad`` False), so a planner's backward pass
    computes gradients for the actions only; training unfreezes them.
    ``expect``: the model spec the caller asked for; a different one in the file is refused.
    ``form``: the form the caller uses (a checkpoint of another is refused); None: either.
    """
    if isinstance(source, bytes):
        return model_from_payload(read_checkpoint_bytes(source), IN_MEMORY, device, expect, form)
    return model_from_payload(read_checkpoint(source), source, device, expect, form)


def load_model_bytes(checkpoint: bytes, device: str | torch.device = "cpu") -> Any:
    """:func:`load_model` of a checkpoint file's bytes (a trial's copy of the driver's model),
    read in memory."""
    return load_model(checkpoint, device)


def load_marker_model(path: Path, device: str | torch.device = "cpu") -> Any:
    """A trained marker-form model (:func:`load_model` of form ``"markers"``)."""
    return load_model(path, device, form=MARKERS)


def load_planning_model(source: Path | bytes, device: str | torch.device = "cpu") -> Any:
    """A model a planner plans with, from a checkpoint (a path, or a file's bytes): the rod or
    the marker model it holds."""
    return load_model(source, device, form=None)


def model_from_payload(
    payload: dict[str, Any],
    path: Path | str,
    device: str | torch.device = "cpu",
    expect: ModelSpec | None = None,
    form: str | None = ROD,
) -> Any:
    """The model a checkpoint's payload holds (named ``path`` in errors); see
    :func:`load_model`."""
    held_form = checkpoint_form(payload, path)
    if form is not None and held_form != form:
        raise BadInput(_WRONG_FORM[form].format(path=path))
    spec = checkpoint_spec(payload, path)
    if expect is not None and valid_model_spec(expect) != spec:
        raise BadInput(
            f"checkpoint {path} holds model {spec.model_dump()} but {expect.model_dump()} "
            "was requested; pass the matching --model or another checkpoint"
        )
    payload = {**payload, "state_dict": current_weights(payload, spec, held_form)}
    if held_form == ROD:
        return with_weights(build_model(spec, payload["n_segments"]), payload, path, device)
    held = payload["state_dict"].get("held")
    if not torch.is_tensor(held) or held.dtype != torch.bool or held.dim() != 1:
        raise BadInput(f"checkpoint {path} lacks its held-marker mask; retrain it")
    if spec.cable_code and "codes" not in payload["state_dict"]:  # none learned yet
        weights = {**payload["state_dict"], "codes": no_codes(spec.cable_code, spec.members)}
        payload = {**payload, "state_dict": weights}
    model = build_marker_model(spec, len(held), held.numpy())
    model.add_cables(_cable_keys(payload, path))
    model = with_weights(model, payload, path, device)
    _check_scales(model, path)
    return model


def _cable_keys(payload: dict[str, Any], path: Path | str) -> list[str]:
    """The keys of the cables whose codes the checkpoint holds; BadInput where they and the
    codes disagree."""
    keys = payload.get(CABLE_KEYS, [])
    codes = payload["state_dict"].get("codes")
    rows = codes.shape[0] if torch.is_tensor(codes) and codes.dim() >= 2 else 0
    if not rows:
        return []
    if not isinstance(keys, list) or len(keys) != rows or len(set(keys)) != rows:
        raise BadInput(f"checkpoint {path} holds {rows} cable codes but not their keys; retrain it")
    return [str(k) for k in keys]


def with_weights(
    model: torch.nn.Module, payload: dict[str, Any], path: Path | str, device: str | torch.device
) -> Any:
    """``model`` with the checkpoint's finite weights, on ``device``, in eval mode, frozen,
    with the control period it learned at (``model.control_dt``); BadInput if they are not
    finite or do not fit."""
    weights = payload["state_dict"].values()
    if not all(torch.is_tensor(w) and bool(torch.isfinite(w).all()) for w in weights):
        raise BadInput(f"checkpoint {path} holds NaN or inf weights (training diverged); retrain")
    try:
        model.load_state_dict(payload["state_dict"])
    except RuntimeError as exc:
        first = str(exc).strip().splitlines()[0][:160]
        raise BadInput(f"checkpoint {path} weights do not fit {model.spec.name} ({first})") from exc
    model = model.to(resolve_device(device)).eval().requires_grad_(False)
    dt = payload.get(CONTROL_DT)
    #: the control period (s) of the model's training data; None: not recorded (older ones)
    model.control_dt = float(dt) if isinstance(dt, (int, float)) and dt > 0 else None
    #: where the rod came to rest in that data (arrays by name), None where not recorded
    model.rest_states = rest_states_of(payload, path)
    return model


def rest_states_of(payload: dict[str, Any], path: Path | str) -> dict[str, Any] | None:
    """The checkpoint's rest states as float64 arrays, None where it holds none; BadInput
    where they are not finite arrays of matching counts."""
    held = payload.get(REST_STATES)
    if held is None:
        return None
    grippers, positions = (held.get(name) if isinstance(held, dict) else None
                           for name in ("grippers", "positions"))  # fmt: skip
    if not (torch.is_tensor(grippers) and torch.is_tensor(positions)
            and grippers.dim() == 3 and grippers.shape[1:] == (2, 7) and positions.dim() == 3
            and len(grippers) == len(positions) and bool(torch.isfinite(grippers).all())
            and bool(torch.isfinite(positions).all())):  # fmt: skip
        raise BadInput(f"checkpoint {path} holds unreadable rest states; retrain it or drop them")
    return {"grippers": grippers.double().numpy(), "positions": positions.double().numpy()}


def _check_scales(model: torch.nn.Module, path: Path | str) -> None:
    """BadInput unless every normalisation scale of a marker model is positive: a zero
    divides the features into NaN, and every score with them (training keeps them at least
    1e-6)."""
    for name in SCALES:
        scale = getattr(model, name)
        if not bool((scale > 0).all()):
            raise BadInput(
                f"checkpoint {path}: {name} holds {scale.cpu().tolist()}, not positive "
                "numbers (the training data's spread); retrain it"
            )


# ---------------------------------------------------------------------- older layouts
#: the views' own buffers: every other weight is the network's
VIEW_BUFFERS = {
    ROD: {"state_mean", "state_std", "delta_mean", "delta_std", "action_scale",
          "relation_scale", "fitted"},
    MARKERS: {"held", *SCALES, "fitted"},
}  # fmt: skip


def current_weights(payload: dict[str, Any], spec: ModelSpec, form: str) -> dict[str, Any]:
    """The payload's weights in this dlocli's layout. Before format version 4 each model
    class held its layers itself: they move under ``network.``, and the rod MLP's first layer,
    which read the two grippers' commands after all segments, reads each segment's command
    after its own features (zero for the segments no gripper holds): the same function."""
    weights = payload["state_dict"]
    version = payload.get("format_version")
    if (isinstance(version, int) and version >= 4) or any(
        str(k).startswith("network.") for k in weights
    ):
        return weights
    own = VIEW_BUFFERS[form]
    moved = {k if k in own else f"network.{k}": v for k, v in weights.items()}
    if form == ROD and spec.name == "mlp" and torch.is_tensor(moved.get("network.net.0.weight")):
        moved["network.net.0.weight"] = _per_segment_commands(
            moved["network.net.0.weight"], payload["n_segments"], spec.velocity_input
        )
    return moved


def _per_segment_commands(first: torch.Tensor, n: int, velocity: bool) -> torch.Tensor:
    """The rod MLP's first-layer weights (H, N F + 12) -> (H, N (F + 6)), see
    :func:`current_weights`; weights of another width are left for loading to refuse."""
    width = STATE_DIM * (2 if velocity else 1)
    if first.dim() != 2 or first.shape[1] != n * width + 2 * ACTION_DIM:
        return first
    features = first[:, : n * width].reshape(-1, n, width)
    commands = first.new_zeros(first.shape[0], n, ACTION_DIM)
    commands[:, 0] = first[:, n * width : n * width + ACTION_DIM]
    commands[:, -1] = first[:, n * width + ACTION_DIM :]
    return torch.cat([features, commands], -1).reshape(first.shape[0], -1)
