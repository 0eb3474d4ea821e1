"""Marker-model training throughput: rollout steps per second of `dlo train`'s gradient step,
the plain PyTorch path (before issue 43) next to the fused one (the default), in one run.

    python benchmarks/training_throughput.py [--data DATASET] [--ks 64 256] [--batch 32]
        [--repeats 5] [--steps 2] [--threads 1] [--device cpu]

For each recipe of examples/real_cables (mlp, in-bilstm, attention; ``--recipes`` takes any
of its yaml files, e.g. arc-mlp-long) and each rollout length k: one model, copied twice
with the same weights (``model.reference = True``: every step through PyTorch operations
and autograd; ``False``: the fused step around the network, dlocli.models.marker_steps,
and for the networks that are fully connected layers (mlp, arc-mlp) the whole rollout as
one operation, dlocli.models.marker_mlp_rollout), each with its own Adam. A gradient step
is what `dlo train` does: draw windows, roll out, the loss, backward, clip, Adam. The
variants' timings are interleaved (the machine may be shared) and, on CPU, in this
process's CPU time (what sharing the cores changes least); medians of the repeats, and
new / old as the ratio.

For a model with an ``nn.LSTM`` (the in-bilstm), the share of the new gradient step its k
LSTM passes forward and backward take alone (oneDNN's, the same in both variants). The
arithmetic bound: the rollout steps per second if a gradient step did nothing but its
matrix products (their floating-point operations counted by ``torch.utils.flop_counter``,
an ``nn.LSTM``'s by its sizes) at the best rate this CPU reaches for one product of the
step's widths (measured between the variants); bound / old is the most any fused or
compiled form of the same float32 arithmetic could gain. ``--compile`` adds the new variant
with the network (``model.predict``) compiled by ``torch.compile`` (inductor), and its
first step's wall time. ``--data``: a marker dataset (`dlo import`); default a synthetic
swinging cable (the timing hardly depends on the data).
"""

from __future__ import annotations

import argparse
import copy
import math
import time
from pathlib import Path

import numpy as np
import torch
import yaml

from dlocli.models.base import resolve_device
from dlocli.models.marker_model import MarkerModel, build_marker_model
from dlocli.models.marker_training import Cable, WindowSampler, rollout_loss
from dlocli.models.spec import TrainSpec
from dlocli.recorded_cables.deform import held_markers

RECIPES = Path(__file__).parents[1] / "examples" / "real_cables"


def synthetic_cable(markers: int = 12, episodes: int = 8, frames: int = 500) -> Cable:
    """A sagging cable whose ends swing (0.01 s frames), held at two markers per end."""
    rng = np.random.default_rng(0)
    s = np.linspace(0, 1, markers)[None, :]
    recorded = []
    for _ in range(episodes):
        t = np.arange(frames)[:, None] / 100.0
        phase, amp = rng.uniform(0, 6), rng.uniform(0.02, 0.08)
        x = 0.8 * s + amp * np.sin(2 * np.pi * t + phase)
        y = 0.05 * np.sin(np.pi * s) * np.cos(3 * t + phase)
        z = 0.5 - 0.2 * np.sin(np.pi * s) + amp * np.sin(5 * t) * s
        recorded.append(np.stack([x, y, z], -1))
    return Cable(recorded, held_markers(markers))


def load_cable(path: str | None) -> Cable:
    if path is None:
        return synthetic_cable()
    from dlocli.data import load_dataset

    data = load_dataset(path)
    return Cable(data.episodes("train"), data.held)


class Trainer:
    """One variant: its model, Adam and window sampler (the same draws for both variants)."""

    def __init__(self, model: MarkerModel, cable: Cable, spec: TrainSpec, device: torch.device):
        self.model = model.to(device).train()
        self.optimizer = torch.optim.Adam(model.parameters(), lr=spec.lr)
        self.sampler = WindowSampler([cable], spec, device)
        self.device = device

    def seconds_per_step(self, batch: int, k: int, steps: int) -> float:
        _sync(self.device)
        start = _clock(self.device)
        for _ in range(steps):
            loss = rollout_loss(self.model, *self.sampler.sample(batch, k))
            if not math.isfinite(loss.item()):
                raise RuntimeError("the loss diverged")
            self.optimizer.zero_grad(set_to_none=True)
            loss.backward()
            torch.nn.utils.clip_grad_norm_(self.model.parameters(), 1.0)
            self.optimizer.step()
        _sync(self.device)
        return (_clock(self.device) - start) / steps


