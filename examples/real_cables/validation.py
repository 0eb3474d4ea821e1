"""The validation runs behind results.md's choices, condensed into validation.json, and the
commands that run them again.

    python examples/real_cables/validation.py collect RUNS        # RUNS -> validation.json
    python examples/real_cables/validation.py commands DATA [OUT] | bash

`collect` walks a tree of `dlo train` and `dlo eval` run directories (a run nested in another
is named by its path, e.g. `all-arc-mlp-coded-u16000/ft-DLO1`) and keeps each run's resolved
spec (train runs) and summary, beside this script; the training curves (metrics.csv) stay with
the runs. `commands` prints, in order, the `dlo train` and `dlo eval` commands that rerun
every kept run into OUT (default runs/validation) on DATA/CABLE, the imported DEFORM cables
(`dlo import`, as run.sh lays them out: DATA/DLO1/data ...; DATA is run.sh's RUNS). A fine-tune
starts from the kept run it started from, rerun under OUT; where that run was not kept (the
`ftall-*` runs started from a shared model fitted on all train recordings), from the run it is
kept in.
"""

from __future__ import annotations

import json
import re
import shlex
import sys
from pathlib import Path

HERE = Path(__file__).parent
KEPT = HERE / "validation.json"
CABLE = re.compile(r"DLO\d")


def collect(runs: Path) -> dict:
    kept = {}
    for summary in sorted(runs.rglob("summary.json")):
        run = summary.parent
        entry = {"summary": json.loads(summary.read_text())}
        if (run / "spec.json").is_file():
            entry = {"spec": json.loads((run / "spec.json").read_text()), **entry}
        kept[run.relative_to(runs).as_posix()] = entry
    return kept


def _cable_data(path: str, data: Path) -> str:
    (cable,) = CABLE.findall(Path(path).as_posix())[-1:]
    return str(data / cable / "data")


def _run_named(path: str | None, name: str, outs: dict[str, str], out: Path) -> str | None:
    """The kept run a saved path (absolute, or relative to where it ran) names, under OUT; a
    run copied here from elsewhere starts from the run it is kept in."""
    if path is None:
        return None
    matches = [run for saved, run in outs.items() if saved == path or saved.endswith(f"/{path}")]
    parent = name.rpartition("/")[0]
    if len(matches) != 1 and parent not in outs.values():
        raise SystemExit(f"{name}: no single kept run wrote {path}: {matches}")
    return str(out / (matches[0] if len(matches) == 1 else parent))


def commands(kept: dict, data: Path, out: Path) -> list[str]:
    """Train runs first (a fine-tune after the run it starts from), then evaluations."""
    outs = {entry["spec"]["out"]: name for name, entry in kept.items() if "spec" in entry}
    specs_dir = out / "specs"
    lines = [f"mkdir -p {shlex.quote(str(specs_dir))}"]
    trains = [name for name, entry in kept.items() if "spec" in entry]
    trains.sort(key=lambda name: kept[name]["spec"].get("init_from") is not None)
    for name in trains:
        spec = dict(kept[name]["spec"])
        saved = spec["data"]
        spec["data"] = ([_cable_data(p, data) for p in saved] if isinstance(saved, list)
                        else _cable_data(saved, data))  # fmt: skip
        spec["init_from"] = _run_named(spec.get("init_from"), name, outs, out)
        spec.pop("out", None)
        path = specs_dir / (name.replace("/", "__") + ".json")
        lines.append(f"cat > {shlex.quote(str(path))} <<'SPEC'\n{json.dumps(spec)}\nSPEC")
        lines.append(
            f"dlo train --spec {shlex.quote(str(path))} --out {shlex.quote(str(out / name))}"
            " --overwrite --json > /dev/null"
        )
    for name, entry in kept.items():
        if "spec" in entry:
            continue
        summary = entry["summary"]
        checkpoint = _run_named(summary["checkpoint"], name, outs, out)
        lines.append(
            f"dlo eval --checkpoint {shlex.quote(checkpoint)}"
            f" --data {shlex.quote(_cable_data(summary['data'], data))}"
            f" --out {shlex.quote(str(out / name))} --overwrite --json > /dev/null"
        )
    return lines


def main(argv: list[str]) -> None:
    if len(argv) >= 2 and argv[0] == "collect":
        KEPT.write_text(json.dumps(collect(Path(argv[1])), indent=1) + "\n")
    elif len(argv) >= 2 and argv[0] == "commands":
        out = Path(argv[2] if len(argv) > 2 else "runs/validation")
        print("set -euo pipefail")
        print("\n".join(commands(json.loads(KEPT.read_text()), Path(argv[1]), out)))
    else:
        raise SystemExit(__doc__)


if __name__ == "__main__":
    main(sys.argv[1:])
