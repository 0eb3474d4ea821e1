"""The networks that serve any marker count in the marker view (attention, told cables
apart by their geometry; arc-mlp, by their whole shape): one network trained on two
cables of different marker counts at once."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from dlocli.models.fit import fit as fit_model
from dlocli.models.marker_model import build_marker_model
from dlocli.models.marker_training import Cable, Cables, validation_score
from dlocli.models.spec import FitSpec
from dlocli.recorded_cables import deform

from tiny import swinging_cable

SPEC = {"name": "attention", "hidden": 16, "encoder_layers": 1, "heads": 2,
        "length_projection": 3}  # fmt: skip


def _cable(markers: int, seeds: range, stretch: float = 1.0) -> Cable:
    episodes = [stretch * swinging_cable(s, frames=50, markers=markers).transpose(0, 2, 1)
                for s in seeds]  # fmt: skip
    return Cable(episodes, deform.held_markers(markers))


def test_descriptors_hold_the_neighbour_vectors_and_the_cable_length() -> None:
    model = build_marker_model(SPEC, 12, deform.held_markers(12))
    x = torch.as_tensor(_cable(12, range(1)).episodes[0][:2], dtype=torch.float32)
    d = model.descriptors(x)
    edges = x[:, 1:] - x[:, :-1]
    torch.testing.assert_close(d[:, 1:, 0:3], -edges)  # to the previous marker
    torch.testing.assert_close(d[:, :-1, 3:6], edges)  # to the next one
    assert bool((d[:, 0, 0:3] == 0).all()) and bool((d[:, -1, 3:6] == 0).all())
    torch.testing.assert_close(d[:, :, 8], edges.norm(dim=-1).sum(1)[:, None].expand(-1, 12))
    longer = model.descriptors(2 * x)  # a cable twice as long reads twice the length
    torch.testing.assert_close(longer[..., 6:], 2 * d[..., 6:])


ARC_MLP = {"name": "arc-mlp", "hidden": 32, "layers": 2, "points": 16, "length_projection": 3}


@pytest.mark.parametrize("spec", [SPEC, ARC_MLP], ids=["attention", "arc-mlp"])
def test_one_network_learns_cables_of_different_marker_counts(spec: dict) -> None:
    """Trained on a 13-marker and a 12-marker cable at once, it predicts both better than
    before training, through each cable's own held mask."""
    train = [_cable(13, range(0, 4)), _cable(12, range(4, 8), stretch=0.8)]
    val = [_cable(13, range(20, 22)), _cable(12, range(22, 24), stretch=0.8)]
    torch.manual_seed(0)
    model = build_marker_model(spec, 13, train[0].held)
    model.fit_normalization([(e, c.held) for c in train for e in c.episodes])
    before = [validation_score(model, [c]) for c in val]
    fit = FitSpec(update_steps=60, eval_every=20, rollout_steps=8, rollout_start=2, lr=3e-3,
                  batch_size=8, device="cpu")  # fmt: skip
    history = fit_model(model, Cables(train, val), fit).history
    after = [validation_score(model, [c]) for c in val]
    assert len(history) == 3 and all(np.isfinite(after))
    assert after[0] < before[0] and after[1] < before[1], (before, after)