def _clock(device: torch.device) -> float:
    """Seconds: on CPU this process's CPU time (one thread: its time on a core, what other
    processes on a shared machine do not change), elsewhere the wall clock."""
    return time.process_time() if device.type == "cpu" else time.perf_counter()


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize()


def lstm_seconds(model: MarkerModel, batch: int, k: int, steps: int) -> float:
    """Seconds of the model's LSTM forward and backward, k times (one rollout's) at the
    rollout's shapes, per gradient step."""
    lstm = model.network.lstm
    sequence = torch.randn(batch, len(model.held), lstm.input_size, device=model.device)
    start = _clock(model.device)
    for _ in range(steps):
        for _ in range(k):
            lstm(sequence.requires_grad_(True))[0].sum().backward()
    _sync(model.device)
    return (_clock(model.device) - start) / steps


def rollout_step_flops(model: MarkerModel, cable: Cable, spec: TrainSpec, batch: int) -> float:
    """Floating-point operations of one rollout step's forward and backward (the plain
    path's matrix products; an ``nn.LSTM``'s counted from its sizes: its oneDNN kernel is not
    seen by the counter)."""
    from torch.utils.flop_counter import FlopCounterMode

    model = copy.deepcopy(model).cpu()
    model.reference = True
    lstm_flops = [0.0]

    def count_lstm(lstm: torch.nn.LSTM, inputs: tuple, _: object) -> None:
        sequence = inputs[0]
        calls = sequence.shape[0] * sequence.shape[1]  # batch x time
        directions = 2 if lstm.bidirectional else 1
        for layer in range(lstm.num_layers):
            n_in = lstm.input_size if layer == 0 else directions * lstm.hidden_size
            macs = calls * directions * 4 * lstm.hidden_size * (n_in + lstm.hidden_size)
            lstm_flops[0] += 3 * 2 * macs  # forward, and twice that backward

    hooks = [m.register_forward_hook(count_lstm) for m in model.modules()
             if isinstance(m, torch.nn.LSTM)]  # fmt: skip
    steps = 4
    windows, held = WindowSampler([cable], spec, torch.device("cpu")).sample(batch, steps)
    with FlopCounterMode(display=False) as counter:
        rollout_loss(model, windows, held).backward()
    for hook in hooks:
        hook.remove()
    return (counter.get_total_flops() + lstm_flops[0]) / steps


def matmul_rate(model: MarkerModel, batch: int) -> float:
    """The best floating-point operations per second of one matrix product at the sizes of a
    rollout step (rows: the batch's markers; the model's widths), on this CPU, one thread."""
    widths = sorted({p.shape[-1] for p in model.parameters() if p.dim() == 2})
    rows = batch * len(model.held)
    best = 0.0
    for inner in widths:
        for outer in widths:
            a, b = torch.randn(rows, inner), torch.randn(inner, outer)
            torch.mm(a, b)
            repeats = 50
            start = time.process_time()
            for _ in range(repeats):
                torch.mm(a, b)
            seconds = max(time.process_time() - start, 1e-9)
            best = max(best, 2 * rows * inner * outer * repeats / seconds)
    return best


