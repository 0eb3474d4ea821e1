"""Latency per control step of the model-based planners, and the share spent in the model.

    python benchmarks/mpc_latency.py [--model CKPT] [--hidden 150] [--steps 12] [--threads 2]
                                     [--quick] [--json]

Each setting runs ``--steps`` closed-loop control steps of the MuJoCo single-gripper task,
on the rod the installed MuJoCo runs (the cable on 3.x, the flex rod from 4.0 on; the first
two steps are warm-up and not counted), and reports the median and 95th percentile of
``Controller.last_latency_ms``. "model %" is the share of that median spent in the model
itself: the median time of ``iterations`` bare rollouts (+ gradient for ``mpc``) at the
setting's batch size, divided by the step's median latency; the rest is the planner's own
work (tensors from the observation, optimiser updates, bookkeeping).

The last lines compare the default setting, timed in the same run, with two references:
the same default through the plain PyTorch model (``model.reference = True``: stock
``nn.LSTM``, the default path before :mod:`dlocli.models.fast_rollout`), and the floor: the
bare PyTorch matrix products of one H-step rollout at batch 1 (the in-bilstm's f_e and f_v
layers, its LSTM input projections and the 2 x N recurrent products per layer, back to back
on preallocated tensors, nothing else). At batch 1 the recurrent products are
matrix-vector products that read all of W_hh per step, bound by memory bandwidth; the
compiled path reads the same weights, so it cannot go far below this floor either.

Without ``--model`` an untrained in-bilstm of ``--hidden`` width is used: latency does not
depend on the weights. The row marked ``paper-like`` is the slow reference setting (50
cold-start Adam iterations per step, no warm start).
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch

import dlocli
from dlocli.backend_spec import default_backend
from dlocli.controllers.base import Controller, make_controller
from dlocli.controllers.planning import ModelPlanner
from dlocli.models.base import ModelSpec, build_model
from dlocli.models.checkpoints import load_model

PAPER_LIKE = {"optimizer": "adam", "iterations": 50, "warm_start": False, "restarts": 1}

SETTINGS: list[tuple[str, dict[str, Any]]] = [
    ("mpc", {}),  # defaults: gauss-newton, lagged Jacobian, 1 iteration
    ("mpc", {"exact_gradient": True}),
    ("mpc", {"curvature_every": 5}),
    ("mpc", {"refresh": "background"}),  # the Jacobian refresh on a second core
    ("mpc", {"iterations": 3}),
    ("mpc", {"optimizer": "adam"}),
    ("mpc", {"optimizer": "adam", "iterations": 3}),
    ("mpc", {"iterations": 2, "restarts": 4}),
    ("mpc", {"iterations": 2, "restarts": 16}),
    ("mpc", {"iterations": 2, "replan_every": 2}),
    ("mpc", {"iterations": 20}),
    ("mpc", PAPER_LIKE),
    ("mppi", {}),  # defaults
    ("mppi", {"samples": 16}),
    ("mppi", {"samples": 64}),
    ("mppi", {"samples": 256, "iterations": 3}),
]
QUICK = [s for s in SETTINGS if s[1].get("iterations", 0) < 20 and s[1].get("samples", 0) < 256]


def get_model(path: Path | None, hidden: int, n_segments: int, device: torch.device) -> Any:
    """The checkpoint at ``path``, or an untrained in-bilstm of width ``hidden``."""
    if path is not None:
        return load_model(path, device)
    return build_model(ModelSpec(hidden=hidden), n_segments).to(device).eval()


def model_ms(
    controller: ModelPlanner, obs: np.ndarray, name: str, options: dict[str, Any]
) -> float:
    """Median ms of the bare model work of one re-plan at this setting's batch size."""
    spec = controller.spec
    batch = getattr(spec, "restarts", None) or getattr(spec, "samples", 1)
    iterations = spec.iterations  # type: ignore[attr-defined]
    state = controller.state_tensor(obs)
    plans = controller.random_plans(batch)
    backprop = name == "mpc" and (
        spec.optimizer != "gauss-newton" or spec.exact_gradient  # type: ignore[attr-defined]
    )
    times = []
    for _ in range(5):
        start = time.perf_counter()
        for _ in range(iterations):
            if backprop:
                plans.requires_grad_(True)
                torch.autograd.grad(controller.predict_cost(state, plans).sum(), plans)
            else:
                with torch.inference_mode():
                    controller.predict_cost(state, plans)
        times.append(time.perf_counter() - start)
    return 1000.0 * float(np.median(times))


