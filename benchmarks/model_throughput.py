"""Speed of the learned dynamics model: eager reference vs dlocli's implementation.

Both run the same weights in the same process, measurements interleaved (the machine may be
shared). For each: training transitions/s (Adam, batch 256 and ``dlo train``'s default
batch), forward latency at batch 1 and 256, and the MPC-relevant horizon-5 rollouts at batch
1, forward only (the default MPC's) and with a backward pass (gradient MPC's); next to the
machine's measured fp32 matrix-multiply rate, so the distance to the hardware limit is
visible.

    python benchmarks/model_throughput.py [--threads 2] [--model in-bilstm] [--json]

"Eager reference" = the model written plainly with stock PyTorch modules (``nn.LSTM``, the
relation-network input built per relation): ``model.reference = True``.
"""

from __future__ import annotations

import argparse
import json
import time
from collections.abc import Callable

import torch

from dlocli.models.base import STATE_DIM, DynamicsModel, ModelSpec, build_model
from dlocli.models.spec import TrainSpec


def matmul_gflops(size: int = 1024, seconds: float = 1.0, device: str = "cpu") -> float:
    """Measured fp32 GEMM rate (GFLOP/s) of an n x n product: the hardware reference."""
    a = torch.randn(size, size, device=device)
    b = torch.randn(size, size, device=device)
    for _ in range(3):
        a @ b
    _sync(device)
    count, start = 0, time.perf_counter()
    while time.perf_counter() - start < seconds:
        a @ b
        count += 1
    _sync(device)
    return 2 * size**3 * count / (time.perf_counter() - start) / 1e9


def forward_flops(model: DynamicsModel) -> float:
    """FLOPs (2 x multiply-adds) of one forward pass for one sample, as in the equations."""
    n = model.n_segments
    total = 0.0
    for name, module in model.named_modules():
        if isinstance(module, torch.nn.Linear):
            rows = 2 * (n - 1) if name.startswith("network.edge_net") else n
            rows = 1 if name.startswith("network.net") else rows  # the mlp baseline: one row
            total += 2 * rows * module.in_features * module.out_features
        elif isinstance(module, torch.nn.LSTM):
            h, size = module.hidden_size, module.input_size
            for layer in range(module.num_layers):
                width = size if layer == 0 else 2 * h
                total += 2 * 2 * n * 4 * h * (width + h)  # 2 directions, N steps
    return total


def _sync(device: str | torch.device) -> None:
    if torch.device(device).type == "cuda":
        torch.cuda.synchronize()


def _inputs(model: DynamicsModel, batch: int, horizon: int = 1) -> tuple[torch.Tensor, ...]:
    dev = model.device
    state = torch.randn(batch, model.n_segments, STATE_DIM, device=dev) * 0.1
    state[..., 3] += 1.0
    actions = torch.rand(batch, horizon, 2, 6, device=dev) * 2 - 1
    return state, actions


def bench_cases(model: DynamicsModel) -> dict[str, tuple[Callable[[], None], int]]:
    """name -> (function running one unit of work, samples processed per call)."""
    s1, a1 = _inputs(model, 1, 5)
    s256, a256 = _inputs(model, 256)
    opt = torch.optim.Adam(model.parameters(), lr=1e-6)

    def train_step(batch: int) -> Callable[[], None]:
        state, actions = s256[:batch], a256[:batch, 0]

        def step() -> None:
            model.train().requires_grad_(True)
            loss = model.loss(state, actions, state + 0.001)
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
            model.eval().requires_grad_(False)  # planning: frozen weights, as load_model gives

        return step

    @torch.no_grad()
    def forward1() -> None:
        model(s1, a1[:, 0])

    @torch.no_grad()
    def forward256() -> None:
        model(s256, a256[:, 0])

    @torch.no_grad()
    def rollout5() -> None:  # the default MPC's work per control step
        model.rollout(s1, a1)

    def rollout5_backward() -> None:
        actions = a1.clone().requires_grad_(True)
        model.rollout(s1, actions)[..., :3].square().sum().backward()

    default_batch = min(TrainSpec().batch_size, 256)
    return {
        "train_batch256": (train_step(256), 256),
        f"train_batch{default_batch}": (train_step(default_batch), default_batch),
        "forward_batch1": (forward1, 1),
        "forward_batch256": (forward256, 256),
        "rollout5_batch1": (rollout5, 5),
        "rollout5_backward_batch1": (rollout5_backward, 5),
    }


