"""The README's main job over seeds, as it is and with planner options changed, on the rod of
the installed MuJoCo (4: the flex rod, 3.17: the composite cable).

    python benchmarks/main_job_seeds.py run OUT --label LABEL [--spec FILE] [--seeds 0,1,2,3,4]
                                            [--count FLAG=N ...]
    python benchmarks/main_job_seeds.py report OUT [OUT ...] [--write STEM]

``run``: the README's main command (read from the README, its counts as they are) once per
seed into OUT/<backend>-<LABEL>-s<seed>, with ``--spec FILE`` added when given (e.g.
examples/flex_planner.yaml), and each ``--count`` replacing one of the command's counts (e.g.
``--count trials=8``: the job's own counts, which a spec file cannot change since the
command's flags override it). A finished run is kept (delete it to measure again). ``report``:
per rod and label, each seed's score (1 - final / initial, the summary's), the final error,
doing nothing, random actions and the held-end servo (no model) from the same starts, MPC
milliseconds per control step and
wall seconds as the run measured them; the mean and the worst score. The label ``default`` is
the README's command as it is (its rod's planner defaults: on the flex rod motion_cost 32 and
damping 1, on the composite cable the paper's cost); ``paper`` is the paper's planner,
``--spec examples/paper_planner.yaml``. Prints a markdown table;
``--write STEM`` also writes STEM.md and STEM.json (benchmarks/results/main_job_seeds).
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path
from typing import Any

from readme_main_command import readme_command  # this folder: a script's first path entry

from dlocli.backend_spec import default_backend

REFERENCE = "default"  # the label of the README's command as it is


def run(out: Path, seeds: list[int], label: str, spec: Path | None, counts: dict[str, str]) -> None:
    backend = default_backend()  # the command's own rod: the installed MuJoCo's
    extra = [] if spec is None else ["--spec", str(spec)]
    command = with_counts(readme_command(), counts)
    for seed in seeds:
        folder = out / f"{backend}-{label}-s{seed}"
        if finished(folder):
            continue
        call = [sys.executable, "-m", "dlocli", *command, *extra,
                "--seed", str(seed), "--out", str(folder), "--json"]  # fmt: skip
        subprocess.run(call, check=True, stdout=subprocess.DEVNULL)
        print(f"{folder.name}: {row(folder)}", flush=True)


def with_counts(command: list[str], counts: dict[str, str]) -> list[str]:
    """``command`` with the value after each ``--FLAG`` of ``counts`` replaced (SystemExit
    naming a flag the command does not have)."""
    command = list(command)
    for flag, value in counts.items():
        if f"--{flag}" not in command:
            raise SystemExit(f"--count {flag}: the README's command has no --{flag}")
        command[command.index(f"--{flag}") + 1] = value
    return command


def finished(folder: Path) -> bool:
    """Whether ``folder`` holds a run that did all its iterations (a summary is written after
    every iteration)."""
    if not (folder / "summary.json").is_file():
        return False
    summary = json.loads((folder / "summary.json").read_text())
    return summary["iterations_done"] == json.loads((folder / "spec.json").read_text())["iters"]


def row(folder: Path) -> dict[str, Any]:
    summary = json.loads((folder / "summary.json").read_text())
    spec = json.loads((folder / "spec.json").read_text())
    steps = spec["trials"] * spec["task"]["episode_steps"] * summary["iterations_done"]
    return {
        "backend": spec["backend"]["name"],
        "label": folder.name.removeprefix(spec["backend"]["name"] + "-").rsplit("-s", 1)[0],
        "seed": spec["seed"],
        "counts": f"{spec['iters']} x {spec['trials']}, {spec['initial_episodes']} random",
        "score": round(summary["score"], 3),
        "initial_mm": round(summary["initial_error_mm"], 1),
        "final_mm": round(summary["final_error_mm"], 1),
        "zero_mm": round(summary["zero_final_error_mm"], 1),
        "random_mm": round(summary["random_final_error_mm"], 1),
        # runs before the held-end servo was a reference have none
        "held_end_mm": rounded(summary["curve"][-1].get("held-end_final_error_mm_mean")),
        "mpc_ms_per_step": round(1000.0 * summary["mpc_seconds"] / steps, 2),
        "wall_s": round(summary["seconds"]),  # the run's own, from its start to its summary
        "motion_cost": spec["mpc"].get("motion_cost", 0.0),
        "damping": spec["mpc"].get("damping", 0.01),
        "servo_cost": spec["mpc"].get("servo_cost", 0.0),
        "rest_roll": spec["mpc"].get("rest_roll", False),
    }


def rounded(value: float | None) -> float | None:
    return None if value is None else round(value, 1)


def report(outs: list[Path]) -> tuple[str, dict[str, Any]]:
    found = [f for out in outs for f in out.iterdir() if finished(f)]
    rows = sorted(map(row, found), key=lambda r: (r["backend"], r["label"], r["seed"]))
    groups: dict[tuple[str, str, str], list[dict[str, Any]]] = {}
    for r in rows:
        groups.setdefault((r["backend"], r["label"], r["counts"]), []).append(r)
    lines = [
        "| rod | variant | iterations x trials, initial | seeds | scores | mean | worst | final "
        "mm (mean) | doing nothing mm | random mm | held-end servo mm | MPC ms/step | "
        "wall s (max) |",
        "|---|---|---|---|---|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    summary: dict[str, Any] = {"rows": rows, "groups": {}}
    for (backend, label, counts), members in groups.items():
        scores = [m["score"] for m in members]

        def mean(key: str, members: list[dict[str, Any]] = members) -> float:
            return sum(m[key] for m in members) / len(members)

        group = {"counts": counts, "seeds": [m["seed"] for m in members], "scores": scores,
                 "mean_score": round(sum(scores) / len(scores), 3), "worst_score": min(scores),
                 "final_mm": round(mean("final_mm"), 1), "zero_mm": round(mean("zero_mm"), 1),
                 "random_mm": round(mean("random_mm"), 1),
                 "held_end_mm": servo_mean(members),
                 "mpc_ms_per_step": round(mean("mpc_ms_per_step"), 2),
                 "wall_s_max": max(m["wall_s"] for m in members)}  # fmt: skip
        summary["groups"][f"{backend}/{label}"] = group
        lines.append(
            f"| {backend} | {label} | {counts} | {', '.join(map(str, group['seeds']))} | "
            f"{' / '.join(f'{s:.3f}' for s in scores)} | {group['mean_score']:.3f} | "
            f"{group['worst_score']:.3f} | {group['final_mm']} | {group['zero_mm']} | "
            f"{group['random_mm']} | {shown(group['held_end_mm'])} | "
            f"{group['mpc_ms_per_step']} | {group['wall_s_max']} |"
        )
    lines.append(
        "\nMPC ms/step and wall s are as the runs measured them: with other runs on the same "
        "cores they are upper bounds, not comparable between rows; compare planners' MPC time "
        "through one model, taking turns (`benchmarks/flex_control_gap.py latency`)."
    )
    return "\n".join(lines) + "\n", summary


def shown(value: float | None) -> str:
    return "–" if value is None else str(value)


def servo_mean(members: list[dict[str, Any]]) -> float | None:
    """The held-end servo's mean final error over the members, None if one has none."""
    found = [m.get("held_end_mm") for m in members]
    return None if None in found else round(sum(found) / len(found), 1)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = parser.add_subparsers(dest="what", required=True)
    go = sub.add_parser("run")
    go.add_argument("out", type=Path)
    go.add_argument("--seeds", default="0,1,2,3,4")
    go.add_argument("--label", default=REFERENCE, help="names the runs' folders")
    go.add_argument("--spec", type=Path, default=None, help="a spec file added to the command")
    go.add_argument(
        "--count",
        action="append",
        default=[],
        metavar="FLAG=N",
        help="replace one of the command's counts, e.g. trials=8; repeatable",
    )
    show = sub.add_parser("report")
    show.add_argument("outs", type=Path, nargs="+")
    show.add_argument("--write", type=Path, default=None, help="stem of the .md and .json")
    args = parser.parse_args()
    if args.what == "run":
        counts = dict(item.split("=", 1) for item in args.count)
        run(args.out, [int(s) for s in args.seeds.split(",")], args.label, args.spec, counts)
        return
    table, summary = report(args.outs)
    print(table)
    if args.write is not None:
        args.write.with_suffix(".md").write_text(table)
        args.write.with_suffix(".json").write_text(json.dumps(summary, indent=1) + "\n")


if __name__ == "__main__":
    main()
