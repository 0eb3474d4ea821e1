"""Conformance suite of the dynamics models: every registered model, on real simulator data.

Sizes are tiny except where the paper's default architecture is the point.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

from dlocli.data import load_dataset
from dlocli.errors import BadInput
from dlocli.models.base import build_model, resolve_device
from dlocli.models.checkpoints import load_model, load_model_bytes, save_checkpoint
from dlocli.models.spec import model_spec
from dlocli.registry import models

TINY = {"hidden": 16}


@pytest.fixture(scope="module")
def real(small_dataset_dir):
    """(dataset, transitions as float32 tensors) of the session's small MuJoCo dataset."""
    data = load_dataset(small_dataset_dir)
    arrays = data.transitions()
    tensors = {k: torch.as_tensor(arrays[k], dtype=torch.float32) for k in arrays}
    return data, arrays, tensors


def fitted(name: str, real, **sizes) -> torch.nn.Module:
    data, arrays, _ = real
    torch.manual_seed(0)
    model = build_model({"name": name, **TINY, **sizes}, data.n_segments)
    model.fit_normalization(arrays)
    return model.eval()


@pytest.fixture(params=models.names())
def model(request, real):
    return fitted(request.param, real)


def batch(real, size: int = 5, horizon: int = 4):
    """Start states (B,N,7) and the recorded actions after them (B,H,2,6)."""
    _, _, t = real
    state = t["state"][:size]
    actions = t["action"][: size * horizon].reshape(size, horizon, 2, 6)
    return state, actions


def test_shapes_and_unit_quaternions(model, real):
    state, actions = batch(real)
    nxt = model(state, actions[:, 0])
    assert nxt.shape == state.shape
    rolled = model.rollout(state, actions)
    assert rolled.shape == (5, 4, model.n_segments, 7)
    for out in (nxt, rolled):
        norms = out[..., 3:].norm(dim=-1)
        torch.testing.assert_close(norms, torch.ones_like(norms), atol=1e-5, rtol=0)
        assert torch.all(out[..., 3] >= 0), "canonical sign w >= 0 like the dataset"


def test_gradient_reaches_actions(model, real):
    state, actions = batch(real)
    actions = actions.clone().requires_grad_(True)
    model.rollout(state, actions)[..., :3].square().sum().backward()
    assert actions.grad is not None and torch.isfinite(actions.grad).all()
    assert actions.grad[:, :, 1].abs().sum() > 0, "the right gripper's commands matter"
    assert actions.grad[:, -1].abs().sum() > 0, "every step of the plan gets a gradient"


def test_rollout_equals_iterated_forward(model, real):
    state, actions = batch(real)
    previous = real[2]["previous_state"][: len(state)]
    with torch.no_grad():
        rolled = model.rollout(state, actions, previous)
        s, prev = state, previous
        for t in range(actions.shape[1]):
            prev, s = s, model(s, actions[:, t], prev)
            assert torch.equal(rolled[:, t], s)


def test_velocity_input_reads_the_previous_state(model, real):
    """With velocity_input (the default) the last step's change is an input; without, the
    previous state is ignored; None means at rest (previous = state)."""
    state, actions = batch(real)
    moved = state.clone()
    moved[..., :3] -= 0.01  # the rod moved 1 cm up to this state
    with torch.no_grad():
        at_rest, moving = model(state, actions[:, 0]), model(state, actions[:, 0], moved)
        assert torch.equal(at_rest, model(state, actions[:, 0], state))
        assert torch.equal(at_rest, moving) != model.spec.velocity_input
        plain = fitted(model.spec.name, real, velocity_input=False)
        assert torch.equal(plain(state, actions[:, 0]), plain(state, actions[:, 0], moved))


