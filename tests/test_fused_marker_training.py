"""The fused marker rollouts (dlocli.models.marker_steps, marker_mlp_rollout) compute the
plain PyTorch path's loss and gradients: both float32 paths are compared with the plain
path in float64 (the truth up to rounding), and the fused one must be about as close to it
as the plain float32 one is (rounding grows through a rollout, so no fixed tolerance fits)."""

from __future__ import annotations

import copy

import numpy as np
import pytest
import torch

from dlocli.models.marker_model import MarkerModel, build_marker_model
from dlocli.models.marker_training import Cable, WindowSampler, rollout_loss
from dlocli.models.network import Network, Nodes
from dlocli.models.spec import FitSpec
from dlocli.recorded_cables import deform

from tiny import swinging_cable

MARKERS = 12
RECIPES = {  # examples/real_cables' models
    "mlp": {"name": "mlp", "hidden": 256, "layers": 2, "length_projection": 3},
    "arc-mlp": {"name": "arc-mlp", "hidden": 64, "layers": 2, "points": 16, "length_projection": 3},
    "in-bilstm": {"name": "in-bilstm", "hidden": 64, "length_projection": 3},
    "attention": {
        "name": "attention",
        "hidden": 16,
        "encoder_layers": 1,
        "heads": 2,
        "length_projection": 3,
    },  # fmt: skip
}


def _model_and_windows(name: str, k: int = 12, batch: int = 4) -> tuple[MarkerModel, torch.Tensor]:
    held = deform.held_markers(MARKERS)
    episodes = [swinging_cable(seed, frames=60, markers=MARKERS).transpose(0, 2, 1)
                for seed in range(3)]  # fmt: skip
    torch.manual_seed(0)
    model = build_marker_model(RECIPES[name], MARKERS, held)
    model.fit_normalization([(e, held) for e in episodes])
    model.train()
    sampler = WindowSampler([Cable(episodes, held)], FitSpec(seed=1), torch.device("cpu"))
    windows, *_ = sampler.sample(batch, k)
    return model, windows


def _loss_and_grads(model: MarkerModel, windows: torch.Tensor, reference: bool):
    model.reference = reference
    model.zero_grad(set_to_none=True)
    loss = rollout_loss(model, windows, model.held)
    loss.backward()
    return loss.detach().double(), torch.cat([p.grad.flatten() for p in model.parameters()])


def _relative(a: torch.Tensor, truth: torch.Tensor) -> float:
    return float((a.double() - truth).norm() / truth.norm())


@pytest.mark.parametrize("name", sorted(RECIPES))
def test_fused_training_rollout_matches_the_plain_one(name: str) -> None:
    model, windows = _model_and_windows(name)
    truth_loss, truth = _loss_and_grads(copy.deepcopy(model).double(), windows.double(), True)
    plain_loss, plain = _loss_and_grads(model, windows, True)
    fused_loss, fused = _loss_and_grads(model, windows, False)
    assert fused.dtype == torch.float32
    margin = 2 * abs(float(plain_loss - truth_loss)) + 1e-5 * float(truth_loss)
    assert abs(float(fused_loss - truth_loss)) <= margin
    assert _relative(fused, truth) <= 2 * _relative(plain, truth) + 1e-5


def test_training_takes_the_fused_path_by_default() -> None:
    """The MLP's rollout is one autograd node; the others' steps hold the fused ones."""
    nodes = {"mlp": "MLPRolloutBackward", "arc-mlp": "MLPRolloutBackward",
             "in-bilstm": "AdvanceBackward",
             "attention": "AdvanceBackward"}  # fmt: skip
    for name, node in nodes.items():
        model, windows = _model_and_windows(name, k=3)
        assert not model.reference
        loss = rollout_loss(model, windows, model.held)
        assert node in _graph_nodes(loss.grad_fn)


def _graph_nodes(fn) -> set[str]:
    seen, todo = set(), [fn]
    while todo:
        f = todo.pop()
        if f is not None and type(f).__name__ not in seen:
            seen.add(type(f).__name__)
            todo += [g for g, _ in f.next_functions]
    return seen


