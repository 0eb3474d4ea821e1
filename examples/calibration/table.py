"""The calibration results as one markdown table (from results/*/report.json).

python examples/calibration/table.py > examples/calibration/results/summary.md
"""

from __future__ import annotations

import json
from pathlib import Path

RESULTS = Path(__file__).parent / "results"


def main() -> None:
    reports = {
        p.parent.name: json.loads(p.read_text()) for p in sorted(RESULTS.glob("*/report.json"))
    }
    print(
        "| cable, backend | default material | calibrated | DER (published) | XPBD (published) "
        "| freeze | young_bending (Pa) | bending_damping (s) | air_damping (1/s) | fit time |"
    )
    print("|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|")
    for name, r in reports.items():
        p, pub = r["parameters"], r["published_cm"]
        print(
            f"| {name} | {r['eval_default_cm']:.2f} | **{r['eval_calibrated_cm']:.2f}** | "
            f"{pub.get('DER', float('nan')):.2f} | {pub.get('XPBD', float('nan')):.2f} | "
            f"{r['eval_freeze_cm']:.2f} | {p['young_bending']:.3g} | {p['bending_damping']:.3g} | "
            f"{p['air_damping']:.3g} | {r['fit_seconds'] / 60:.0f} min ({r['generations']} gen.) |"
        )


if __name__ == "__main__":
    main()
