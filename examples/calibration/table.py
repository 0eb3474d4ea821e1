"""The calibration results (RESULTS/*/report.json), the MuJoCo 4 flex rod's fits beside the
composite cable's (RESULTS/CABLE-mujoco-flex, with the swing decays of
RESULTS/swing_decay_*.json) and the sim-to-real results (RESULTS/sim_to_real_*.json) as
markdown tables; RESULTS defaults to results/ (today's rod), results/rigid/ holds the earlier
rod's (rigid clamps). The fits' reports are read from REPORTS (default RESULTS: the fits kept
there; the earlier rod's are in the calibration runs, e.g. runs/calibration).

python examples/calibration/table.py [RESULTS [REPORTS]] > RESULTS/summary.md
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

RESULTS = Path(sys.argv[1]) if len(sys.argv) > 1 else Path(__file__).parent / "results"
REPORTS = Path(sys.argv[2]) if len(sys.argv) > 2 else RESULTS


def main() -> None:
    reports = {
        p.parent.name: json.loads(p.read_text()) for p in sorted(REPORTS.glob("*/report.json"))
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
    print()
    flex_table(reports)
    sim_to_real_table()


def _swing_decays() -> dict[str, dict[str, float]]:
    """Per fit (folder name), its swing's frequency, damping ratio and decay time."""
    found: dict[str, dict[str, float]] = {}
    for path in sorted(RESULTS.glob("swing_decay_*.json")):
        found.update(json.loads(path.read_text()))
    return found


def _swing(swings: dict[str, dict[str, float]], name: str) -> str:
    if name not in swings:
        return "–"
    s = swings[name]
    return f"{s['damping_ratio']:.3f} ({s['decay_s']:.2f} s)"


def flex_table(reports: dict[str, dict]) -> None:
    """The flex rod (MuJoCo 4) against the composite cable (MuJoCo 3.17), per cable: eval
    scores (cm), the flex rod's over the cable's, its fitted material and both swing decays
    (damping ratio of the sideways swing, and its 1/e time)."""
    cables = [n.removesuffix("-mujoco-flex") for n in reports if n.endswith("-mujoco-flex")]
    if not cables:
        return
    swings = _swing_decays()
    print(
        "| cable | composite cable, calibrated | flex rod, calibrated | flex / composite "
        "| DER (published) | freeze | flex young_bending (Pa) | flex bending_damping (s) "
        "| flex air_damping (1/s) | swing decay, composite | swing decay, flex | flex fit time |"
    )
    print("|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|")
    for cable in cables:
        flex, cable_fit = reports[f"{cable}-mujoco-flex"], reports.get(f"{cable}-mujoco")
        p = flex["parameters"]
        composite = cable_fit["eval_calibrated_cm"] if cable_fit else float("nan")
        print(
            f"| {cable} | {composite:.2f} | **{flex['eval_calibrated_cm']:.2f}** | "
            f"{flex['eval_calibrated_cm'] / composite:.1%} | "
            f"{flex['published_cm'].get('DER', float('nan')):.2f} | "
            f"{flex['eval_freeze_cm']:.2f} | {p['young_bending']:.3g} | "
            f"{p['bending_damping']:.3g} | {p['air_damping']:.3g} | "
            f"{_swing(swings, f'{cable}-mujoco')} | {_swing(swings, f'{cable}-mujoco-flex')} | "
            f"{flex['fit_seconds'] / 60:.0f} min ({flex['generations']} gen.) |"
        )
    print()


def _seeds(values: list[float]) -> str:
    """Mean (min–max) of a few seeds' scores."""
    return f"{sum(values) / len(values):.2f} ({min(values):.2f}–{max(values):.2f})"


def sim_to_real_table() -> None:
    """Real eval score (cm) against the number of real train trajectories, per cable."""
    if not any(RESULTS.glob("sim_to_real_*.json")):
        return
    print("| cable | model | 0 real | 1 | 4 | 16 | 56 |")
    print("|---|---|---:|---:|---:|---:|---:|")
    for path in sorted(RESULTS.glob("sim_to_real_*.json")):
        r = json.loads(path.read_text())
        cable, steps = path.stem.removeprefix("sim_to_real_"), r["steps"]
        alone, tuned = r["real_only_cm"], r["finetuned_cm"]
        seeds = r["finetuned_long_seeds_cm"]
        print(
            f"| {cable} | real only ({steps['real_only_small']} steps; "
            f"{steps['real_only_56']} on 56) | – | {alone['1']:.2f} | {alone['4']:.2f} | "
            f"{alone['16']:.2f} | {_seeds(r['real_only_56_seeds_cm'])} |"
        )
        print(
            f"| | simulation, then real, {steps['finetune']} steps | {r['sim_only_cm']:.2f} | "
            f"{tuned['1']:.2f} | {tuned['4']:.2f} | {tuned['16']:.2f} | {tuned['56']:.2f} |"
        )
        print(
            f"| | simulation, then real, {steps['finetune_long']} steps | | | | "
            f"{_seeds(seeds['16'])} | {_seeds(seeds['56'])} |"
        )


if __name__ == "__main__":
    main()