@pytest.mark.parametrize("name", sorted(RECIPES))
def test_fused_steps_pass_gradients_to_the_rollout_inputs(name: str) -> None:
    """Planners differentiate a rollout by the held markers' futures and its start: the
    per-step fused operations give those gradients as the plain path does."""
    model, windows = _model_and_windows(name, k=6)
    model.requires_grad_(False)
    grads = {}
    for label, m, w in (("truth", copy.deepcopy(model).double(), windows.double()),
                        ("plain", model, windows), ("fused", model, windows)):  # fmt: skip
        m.reference = label != "fused"
        x_prev, future = w[:, 0].clone().requires_grad_(True), w[:, 2:].clone().requires_grad_(True)
        pred = m.rollout(w[:, 1], x_prev, future)
        (pred * torch.linspace(-1, 1, pred.numel()).view_as(pred).to(pred.dtype)).sum().backward()
        grads[label] = torch.cat([x_prev.grad.flatten(), future.grad.flatten()])
    assert (
        _relative(grads["fused"], grads["truth"])
        <= 2 * _relative(grads["plain"], grads["truth"]) + 1e-5
    )


@pytest.mark.parametrize("name", sorted(RECIPES))
def test_fused_prediction_without_gradient_matches(name: str) -> None:
    model, windows = _model_and_windows(name, k=20)
    model.eval()
    with torch.no_grad():
        rolled = {}
        for reference in (True, False):
            model.reference = reference
            rolled[reference] = model.rollout(windows[:, 1], windows[:, 0], windows[:, 2:])
    scale = float(windows.abs().max())
    torch.testing.assert_close(rolled[False], rolled[True], rtol=0, atol=1e-4 * scale)
    held = model.held.cpu().numpy()
    assert np.array_equal(rolled[False][:, :, held].numpy(), windows[:, 2:, held].numpy())


def test_a_subclass_with_its_own_features_keeps_them() -> None:
    """The fused steps compute the view's features; a subclass's own are not skipped."""

    class Scaled(MarkerModel):
        def features(self, x, x_prev, held_next, held):
            return 2 * super().features(x, x_prev, held_next, held)

    model, windows = _model_and_windows("mlp", k=3)
    scaled = Scaled(model.spec, MARKERS, model.held.numpy())
    scaled.load_state_dict(model.state_dict())
    loss = rollout_loss(scaled, windows, scaled.held)
    assert not {"MLPRolloutBackward", "AdvanceBackward"} & _graph_nodes(loss.grad_fn)


class _PluginNetwork(Network):
    """A plugin's network of stock layers the fused step knows nothing of: a convolution
    along the markers, a bidirectional GRU, a layer norm and a linear head."""

    def __init__(self, spec, nodes: Nodes) -> None:
        super().__init__(spec, nodes)
        self.conv = torch.nn.Conv1d(nodes.inputs, 16, 3, padding=1)
        self.gru = torch.nn.GRU(16, 16, batch_first=True, bidirectional=True)
        self.norm = torch.nn.LayerNorm(32)
        self.head = torch.nn.Linear(32, nodes.outputs)

    def forward(self, nodes: torch.Tensor, relations: torch.Tensor) -> torch.Tensor:
        hidden = torch.nn.functional.gelu(self.conv(nodes.transpose(1, 2)))
        return self.head(self.norm(self.gru(hidden.transpose(1, 2))[0]))


def test_any_network_gets_the_fused_step_with_the_plain_gradients() -> None:
    """The fused features and advance wrap whatever network a model has: a plugin's of
    stock layers trains through them (the plain path's loss and gradients)."""
    base, windows = _model_and_windows("mlp")
    torch.manual_seed(0)
    model = copy.deepcopy(base)  # the view with its fitted scales, holding the plugin's net
    model.network = _PluginNetwork(base.spec, base.network.nodes)
    model.train()
    assert "AdvanceBackward" in _graph_nodes(rollout_loss(model, windows, model.held).grad_fn)
    truth_loss, truth = _loss_and_grads(copy.deepcopy(model).double(), windows.double(), True)
    plain_loss, plain = _loss_and_grads(model, windows, True)
    fused_loss, fused = _loss_and_grads(model, windows, False)
    margin = 2 * abs(float(plain_loss - truth_loss)) + 1e-5 * float(truth_loss)
    assert abs(float(fused_loss - truth_loss)) <= margin
    assert _relative(fused, truth) <= 2 * _relative(plain, truth) + 1e-5