def test_in_bilstm_without_absolute_position_is_translation_invariant(real):
    """Without absolute positions, shifting the rod shifts the prediction and nothing else
    (a rod without contacts obeys this); with them, the paper's model is not bound to."""
    state, actions = batch(real)
    shift = torch.tensor([0.05, -0.03, 0.02, 0, 0, 0, 0])
    with torch.no_grad():
        for absolute in (False, True):
            m = fitted("in-bilstm", real, absolute_position=absolute)
            moved = m.rollout(state + shift, actions, state + shift) - shift
            same = torch.allclose(moved, m.rollout(state, actions, state), atol=1e-5)
            assert same != absolute


def test_save_load_round_trip_is_exact(model, real, tmp_path):
    state, actions = batch(real)
    path = save_checkpoint(model, tmp_path / "m.pt", {"epoch": 3})
    again = load_model(path, "cpu", expect=model.spec)
    assert again.spec == model.spec and again.n_segments == model.n_segments
    with torch.no_grad():
        assert torch.equal(model.rollout(state, actions), again.rollout(state, actions))
    run = tmp_path / "run"
    save_checkpoint(model, run / "checkpoints" / "final.pt")
    assert torch.equal(load_model(run).state_std, model.state_std), "a run dir means final.pt"


def test_a_checkpoints_bytes_load_as_its_file_does(model, real, tmp_path):
    """Online trials get the checkpoint as bytes and load it in memory."""
    state, actions = batch(real)
    path = save_checkpoint(model, tmp_path / "m.pt")
    again = load_model_bytes(path.read_bytes())
    with torch.no_grad():
        assert torch.equal(load_model(path).rollout(state, actions), again.rollout(state, actions))
    with pytest.raises(BadInput, match="the model checkpoint in memory is not a readable"):
        load_model_bytes(path.read_bytes()[:100])


def test_version_1_checkpoint_loads_without_velocity(real, tmp_path):
    """Checkpoints written before the velocity input existed hold models without it (and
    with absolute positions, which came later)."""
    old = fitted("in-bilstm", real, velocity_input=False)
    path = save_checkpoint(old, tmp_path / "v1.pt")
    payload = torch.load(path, weights_only=True)
    payload["format_version"] = 1
    del payload["model_spec"]["velocity_input"], payload["model_spec"]["absolute_position"]
    torch.save(payload, path)
    again = load_model(path)
    assert again.spec.velocity_input is False and again.spec.absolute_position is True
    state, actions = batch(real)
    with torch.no_grad():
        assert torch.equal(old.rollout(state, actions), again.rollout(state, actions))


def test_single_task_model_accepts_bimanual_actions(model, real):
    _, arrays, _ = real
    assert np.all(arrays["action"][:, 0] == 0), "the fixture is single-gripper data"
    state, actions = batch(real)
    both = actions[:, 0].clone()
    both[:, 0] = both[:, 1].flip(0)  # the left gripper moves too
    with torch.no_grad():
        single, bimanual = model(state, actions[:, 0]), model(state, both)
    assert torch.isfinite(bimanual).all()
    assert not torch.equal(single, bimanual), "the left gripper's command reaches the model"


def test_normalisation_fits_the_data(model, real):
    _, _, t = real
    with torch.no_grad():
        target = model.loss(t["state"], t["action"], t["next_state"])
    assert torch.isfinite(target)
    assert bool(model.fitted)
    assert torch.all(model.delta_std > 0) and torch.all(model.state_std > 0)
    assert model.action_scale[0] > 0.3, "scale from the moving gripper, not the idle one"


@pytest.mark.parametrize("name", models.names())
def test_bad_checkpoints_are_bad_input(name, real, tmp_path):
    model = fitted(name, real)
    good = save_checkpoint(model, tmp_path / "good.pt")
    (tmp_path / "garbage.pt").write_bytes(b"not a checkpoint at all")
    torch.save({"weights": torch.zeros(3)}, tmp_path / "foreign.pt")
    truncated = tmp_path / "truncated.pt"
    truncated.write_bytes(good.read_bytes()[:200])
    for path in ("garbage.pt", "foreign.pt", "truncated.pt", "missing.pt"):
        with pytest.raises(BadInput):
            load_model(tmp_path / path)
    with pytest.raises(BadInput, match="requested"):
        load_model(good, expect=model_spec({"name": name, **TINY, "hidden": 24}))
    (tmp_path / "empty_run").mkdir()
    with pytest.raises(BadInput, match="final.pt"):
        load_model(tmp_path / "empty_run")