def compare(spec: TrainSpec, cable: Cable, k: int, args: argparse.Namespace) -> dict[str, float]:
    """Median seconds per gradient step of both variants, interleaved (and of the LSTM's
    passes, for a model that has one; on CPU, the matrix products' best rate, "rate")."""
    device = resolve_device(args.device)
    torch.manual_seed(0)
    model = build_marker_model(spec.model, len(cable.held), cable.held)
    model.fit_normalization([(e, cable.held) for e in cable.episodes])
    variants = {}
    for name, reference in (("old", True), ("new", False)) + (("compiled", False),) * args.compile:
        copied = copy.deepcopy(model)
        copied.reference = reference
        if name == "compiled":  # the fused step around the network compiled by inductor
            copied.predict = torch.compile(copied.predict)
        variants[name] = Trainer(copied, cable, spec, device)
    times: dict[str, list[float]] = {}
    for name, trainer in list(variants.items()):
        start = time.perf_counter()  # wall: inductor's compiler runs in other processes
        try:
            trainer.seconds_per_step(args.batch, k, 1)  # warm-up (compiled loops load once)
        except Exception as e:  # no C++ compiler, an unsupported layer: say so, go on
            if name != "compiled":
                raise
            print(f"  torch.compile failed, measured without: {str(e).splitlines()[0]}")
            del variants[name]
            continue
        times[f"{name} warm-up"] = [time.perf_counter() - start]
    times |= {name: [] for name in variants}
    has_lstm = isinstance(getattr(model, "lstm", None), torch.nn.LSTM)
    for _ in range(args.repeats):
        for name, trainer in variants.items():
            times[name].append(trainer.seconds_per_step(args.batch, k, args.steps))
        if has_lstm:
            times.setdefault("lstm", []).append(
                lstm_seconds(variants["new"].model, args.batch, k, args.steps)
            )
        if device.type == "cpu":  # measured between the variants: the same load
            times.setdefault("rate", []).append(matmul_rate(model, args.batch))
    return {name: float(np.median(t)) for name, t in times.items()}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--data", default=None, help="a marker dataset; default synthetic")
    parser.add_argument("--ks", type=int, nargs="+", default=[64, 256])
    parser.add_argument("--batch", type=int, default=32)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--steps", type=int, default=2, help="gradient steps per timing")
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--recipes", nargs="+", default=["mlp", "in-bilstm", "attention"])
    parser.add_argument("--compile", action="store_true",
                        help="also the new variant with torch.compile(model.predict)")  # fmt: skip
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    if args.compile:
        from torch._inductor import config

        config.compile_threads = 1  # the benchmark's one core
    cable = load_cable(args.data)
    print(f"data {args.data or 'synthetic'}, {len(cable.held)} markers, batch {args.batch}, "
          f"{args.threads} thread(s), device {args.device}, median of {args.repeats} x "
          f"{args.steps} gradient steps (windows, rollout, loss, backward, clip, Adam), "
          f"{'CPU' if args.device == 'cpu' else 'wall'} time"
          )  # fmt: skip
    print(f"  {'recipe':12s} {'k':>4s} {'old steps/s':>12s} {'new steps/s':>12s} {'new/old':>8s}"
          f"  {'LSTM share of new':>17s} {'bound steps/s':>13s} {'bound/old':>9s}")  # fmt: skip
    for recipe in args.recipes:
        raw = yaml.safe_load((RECIPES / f"{recipe}.yaml").read_text())
        spec = TrainSpec.model_validate({**raw, "device": args.device})
        model = build_marker_model(spec.model, len(cable.held), cable.held)
        flops = rollout_step_flops(model, cable, spec, args.batch)
        for k in args.ks:
            per_step = compare(spec, cable, k, args)
            bound = per_step.get("rate", math.nan) / flops  # the CPU's: elsewhere not measured
            old, new = k / per_step["old"], k / per_step["new"]
            share = per_step["lstm"] / per_step["new"] if "lstm" in per_step else math.nan
            shown = f"{share:17.0%}" if math.isfinite(share) else f"{'-':>17s}"
            print(f"  {recipe:12s} {k:4d} {old:12.0f} {new:12.0f} {new / old:7.2f}x  {shown} "
                  f"{bound:13.0f} {bound / old:8.2f}x", flush=True)  # fmt: skip
            if "compiled" in per_step:
                compiled = k / per_step["compiled"]
                print(f"  {'':12s} {'':4s} torch.compile'd network: {compiled:.0f} steps/s "
                      f"({compiled / old:.2f}x), first step {per_step['compiled warm-up']:.0f} s "
                      f"(the new's {per_step['new warm-up']:.1f} s)", flush=True)  # fmt: skip


if __name__ == "__main__":
    main()
