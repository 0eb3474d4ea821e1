"""The calibration report: JSON and markdown, next to DEFORM's published physics rows."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from dlocli.io import write_json_atomic, write_text_atomic

#: DEFORM (Chen et al., CoRL 2024) Table 1, physics simulators, cm, by cable folder name
PUBLISHED_CM: dict[str, dict[str, float]] = {
    "DER": {"DLO1": 1.96, "DLO2": 1.91, "DLO3": 1.86, "DLO4": 1.50},
    "XPBD": {"DLO1": 4.00, "DLO2": 3.85, "DLO3": 3.80, "DLO4": 3.62},
}


def published_rows(cable: str | None) -> dict[str, float]:
    """DEFORM's published physics scores of the cable (its folder name; none if unknown)."""
    return {method: row[cable] for method, row in PUBLISHED_CM.items() if cable in row}


def markdown(summary: dict[str, Any]) -> str:
    """The report as a markdown page."""
    rows = [
        ("default material", summary["eval_default_cm"]),
        ("calibrated", summary["eval_calibrated_cm"]),
        ("freeze (free markers stay at frame 1)", summary["eval_freeze_cm"]),
    ] + [(f"DEFORM's {m} (published)", v) for m, v in summary["published_cm"].items()]
    lines = [
        f"# Calibration of {summary['cable']} ({summary['backend']})",
        "",
        "DEFORM protocol score on the eval recordings (cm, lower is better):",
        "",
        "| rod | eval score (cm) |",
        "|---|---|",
        *[f"| {name} | {value:.3f} |" for name, value in rows],
        "",
        "| parameter | default | calibrated |",
        "|---|---|---|",
        *[
            f"| {n} | {summary['default_parameters'][n]:.4g} | {v:.4g} |"
            for n, v in summary["parameters"].items()
        ],
        "",
        f"Rod {summary['rod_length_m']} m, density {summary['density_kg_m3']} kg/m^3; "
        f"{summary['generations']} generations, {summary['evaluations']} candidates on "
        f"{len(summary['train_recordings'])} train recordings in {summary['fit_seconds']} s "
        f"(best train score {summary['train_best_cm']} cm). Calibrated rod on eval: start "
        f"error {summary['eval_start_error_mm']} mm, held-marker tracking "
        f"{summary['eval_held_error_mm']} mm, {summary['eval_diverged']} diverged.",
        "",
    ]
    return "\n".join(lines)


def write_report(out: Path, summary: dict[str, Any]) -> None:
    """OUT/report.json and OUT/report.md (atomic)."""
    summary["published_cm"] = published_rows(summary["cable"])
    write_json_atomic(out / "report.json", summary)
    write_text_atomic(out / "report.md", markdown(summary))