def test_devices():
    assert resolve_device("cpu") == torch.device("cpu")
    assert resolve_device("auto").type in ("cpu", "cuda")
    for bad in ("cuda:7", "tpu", "gpu0"):
        if bad == "cuda:7" and torch.cuda.device_count() > 7:
            continue
        with pytest.raises(BadInput):
            resolve_device(bad)


def test_paper_architecture_defaults():
    model = build_model({}, 20)
    linear = torch.nn.Linear
    net = model.network
    assert [m.out_features for m in net.edge_net if isinstance(m, linear)] == [150] * 4
    assert [m.out_features for m in net.node_net if isinstance(m, linear)] == [150] * 3 + [7]
    # v_i = (position, quaternion, their change over the last step): 14 numbers
    assert model.network.edge_net[0].in_features == 2 * (14 + 6), "(v_i, a_i, v_j, a_j)"
    assert model.network.node_net[0].in_features == 14 + 2 * 150, "(v_i, [h_left_i, h_right_i])"
    without = build_model({"velocity_input": False}, 20)
    assert without.network.edge_net[0].in_features == 2 * (7 + 6)
    lstm = model.network.lstm
    assert (lstm.num_layers, lstm.hidden_size, lstm.bidirectional) == (2, 150, True)


def test_gradient_planner_path_matches_reference(real):
    """Back-propagation to the actions through frozen weights (the gradient planners') takes
    dlocli.models.rnn's kernels: the same rollout and action gradients as plain PyTorch."""
    from dlocli.models import rnn

    model = fitted("in-bilstm", real, hidden=24, lstm_layers=2).requires_grad_(False)
    state, actions = batch(real, size=3, horizon=2)
    outs, grads = [], []
    for reference in (False, True):
        model.reference = reference
        acts = actions.clone().requires_grad_(True)
        out = model.rollout(state, acts)
        out[..., :3].sum().backward()
        outs.append(out.detach())
        grads.append(acts.grad)
    assert rnn._frozen_backward(acts, model.network.lstm)
    torch.testing.assert_close(outs[0], outs[1], atol=1e-6, rtol=1e-5)
    torch.testing.assert_close(grads[0], grads[1], atol=1e-5, rtol=1e-4)
    model.requires_grad_(True)  # training: the stock LSTM
    assert not rnn._frozen_backward(acts, model.network.lstm)


@pytest.mark.parametrize(
    "sizes",
    [
        {"hidden": 150},  # the paper's sizes
        {"velocity_input": False, "absolute_position": False, "edge_layers": 1, "lstm_layers": 1,
         "node_layers": 1},
        {"lstm_layers": 3, "edge_layers": 2},
    ],
)  # fmt: skip
def test_planner_rollout_matches_reference(real, sizes):
    """Forward-only rollouts at small batches (the planners') take the compiled path of
    dlocli.models.fast_rollout: the same function as plain PyTorch. Rounding differences
    grow along a rollout, so each step is held to PyTorch's own float32 error (against
    float64): the compiled path may differ from float64 by at most twice as much."""
    import copy

    from dlocli.models import fast_rollout

    model = fitted("in-bilstm", real, **sizes)
    exact = copy.deepcopy(model).double()
    exact.reference = True
    state, actions = batch(real, size=3, horizon=5)
    previous = real[2]["previous_state"][:3]
    for size in (1, 3):
        for prev in (None, previous[:size]):
            args = (state[:size], actions[:size], prev)
            with torch.no_grad():
                assert fast_rollout.usable(model, *args)
                fast = model.rollout(*args)
                model.reference = True
                assert not fast_rollout.usable(model, *args)
                ref = model.rollout(*args)
                model.reference = False
                r64 = exact.rollout(*(None if a is None else a.double() for a in args))
            assert fast.shape == ref.shape == (size, 5, model.n_segments, 7)
            assert (fast - state[:size, None]).abs().max() > 1e-4, "the rollout moves the rod"
            torch.testing.assert_close(fast[:, 0], ref[:, 0], atol=5e-6, rtol=1e-5)
            error_fast = (fast - r64).abs().amax(dim=(0, 2, 3))
            error_torch = (ref - r64).abs().amax(dim=(0, 2, 3))
            assert (error_fast <= 2 * error_torch + 1e-6).all(), (error_fast, error_torch)