def floor_ms(model: Any, horizon: int, repeats: int = 30) -> float | None:
    """Median ms of the bare matrix products of one ``horizon``-step in-bilstm rollout at
    batch 1 (None for other models). See the module docstring."""
    if not hasattr(model.network, "edge_net"):
        return None
    n, model = model.n_segments, model.network
    linears = [(m, 2 * (n - 1)) for m in model.edge_net if isinstance(m, torch.nn.Linear)]
    linears += [(m, n) for m in model.node_net if isinstance(m, torch.nn.Linear)]
    layers = [
        (torch.cat([w_ih_f, w_ih_b]).t().contiguous(), torch.stack([w_hh_f.t(), w_hh_b.t()]))
        for w_ih_f, w_hh_f, w_ih_b, w_hh_b in (
            [
                getattr(model.lstm, f"weight_{k}_l{layer}{d}")
                for d in ("", "_reverse")
                for k in ("ih", "hh")
            ]  # fmt: skip
            for layer in range(model.lstm.num_layers)
        )
    ]
    hidden = model.lstm.hidden_size
    inputs = [torch.zeros(rows, m.in_features) for m, rows in linears]
    xs = [torch.zeros(n, w_ih_t.shape[0]) for w_ih_t, _ in layers]
    h = torch.zeros(2, 1, hidden)

    def rollout() -> None:
        for _ in range(horizon):
            for (m, _), x in zip(linears, inputs, strict=True):
                torch.addmm(m.bias, x, m.weight.t())
            for (w_ih_t, w_hh_t), x in zip(layers, xs, strict=True):
                torch.mm(x, w_ih_t)
                for _ in range(n):
                    torch.bmm(h, w_hh_t)

    times = []
    with torch.inference_mode():
        rollout()
        for _ in range(repeats):
            start = time.perf_counter()
            rollout()
            times.append(time.perf_counter() - start)
    return 1000.0 * float(np.median(times))


def time_setting(
    env: Any, model: Any, name: str, options: dict[str, Any], steps: int
) -> dict[str, Any]:
    """Closed-loop latency of one planner setting; the env restarts from the same state."""
    obs, _ = env.reset(seed=0)
    controller: Controller = make_controller(name, env, options=options, model=model)
    controller.reset(env.goal)
    latencies, cpu = [], []
    for _ in range(steps):
        start = time.process_time()
        action = controller.act(obs)
        cpu.append(1000.0 * (time.process_time() - start))
        latencies.append(controller.last_latency_ms)
        obs, *_ = env.step(action)
    measured = np.array(latencies[2:])
    median = float(np.median(measured))
    assert isinstance(controller, ModelPlanner)
    in_model = model_ms(controller, obs, name, options) / max(controller.spec.replan_every, 1)
    resolved = controller.spec.model_dump()
    return {
        "controller": name,
        "options": options,
        "resolved": resolved,
        "paper_like": name == "mpc" and all(resolved[k] == v for k, v in PAPER_LIKE.items()),
        "latency_ms_median": round(median, 2),
        "latency_ms_p95": round(float(np.percentile(measured, 95)), 2),
        "latency_ms_max": round(float(np.max(measured)), 2),
        "latency_ms_mean": round(float(np.mean(measured)), 2),
        "cpu_ms_median": round(float(np.median(cpu[2:])), 2),
        "hz": round(1000.0 / median, 1),
        "model_share": round(min(in_model / median, 1.0), 3),
    }


def pytorch_path(env: Any, model: Any, steps: int) -> dict[str, Any] | None:
    """The default setting with ``model.reference`` set (None for models without it)."""
    if not hasattr(model, "reference"):
        return None
    model.reference = True
    try:
        return time_setting(env, model, "mpc", {}, steps)
    finally:
        model.reference = False


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawTextHelpFormatter
    )
    parser.add_argument("--model", type=Path, default=None, help="checkpoint (default: untrained)")
    parser.add_argument("--hidden", type=int, default=150, help="width of the untrained model")
    parser.add_argument(
        "--steps",
        type=int,
        default=52,
        help="control steps per setting (the mean includes gauss-newton's Jacobian refreshes)",
    )
    parser.add_argument("--threads", type=int, default=1, help="torch threads (dlo control: 1)")
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--quick", action="store_true", help="skip the settings slower than ~0.5 s")
    parser.add_argument("--json", action="store_true", help="print the rows as JSON")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    env = dlocli.make_env(backend=default_backend(), task="single", seed=0, episode_steps=10**6)
    model = get_model(args.model, args.hidden, env.n_segments, torch.device(args.device))
    rows = [
        time_setting(env, model, n, o, args.steps) for n, o in (QUICK if args.quick else SETTINGS)
    ]
    floor = floor_ms(model, rows[0]["resolved"]["horizon"])
    before = pytorch_path(env, model, args.steps)
    env.close()
    if args.json:
        print(json.dumps({"settings": rows, "pytorch_path": before, "floor_ms": floor}, indent=1))
        return
    header = (f"{'controller':10} {'options':46} {'median ms':>9} {'p95 ms':>7} {'max ms':>7} "
              f"{'mean ms':>7} {'cpu ms':>7}")  # fmt: skip
    print(f"{header} {'Hz':>6} {'model %':>7}")
    for row in rows:
        label = ", ".join(f"{k}={v}" for k, v in row["options"].items()) or "(defaults)"
        label += "  <- paper-like" if row["paper_like"] else ""
        print(f"{row['controller']:10} {label:46} {row['latency_ms_median']:9.1f} "
              f"{row['latency_ms_p95']:7.1f} {row['latency_ms_max']:7.1f} "
              f"{row['latency_ms_mean']:7.1f} {row['cpu_ms_median']:7.1f} {row['hz']:6.1f} "
              f"{100 * row['model_share']:6.0f}%")  # fmt: skip
    default = rows[0]["latency_ms_median"]
    if before is not None:
        print(f"the default through plain PyTorch (the path before fast_rollout): median "
              f"{before['latency_ms_median']:.1f} ms; the default is "
              f"{before['latency_ms_median'] / default:.2f}x faster")  # fmt: skip
    if floor is not None:
        print(f"floor: the matrix products of one rollout at batch 1 take {floor:.1f} ms; "
              f"the default's median is {default / floor:.2f}x that")  # fmt: skip


if __name__ == "__main__":
    main()
