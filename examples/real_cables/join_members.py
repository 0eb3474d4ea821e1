"""Join networks trained apart into the ensemble `--members` would have trained.

    python examples/real_cables/join_members.py OUT RUN RUN [RUN ...]

Each RUN is a `dlo train` run directory of one network (one spec, the same cables, seeds
S, S+1, ...: on other machines, or at other times). OUT becomes a run directory holding
their ensemble (`dlocli.models.member_fits.joined`): `dlo eval --checkpoint OUT` scores it,
`dlo train --init-from OUT` fine-tunes it, each member with its own cable codes. Its
summary.json gives the slowest member's training seconds (the members of `--members` train
at the same time, one per core).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from dlocli.errors import BadInput, DloError
from dlocli.io import write_json_atomic
from dlocli.models.checkpoints import CABLE_KEYS, CONTROL_DT, load_marker_model, save_checkpoint
from dlocli.models.member_fits import joined


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("out", type=Path)
    parser.add_argument("runs", type=Path, nargs="+")
    args = parser.parse_args()
    try:
        join(args.out, args.runs)
    except DloError as error:  # one line and the CLI's exit code, as `dlo` gives
        print(f"error: {error}", file=sys.stderr)
        sys.exit(error.exit_code)


def join(out: Path, runs: list[Path]) -> None:
    """Write the ensemble of the networks in ``runs`` as the run directory ``out``."""
    if (out / "summary.json").exists():
        raise BadInput(f"{out} already holds a run; remove it or give another folder")
    models = [load_marker_model(run) for run in runs]
    ensemble = joined(models)
    rate = getattr(models[0], "control_dt", None)
    extra = {CABLE_KEYS: ensemble.cable_keys, **({} if rate is None else {CONTROL_DT: rate})}
    save_checkpoint(ensemble, out / "checkpoints" / "final.pt", extra)
    spec = json.loads((runs[0] / "spec.json").read_text())
    spec["model"]["members"] = len(models)
    write_json_atomic(out / "spec.json", spec)
    seconds = [json.loads((run / "summary.json").read_text())["seconds"] for run in runs]
    summary = {"joined_from": [str(run) for run in runs], "seconds": max(seconds),
               "member_seconds": seconds}  # fmt: skip
    write_json_atomic(out / "summary.json", summary)
    print(json.dumps(summary))


if __name__ == "__main__":
    main()
