"""Time per predicted step of the real-cable recipe models (batch 1, one CPU thread), the
quantity DEFORM's Table 1 reports next to its scores.

    python benchmarks/real_cables_latency.py [--markers 12] [--steps 300] [--repeats 5]

Each recipe's model (examples/real_cables/*.yaml that name one; once per distinct model) is
timed with and without its length projection, interleaved in one process (the machine may
be shared): medians of the repeats and the projection's cost as a ratio. Timing does not depend on
the weights, so fresh models are timed; no data is needed.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
import torch
import yaml

from dlocli.models.marker_model import build_marker_model
from dlocli.models.spec import TrainSpec
from dlocli.recorded_cables.deform import held_markers

RECIPES = Path(__file__).parents[1] / "examples" / "real_cables"


@torch.inference_mode()
def per_step_ms(model: torch.nn.Module, markers: int, steps: int) -> float:
    frames = torch.randn(1, steps + 2, markers, 3) * 0.01 + torch.linspace(0, 1, markers)[:, None]
    start = time.perf_counter()
    model.rollout(frames[:, 1], frames[:, 0], frames[:, 2:])
    return (time.perf_counter() - start) / steps * 1000.0


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--markers", type=int, default=12)
    parser.add_argument("--steps", type=int, default=300)
    parser.add_argument("--repeats", type=int, default=5)
    args = parser.parse_args()
    torch.set_num_threads(1)
    held = held_markers(args.markers)
    models, timed = {}, []
    for recipe in sorted(RECIPES.glob("*.yaml")):
        raw = yaml.safe_load(recipe.read_text())
        if "model" not in raw:  # a fine-tuning recipe: the model is the checkpoint's
            continue
        spec = TrainSpec.model_validate(raw).model
        if spec in timed:  # recipes that differ only in training predict alike
            continue
        timed.append(spec)
        for sweeps in (spec.length_projection, 0):
            name = f"{recipe.stem}, projection {sweeps}"
            models[name] = build_marker_model(
                spec.model_copy(update={"length_projection": sweeps}), args.markers, held
            ).eval()
    times: dict[str, list[float]] = {name: [] for name in models}
    for model in models.values():
        per_step_ms(model, args.markers, 20)  # warm-up
    for _ in range(args.repeats):
        for name, model in models.items():
            times[name].append(per_step_ms(model, args.markers, args.steps))
    print(f"batch 1, 1 thread, {args.markers} markers, {args.steps}-step rollouts, "
          f"median of {args.repeats}")  # fmt: skip
    medians = {name: float(np.median(t)) for name, t in times.items()}
    for name, ms in medians.items():
        print(f"  {name:32s} {ms:6.3f} ms per step")
    for name in medians:
        if not name.endswith("projection 0"):
            base = name.rsplit(",", 1)[0] + ", projection 0"
            print(f"  {name}: projection costs {medians[name] / medians[base]:.2f}x")


if __name__ == "__main__":
    main()
