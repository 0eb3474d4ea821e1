"""What the replay's unmeasured choices cost: the grippers' roll rule and the start.

    python examples/calibration/replay_choices.py $DEFORM/DLO3 0.998 0.0968 OUT.json

Replays every eval recording of one cable on the default material with each choice and
prints the mean DEFORM score (cm), the free markers' start error (mm) and the divergences.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np

from dlocli.calibration.fit import load_cable
from dlocli.calibration.replay import ReplaySettings, replay
from dlocli.calibration.spec import CalibrateSpec
from dlocli.registry import backends

CHOICES = {
    "transported roll, 1 s approach + 1 s settle": ReplaySettings("transported", 1.0, 1.0),
    "level roll, 1 s approach + 1 s settle": ReplaySettings("level", 1.0, 1.0),
    "transported roll, 1 s approach, no settle": ReplaySettings("transported", 1.0, 0.0),
    "transported roll, 0.5 s approach + 3 s settle": ReplaySettings("transported", 0.5, 3.0),
}


def main(source: str, length: float, mass: float, out: str) -> None:
    results = {}
    for name in ("mujoco", "pybullet"):
        spec = CalibrateSpec(source=Path(source), cable_length=length, cable_mass=mass)
        spec.backend.name = name
        cable = load_cable(spec)
        backend = backends.get(name)(cable.backend, control_dt=1.0 / spec.rate_hz)
        for label, settings in CHOICES.items():
            runs = [replay(backend, rec, cable.arc, settings) for _, rec in cable.eval]
            row = {
                "score_cm": round(float(np.mean([r.score_cm for r in runs])), 4),
                "start_error_mm": round(float(np.mean([r.start_error_mm for r in runs])), 2),
                "diverged": sum(r.diverged_at is not None for r in runs),
            }
            results[f"{name}: {label}"] = row
            print(f"{name:9s} {label:48s} {row}", flush=True)
    Path(out).write_text(json.dumps({"source": source, "results": results}, indent=1) + "\n")


if __name__ == "__main__":
    main(sys.argv[1], float(sys.argv[2]), float(sys.argv[3]), sys.argv[4])
