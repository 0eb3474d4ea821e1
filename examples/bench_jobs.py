"""A bench run kept small: its summary here, its job files rebuilt from the summary elsewhere.

    python examples/bench_jobs.py keep RUN EXAMPLE     # after `dlo bench --out RUN`
    python examples/bench_jobs.py unpack EXAMPLE RUN   # a copy to resume or report on

A `dlo bench` run directory holds one file per finished job (`jobs/AGENT-sSEED.json`: its
evaluation rows and what made them). `keep` copies a run's spec.json, results.csv, summary.md,
summary.json and plots/ into examples/EXAMPLE and condenses its job files into jobs.json (each
job's agent, seed, fingerprint, options, versions and seconds: everything but the rows, which
results.csv holds). `unpack` rebuilds the job files from the two into RUN (outside the
repository): `dlo bench --resume RUN` then reruns none of the finished jobs, and `dlo bench
--report RUN` redraws the tables and plots.
"""

from __future__ import annotations

import csv
import json
import re
import shutil
import sys
from pathlib import Path

HERE = Path(__file__).parent
KEPT = ("spec.json", "results.csv", "summary.md", "summary.json")
INTEGER = re.compile(r"-?\d+")


def _value(text: str) -> int | float | str | None:
    """A results.csv cell as the job file held it (the CSV writes None as empty)."""
    if text == "":
        return None
    if INTEGER.fullmatch(text):
        return int(text)
    try:
        return float(text)
    except ValueError:
        return text


def keep(run: Path, example: Path) -> None:
    example.mkdir(parents=True, exist_ok=True)
    for name in KEPT:
        if (run / name).is_file():
            shutil.copy(run / name, example / name)
    if (run / "plots").is_dir():
        shutil.copytree(run / "plots", example / "plots", dirs_exist_ok=True)
    jobs = {}
    for path in sorted((run / "jobs").glob("*.json")):
        job = json.loads(path.read_text())
        jobs[path.stem] = {k: v for k, v in job.items() if k != "rows"}
    (example / "jobs.json").write_text(json.dumps(jobs, indent=1) + "\n")


def job_files(example: Path) -> dict[str, dict]:
    """Each kept job's file (by its name without .json), rows from results.csv."""
    jobs = json.loads((example / "jobs.json").read_text())
    with open(example / "results.csv", newline="") as f:
        rows = [{k: _value(v) for k, v in row.items()} for row in csv.DictReader(f)]
    files = {}
    for name, job in jobs.items():
        own = [r for r in rows if r["agent"] == job["agent"] and r["seed"] == int(job["seed"])]
        files[name] = {**job, "rows": own}
    return files


def unpack(example: Path, run: Path) -> None:
    (run / "jobs").mkdir(parents=True, exist_ok=True)
    shutil.copy(example / "spec.json", run / "spec.json")
    for name, job in job_files(example).items():
        (run / "jobs" / f"{name}.json").write_text(json.dumps(job, indent=1) + "\n")


def main(argv: list[str]) -> None:
    if len(argv) == 3 and argv[0] == "keep":
        keep(Path(argv[1]), Path(argv[2]))
    elif len(argv) == 3 and argv[0] == "unpack":
        unpack(Path(argv[1]), Path(argv[2]))
    else:
        raise SystemExit(__doc__)


if __name__ == "__main__":
    main(sys.argv[1:])
