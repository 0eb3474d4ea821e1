"""The MLP over a grid along the cable (`arc-mlp`): the interpolations it reads and writes
through, and its flattened form (what the fused rollout trains) equal to it for any marker
count. Trained on cables of two marker counts at once: tests/test_attention.py."""

from __future__ import annotations

import pytest
import torch

from dlocli.models.arc_mlp import ArcMLP, interpolation
from dlocli.models.marker_model import build_marker_model
from dlocli.models.mlp import MLP
from dlocli.models.network import Nodes
from dlocli.models.spec import ArcMLPSpec, MLPSpec
from dlocli.recorded_cables import deform

SPEC = {"name": "arc-mlp", "hidden": 32, "layers": 2, "points": 16, "length_projection": 3}


def test_interpolation_keeps_lines_and_the_ends() -> None:
    like = torch.zeros((), dtype=torch.float64)
    for targets, sources in ((16, 12), (16, 13), (12, 16), (5, 5), (2, 7)):
        m = interpolation(targets, sources, like)
        torch.testing.assert_close(m.sum(1), torch.ones(targets, dtype=torch.float64))
        line = torch.linspace(0.0, 1.0, sources, dtype=torch.float64)  # arc position
        torch.testing.assert_close(m @ line, torch.linspace(0.0, 1.0, targets, dtype=torch.float64))
        assert m[0, 0] == 1 and m[-1, -1] == 1
    torch.testing.assert_close(interpolation(9, 9, like), torch.eye(9, dtype=torch.float64))


def test_on_a_grid_of_its_own_count_it_is_the_mlp() -> None:
    nodes = Nodes(12, 10, 3, relative=10)
    torch.manual_seed(0)
    arc = ArcMLP(ArcMLPSpec(name="arc-mlp", hidden=32, layers=2, points=12), nodes)
    plain = MLP(MLPSpec(name="mlp", hidden=32, layers=2), nodes)
    plain.net.load_state_dict(arc.net.state_dict())
    inputs = torch.randn(5, 12, 10)
    torch.testing.assert_close(arc(inputs, inputs[:, 1:]), plain(inputs, inputs[:, 1:]))


@pytest.mark.parametrize("count", [8, 12, 13, 16, 24])
def test_its_flattened_layers_compute_what_it_computes(count: int) -> None:
    """For any count the composed layers (the fused rollout's) give forward's outputs, and
    their gradients reach the grid's weights."""
    torch.manual_seed(1)
    arc = ArcMLP(ArcMLPSpec(name="arc-mlp", hidden=32, layers=2, points=16),
                 Nodes(12, 10, 3, relative=10)).double()  # fmt: skip
    inputs = torch.randn(4, count, 10, dtype=torch.float64)
    flat = inputs.reshape(4, -1)
    layers = arc.flat_layers(count)
    for i, (weight, bias) in enumerate(layers):
        flat = torch.nn.functional.linear(flat, weight, bias)
        if i < len(layers) - 1:
            flat = flat.relu()
    torch.testing.assert_close(flat.view(4, count, 3), arc(inputs, inputs[:, 1:]))
    flat.square().sum().backward()
    assert all(p.grad is not None and bool(p.grad.abs().sum() > 0) for p in arc.parameters())


def test_its_marker_view_trains_through_the_fused_rollout() -> None:
    model = build_marker_model(SPEC, 13, deform.held_markers(13))
    x = torch.zeros(1, 12, 3)  # another cable's count
    assert model._whole_rollout_layers(x, x, torch.zeros(1, 2, 12, 3)) is not None
