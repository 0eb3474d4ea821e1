"""The sideways swing decay of calibrated rods: each fitted spec's rod hangs between its two
grippers at rest (0.9 of its length apart), both grippers shift it 1 cm sideways in 0.1 s and
stop; the middle of the rod's sideways offset from the grippers then swings freely for up to
SECONDS (until its amplitude is below 1e-4 of the first). Its frequency (zero crossings) and
damping ratio (log decrement of the peaks, dlocli.backends.conformance) are the swing mode's;
the 1/e time of its amplitude is 1 / (zeta omega). Run it in the environment of each backend
(MuJoCo 3 for "mujoco", MuJoCo 4 for "mujoco-flex"):

python examples/calibration/swing_decay.py OUT.json RESULTS/DLO1-mujoco ... RESULTS/DLO4-mujoco

With ``bending_damping=A,B,...`` after OUT.json, each fit is measured at those bending
damping times instead of its own (entries "FIT bending_damping=A").
"""

from __future__ import annotations

import math
import sys
from pathlib import Path

import numpy as np
import yaml

from dlocli.backends import conformance
from dlocli.io import write_json_atomic
from dlocli.registry import backends
from dlocli.specs import BackendSpec

CONTROL_DT = 0.01  # s, the recordings' rate
SHIFT_M, SHIFT_S = 0.01, 0.1
SECONDS = 8.0


def swing(spec: BackendSpec) -> dict[str, float]:
    """Frequency (Hz), damping ratio and 1/e decay time (s) of the rod's sideways swing."""
    backend = backends.get(spec.name)(spec, control_dt=CONTROL_DT)
    try:
        backend.reset(0)
        shift = np.zeros((2, 6))
        shift[:, 1] = SHIFT_M / SHIFT_S
        for _ in range(round(SHIFT_S / CONTROL_DT)):
            backend.step(shift)
        middle = [(backend.n_segments - 1) // 2, backend.n_segments // 2]  # around the centre
        signal = []
        for _ in range(round(SECONDS / CONTROL_DT)):
            if not backend.step(np.zeros((2, 6))):
                raise RuntimeError(f"{spec.name}: the rod diverged while swinging")
            rod_y = backend.segment_positions()[middle, 1].mean()
            signal.append(rod_y - backend.gripper_poses()[:, 1].mean())
    finally:
        backend.close()
    signal = np.array(signal)
    # the swing, until it is lost in the rod's numerical noise
    signal = signal[: np.nonzero(np.abs(signal) > 1e-4 * np.abs(signal).max())[0][-1] + 1]
    hertz = conformance.frequency(signal, CONTROL_DT)
    zeta = conformance.damping_ratio(signal, CONTROL_DT)
    return {
        "swing_hz": hertz,
        "damping_ratio": zeta,
        "decay_s": 1.0 / (zeta * 2 * math.pi * hertz),
    }


def main() -> None:
    out, args = Path(sys.argv[1]), sys.argv[2:]
    sweep: list[float | None] = [None]
    if args and args[0].startswith("bending_damping="):
        sweep = [float(v) for v in args.pop(0).split("=")[1].split(",")]
    found = {}
    for run in [Path(a) for a in args]:
        fields = yaml.safe_load((run / "calibrated.yaml").read_text())
        spec = BackendSpec.model_validate(fields["backend"])
        for time in sweep:
            name = run.name if time is None else f"{run.name} bending_damping={time:g}"
            rod = (
                spec.rod if time is None else spec.rod.model_copy(update={"bending_damping": time})
            )
            found[name] = swing(spec.model_copy(update={"rod": rod}))
            print(name, {k: round(v, 4) for k, v in found[name].items()}, flush=True)
    write_json_atomic(out, found)


if __name__ == "__main__":
    main()