def test_planner_rollout_routes_and_sees_new_weights(real):
    """Gradients, large batches and the reference flag take PyTorch; after a training
    step the compiled path uses the new weights (its repacked weights are not stale)."""
    from dlocli.models import fast_rollout

    model = fitted("in-bilstm", real)
    state, actions = batch(real, size=fast_rollout.MAX_BATCH + 1, horizon=2)
    small = (state[:1], actions[:1], None)
    assert not fast_rollout.usable(model, state, actions, None), "large batch: oneDNN"
    assert not fast_rollout.usable(model, *small), "grad enabled, weights require it"
    plans = actions[:1].clone().requires_grad_(True)
    model.rollout(state[:1], plans).sum().backward()
    assert plans.grad is not None and plans.grad.abs().sum() > 0
    with torch.inference_mode():  # buffers made here are written again outside it
        before = model.rollout(*small)
    with torch.no_grad():
        torch.testing.assert_close(model.rollout(*small), before, atol=0, rtol=0)
    opt = torch.optim.SGD(model.parameters(), lr=0.1)
    t = real[2]
    model.loss(t["state"][:8], t["action"][:8], t["next_state"][:8]).backward()
    opt.step()
    with torch.no_grad():
        after = model.rollout(*small)
        model.reference = True
        ref = model.rollout(*small)
    assert (after - before).abs().max() > 1e-6
    torch.testing.assert_close(after, ref, atol=5e-6, rtol=1e-5)


def test_bilstm_matches_torch_lstm_in_double():
    from dlocli.models.rnn import bilstm

    torch.manual_seed(1)
    lstm = torch.nn.LSTM(5, 6, 2, batch_first=True, bidirectional=True).double()
    lstm.requires_grad_(False)
    x = torch.randn(3, 7, 5, dtype=torch.double, requires_grad=True)
    weights = torch.randn(3, 7, 12, dtype=torch.double)
    mine, ref = bilstm(x, lstm), lstm(x)[0]
    assert mine.grad_fn is not None and "BiLSTMLayer" in type(mine.grad_fn).__name__
    torch.testing.assert_close(mine, ref, atol=1e-12, rtol=0)
    (g_mine,) = torch.autograd.grad((mine * weights).sum(), [x])
    (g_ref,) = torch.autograd.grad((ref * weights).sum(), [x])
    torch.testing.assert_close(g_mine, g_ref, atol=1e-12, rtol=0)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_cuda_rollout_matches_cpu(model, real):
    state, actions = batch(real)
    gpu = load_model_like(model, "cuda")
    acts = actions.cuda().requires_grad_(True)
    out = gpu.rollout(state.cuda(), acts)
    out.sum().backward()
    assert acts.grad is not None and torch.isfinite(acts.grad).all()
    with torch.no_grad():
        torch.testing.assert_close(out.cpu(), model.rollout(state, actions), atol=1e-4, rtol=1e-4)


def load_model_like(model, device: str):
    clone = build_model(model.spec, model.n_segments)
    clone.load_state_dict(model.state_dict())
    return clone.to(device).eval()
