"""Model checkpoints (dlocli.models.checkpoints): every one the repository holds loads, every
layout written before today loads to the same model, the form tag is written from the model
and read in one place, and only that module reads or writes model checkpoints."""

from __future__ import annotations

import re
import subprocess
from pathlib import Path

import numpy as np
import pytest
import torch

import dlocli
from dlocli.errors import BadInput
from dlocli.models.base import build_model
from dlocli.models.checkpoints import (
    CONTROL_DT,
    load_marker_model,
    load_model,
    load_planning_model,
    read_checkpoint,
    save_checkpoint,
)
from dlocli.models.marker_model import build_marker_model
from dlocli.recorded_cables.deform import held_markers

REPO = Path(dlocli.__file__).resolve().parents[1]
TINY = {"hidden": 8}


def committed_checkpoints() -> list[Path]:
    """The ``.pt`` files git tracks in the repository (none where it is not a git clone)."""
    try:
        listed = subprocess.run(["git", "ls-files", "*.pt"], cwd=REPO, capture_output=True,
                                text=True, check=True).stdout.split()  # fmt: skip
    except (OSError, subprocess.CalledProcessError):
        return []
    return [REPO / name for name in listed]


def rod_model() -> torch.nn.Module:
    torch.manual_seed(0)
    model = build_model({"name": "mlp", **TINY, "layers": 2}, 6)
    model.state_mean.normal_()  # buffers that differ from a fresh model's
    return model


def marker_model() -> torch.nn.Module:
    torch.manual_seed(0)
    held = held_markers(6)
    model = build_marker_model({"name": "in-bilstm", **TINY}, 6, held)
    rng = np.random.default_rng(0)
    model.fit_normalization([(rng.normal(0, 0.1, (8, 6, 3)), held)])
    return model


def rewritten(path: Path, change: dict, drop: tuple[str, ...] = ()) -> Path:
    """``path``'s checkpoint with ``change`` merged into its payload and ``drop`` removed, as
    an older or hostile writer left it."""
    payload = torch.load(path, weights_only=True)
    payload.update(change)
    for key in drop:
        del payload[key]
    torch.save(payload, path)
    return path


def same_weights(a: torch.nn.Module, b: torch.nn.Module) -> bool:
    pairs = zip(a.state_dict().items(), b.state_dict().items(), strict=True)
    return all(ka == kb and torch.equal(va, vb) for (ka, va), (kb, vb) in pairs)


def test_every_committed_checkpoint_and_older_layout_loads(tmp_path):
    """Each checkpoint git tracks loads (frozen); and the layouts written before today (rod
    checkpoints had no form tag, marker ones no control period) load through every loader
    that takes their form, to the model that was saved."""
    for path in committed_checkpoints():
        model = load_planning_model(path)
        assert not any(p.requires_grad for p in model.parameters()), path
    rod, markers = rod_model(), marker_model()
    untagged = rewritten(save_checkpoint(rod, tmp_path / "rod.pt"), {}, drop=("form",))
    written = save_checkpoint(markers, tmp_path / "m.pt", {CONTROL_DT: 0.01})
    no_dt = rewritten(written, {}, drop=(CONTROL_DT,))
    rod_loads = [load_model, load_planning_model, lambda p: load_model(p.read_bytes()),
                 lambda p: load_planning_model(p.read_bytes())]  # fmt: skip
    for load in rod_loads:
        loaded = load(untagged)
        assert type(loaded) is type(rod) and same_weights(loaded, rod)
        assert loaded.control_dt is None and not loaded.training
    marker_loads = [load_marker_model, load_planning_model,
                    lambda p: load_planning_model(p.read_bytes())]  # fmt: skip
    for load in marker_loads:
        loaded = load(no_dt)
        assert type(loaded) is type(markers) and same_weights(loaded, markers)
        assert loaded.control_dt is None and not loaded.training


def test_the_form_and_control_period_are_written_and_read_back(tmp_path):
    rod, markers = rod_model(), marker_model()
    rod_path = save_checkpoint(rod, tmp_path / "rod.pt", {CONTROL_DT: 0.02})
    # an `extra` cannot contradict the model: the tag comes from the model itself
    marker_path = save_checkpoint(markers, tmp_path / "m.pt", {"form": "rod", CONTROL_DT: 0.01})
    assert read_checkpoint(rod_path)["form"] == "rod"
    assert read_checkpoint(marker_path)["form"] == "markers"
    assert load_model(rod_path).control_dt == 0.02
    assert load_planning_model(marker_path).control_dt == 0.01


def test_a_form_the_caller_cannot_use_is_refused_in_one_line(tmp_path):
    rod_path = save_checkpoint(rod_model(), tmp_path / "rod.pt")
    marker_path = save_checkpoint(marker_model(), tmp_path / "m.pt")
    with pytest.raises(BadInput, match="marker-form model"):
        load_model(marker_path)
    with pytest.raises(BadInput, match="is a rod model"):
        load_marker_model(rod_path)
    rewritten(rod_path, {"form": "clouds"})
    with pytest.raises(BadInput, match="form 'clouds', not one of rod, markers"):
        load_planning_model(rod_path)


def test_the_load_checks_stay(tmp_path):
    """Non-finite weights and non-positive marker scales are refused at the load boundary."""
    markers = marker_model()
    path = save_checkpoint(markers, tmp_path / "m.pt")
    payload = torch.load(path, weights_only=True)
    payload["state_dict"]["position_scale"] = torch.zeros(3)
    torch.save(payload, path)
    with pytest.raises(BadInput, match="position_scale holds"):
        load_marker_model(path)
    payload["state_dict"]["position_scale"] = torch.full((3,), float("nan"))
    torch.save(payload, path)
    with pytest.raises(BadInput, match="NaN or inf weights"):
        load_planning_model(path)


def test_only_the_checkpoint_module_reads_or_writes_model_checkpoints():
    """torch.load and torch.save are called in dlocli/models/checkpoints.py and for PILCO's
    own learner file only (not counting docstrings): a model checkpoint has one reader and
    one writer."""
    root = REPO / "dlocli"
    calling = sorted(
        str(path.relative_to(REPO))
        for path in root.rglob("*.py")
        if re.search(r"(?<![`\w.])torch\.(load|save)\(", path.read_text())
    )
    assert calling == ["dlocli/controllers/pilco.py", "dlocli/models/checkpoints.py"], calling


LEGACY = REPO / "tests" / "data" / "legacy_checkpoints"


@pytest.mark.parametrize("path", sorted(LEGACY.glob("*.pt")), ids=lambda p: p.stem)
def test_checkpoints_of_the_per_form_classes_predict_as_they_did(path):
    """Checkpoints written when each model form was a class of its own (format version 3:
    rod and marker models of in-bilstm, mlp and attention, hidden 8) load into one network
    inside its view and roll out as their writer did: the rollout saved beside the weights,
    to float32 rounding (the MLP's first layer is laid out anew, so its sums run in another
    order)."""
    payload = read_checkpoint(path)
    assert payload["format_version"] == 3
    model, ref = load_planning_model(path), payload["reference"]
    for reference in (True, False):  # plain PyTorch, and the fast paths
        model.reference = reference
        with torch.no_grad():
            if model.form == "rod":
                out = model.rollout(ref["state"], ref["actions"], ref["previous"])
            else:
                out = model.rollout(ref["x"], ref["x_prev"], ref["held_future"])
        scale = float(ref["rollout"].abs().max())
        torch.testing.assert_close(out, ref["rollout"], rtol=0, atol=1e-5 * scale)