def measure(model: DynamicsModel, repeats: int, min_seconds: float) -> dict[str, dict[str, float]]:
    """Seconds per call of every case, reference and optimised interleaved: the best of
    ``repeats`` windows of ``min_seconds`` (the least disturbed by other processes)."""
    cases = bench_cases(model)
    times: dict[str, dict[str, list[float]]] = {k: {"eager": [], "dlocli": []} for k in cases}
    for name, (fn, _) in cases.items():
        for variant in ("eager", "dlocli"):
            model.reference = variant == "eager"
            fn()  # warm-up
        for _ in range(repeats):
            for variant in ("eager", "dlocli"):
                model.reference = variant == "eager"
                times[name][variant].append(_time_call(fn, model.device, min_seconds))
    model.reference = False
    return {k: {v: min(t) for v, t in d.items()} for k, d in times.items()}


def _time_call(fn: Callable[[], None], device: torch.device, min_seconds: float) -> float:
    calls, start = 0, time.perf_counter()
    while True:
        fn()
        calls += 1
        _sync(device)
        elapsed = time.perf_counter() - start
        if elapsed >= min_seconds:
            return elapsed / calls


def report(model: DynamicsModel, medians: dict[str, dict[str, float]], peak: float) -> dict:
    flops = forward_flops(model)
    cases = bench_cases(model)
    rows = {}
    for name, per in medians.items():
        samples = cases[name][1]
        backward = name.startswith("train") or name.endswith("backward_batch1")
        work = flops * samples * (3 if backward else 1)  # backward ~ 2x the forward
        row = {}
        for variant, sec in per.items():
            row[f"{variant}_ms"] = 1000 * sec
            row[f"{variant}_gflops"] = work / sec / 1e9
        if name.startswith("train"):
            row.update({f"{v}_transitions_per_s": samples / s for v, s in per.items()})
        row["speedup"] = per["eager"] / per["dlocli"]
        row["dlocli_fraction_of_matmul_peak"] = row["dlocli_gflops"] / peak
        rows[name] = row
    return {
        "model": model.spec.name,
        "forward_mflops_per_sample": flops / 1e6,
        "matmul_fp32_gflops": peak,
        "threads": torch.get_num_threads(),
        "cases": rows,
    }


def print_table(result: dict) -> None:
    print(
        f"model {result['model']}: {result['forward_mflops_per_sample']:.1f} MFLOP per "
        f"sample forward; fp32 matmul {result['matmul_fp32_gflops']:.0f} GFLOP/s "
        f"({result['threads']} threads)"
    )
    widths = {"eager": 10, "dlocli": 10, "speedup": 8, "GFLOP/s": 8, "of peak": 8}
    print(f"{'case':28s} " + " ".join(f"{c:>{w}s}" for c, w in widths.items()))
    for name, row in result["cases"].items():
        if name.startswith("train"):
            e, d = row["eager_transitions_per_s"], row["dlocli_transitions_per_s"]
            cols = f"{e:8.0f}/s {d:8.0f}/s"
        else:
            cols = f"{row['eager_ms']:8.2f}ms {row['dlocli_ms']:8.2f}ms"
        print(
            f"{name:28s} {cols} {row['speedup']:7.2f}x {row['dlocli_gflops']:8.1f} "
            f"{100 * row['dlocli_fraction_of_matmul_peak']:7.1f}%"
        )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--model", default="in-bilstm")
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--repeats", type=int, default=7)
    parser.add_argument("--min-seconds", type=float, default=0.2)
    parser.add_argument("--json", action="store_true")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    torch.manual_seed(0)
    model = build_model(ModelSpec(name=args.model), 20).to(args.device).eval()
    model.requires_grad_(False)
    peak = matmul_gflops(device=args.device)
    result = report(model, measure(model, args.repeats, args.min_seconds), peak)
    if args.json:
        print(json.dumps(result, indent=2))
    else:
        print_table(result)


if __name__ == "__main__":
    main()
