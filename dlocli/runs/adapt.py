"""`dlo adapt`: a model with cable codes given a new cable's code from its first recordings.

The model (a marker model trained with ``cable_code`` > 0 on several cables) reads the new
cable's first ``recordings`` train recordings; every candidate code (each training cable's
and their mean) predicts them open loop, and the one of the lowest benchmark score becomes
the new cable's code (:mod:`dlocli.models.code_pick`), a new row of the model's codes under
the new cable's key. With ``fine_tune``, the code alone ("code") or the whole model ("all")
then trains on those recordings (:func:`dlocli.models.fit.fit`) within ``update_steps`` and
``seconds``, validated on them: the pick stands unless a step predicts them better.

The run directory holds spec.json (resolved), scores.csv (each candidate's score on the
recordings read, the pick, the adapted model's and freezing's), summary.json,
checkpoints/final.pt (a checkpoint like `dlo train`'s: `dlo eval`, `dlo control --cable` and
the twins give the new cable its code) and, after a fine-tune, metrics.csv.
"""

from __future__ import annotations

import csv
import io
import math
import time
from pathlib import Path
from typing import Any

import numpy as np

from dlocli.cancel import CancelToken
from dlocli.data import MarkerDataset, load_dataset
from dlocli.errors import BadInput
from dlocli.events import Callback
from dlocli.io import prepare_run_dir, write_json_atomic, write_text_atomic
from dlocli.models.base import check_control_rate
from dlocli.models.cable_codes import cable_key, chosen_code
from dlocli.models.checkpoints import CABLE_KEYS, FINAL_CHECKPOINT, load_model, save_checkpoint
from dlocli.models.code_pick import Candidate, best, cable_names, freeze_cm, score_candidates
from dlocli.models.fit import fit
from dlocli.models.marker_model import MarkerModel
from dlocli.models.marker_training import Cable, Cables, scores_cm
from dlocli.models.spec import AdaptSpec
from dlocli.rundir import owned
from dlocli.runs.train import recorded_rate

#: what the fine-tune of each kind is called in the scores
ADAPTED = {"code": "code learned", "all": "fine-tuned"}


def run_adaptation(
    spec: AdaptSpec,
    overwrite: bool = False,
    progress: Callback | None = None,
    cancel: CancelToken | None = None,
) -> dict[str, Any]:
    """`dlo adapt` (see the module docstring); the summary of the run. Everything is
    checked before the run directory is made: bad input writes nothing."""
    if spec.checkpoint is None or spec.data is None:
        raise BadInput(
            "dlo adapt needs --checkpoint (a model with cable codes) and --data (the new "
            "cable's marker dataset)"
        )
    dataset = new_cable(spec.data, spec.recordings)
    model = coded_model(spec.checkpoint, dataset, spec.data)
    episodes = dataset.episodes("train")
    key = cable_key(dataset.held, episodes)  # the key `dlo eval` and `--cable` look the code up by
    if key in model.cable_keys:
        raise BadInput(
            f"--checkpoint {spec.checkpoint} trained on --data {spec.data}: it has the cable's "
            "own code; score it with `dlo eval`, or adapt the model to another cable"
        )
    read = episodes[: spec.recordings]
    names = cable_names(spec.checkpoint, model.cable_keys)
    with owned(spec.out):  # one writer per run directory
        out = prepare_run_dir(spec.out, overwrite)
        resolved = spec.model_copy(update={"lr": spec.fit_lr()}) if spec.fine_tune else spec
        write_json_atomic(out / "spec.json", resolved.model_dump(mode="json"))
        return _adapt_in(out, resolved, dataset, model, read, key, names, progress, cancel)


def _adapt_in(
    out: Path,
    spec: AdaptSpec,
    dataset: MarkerDataset,
    model: MarkerModel,
    read: list[np.ndarray],
    key: str,
    names: list[str],
    progress: Callback | None,
    cancel: CancelToken | None,
) -> dict[str, Any]:
    """Pick, fine-tune if asked, and write the run's files into ``out``."""
    start = time.perf_counter()
    candidates = score_candidates(model, read, dataset.held, names, progress)
    pick = best(candidates)
    pick_seconds = time.perf_counter() - start
    row = model.add_cables([key])[0]  # the new cable's code: the pick
    model.codes.data[row] = chosen_code(model.codes.data[:row], pick.row)
    model.cable = row

    cable = Cable(read, dataset.held, key)
    steps, fit_seconds, adapted_cm = 0, 0.0, None
    if spec.fine_tune is not None:
        start = time.perf_counter()
        result = fit(model, Cables([cable], [cable]), spec, progress=progress, cancel=cancel)
        fit_seconds = time.perf_counter() - start
        steps = max((r.count for r in result.history), default=0)
        adapted_cm = float(np.mean(scores_cm(model, cable)))
        _write_metrics(out / "metrics.csv", result.history)
    model.cable = row
    save_checkpoint(model, out / FINAL_CHECKPOINT,
                    {**recorded_rate(dataset), CABLE_KEYS: model.cable_keys})  # fmt: skip
    frozen = float(np.mean(freeze_cm(read, dataset.held)))
    rows = score_rows(candidates, pick, spec.fine_tune, adapted_cm, frozen)
    write_text_atomic(out / "scores.csv", _csv(rows))
    summary = {
        "model": model.spec.name,
        "checkpoint": str(spec.checkpoint),
        "data": str(spec.data),
        "recordings": len(read),
        "scores": rows,
        "picked": pick.name,
        "picked_cm": _rounded(pick.mean_cm),
        "mean_code_cm": _rounded(candidates[0].mean_cm),
        "fine_tune": spec.fine_tune,
        "adapted_cm": None if adapted_cm is None else _rounded(adapted_cm),
        "freeze_cm": _rounded(frozen),
        "update_steps": steps,
        "pick_seconds": round(pick_seconds, 2),
        "fit_seconds": round(fit_seconds, 1),
        "cable_key": key,
        "code_row": row,
        "out": str(out),
    }
    write_json_atomic(out / "summary.json", summary)
    return summary


# ---------------------------------------------------------------------- inputs
def new_cable(path: Path, recordings: int) -> MarkerDataset:
    """The new cable's marker dataset; BadInput for rod data, or fewer train recordings than
    ``recordings``."""
    dataset = load_dataset(path)
    if not isinstance(dataset, MarkerDataset):
        raise BadInput(
            f"--data {path} is simulated rod data; dlo adapt reads a recorded cable: pass a "
            "marker dataset (`dlo import`)"
        )
    count = len(dataset.episodes("train"))
    if count == 0:
        raise BadInput(
            f"--data {path} holds no train recordings to pick a code from; import a cable "
            "folder with train/ recordings"
        )
    if recordings > count:
        raise BadInput(
            f"--recordings {recordings}, but --data {path} holds {count} train recording"
            f"{'s' if count > 1 else ''}; pass --recordings {count} or fewer"
        )
    return dataset


def coded_model(path: Path, dataset: MarkerDataset, data: Path) -> MarkerModel:
    """The marker model with cable codes in ``path``, checked against the new cable's
    ``dataset``; BadInput for a rod model, one without codes, another rate or marker layout."""
    model = load_model(path, form=None)
    if not isinstance(model, MarkerModel):
        raise BadInput(
            f"--checkpoint {path} is a rod model; dlo adapt adapts a marker model with cable "
            "codes (`dlo train --cable-code D` on recorded cables)"
        )
    if not model.spec.cable_code or not model.cable_keys:
        raise BadInput(
            f"--checkpoint {path} learned no cable codes, so there is none to pick; train one "
            "on several cables with --cable-code D, or fine-tune this one with `dlo train "
            "--init-from`"
        )
    check_control_rate(model, dataset.control_dt, f"--checkpoint {path}", f"--data {data} is",
                       "adapt it to a cable recorded at {hz} Hz")  # fmt: skip
    if not model.network.any_count and not np.array_equal(model.held.numpy(), dataset.held):
        raise BadInput(
            f"--checkpoint {path} is a {model.spec.name} sized for {model.n_segments} markers "
            f"({int(model.held.sum())} held) but --data {data} has {dataset.n_markers} "
            f"({int(dataset.held.sum())} held); adapt a model that serves any marker count "
            "(arc-mlp, attention, in-bilstm)"
        )
    return model


# ---------------------------------------------------------------------- outputs
def score_rows(
    candidates: list[Candidate],
    pick: Candidate,
    fine_tune: str | None,
    adapted_cm: float | None,
    frozen: float,
) -> list[dict[str, Any]]:
    """The scores table: each candidate (the pick marked), the adapted model, freezing."""
    rows = [{"name": c.name, "score_cm": _rounded(c.mean_cm), "role": "picked" if c is pick
             else "candidate"} for c in candidates]  # fmt: skip
    if fine_tune is not None and adapted_cm is not None:
        rows.append({"name": ADAPTED[fine_tune], "score_cm": _rounded(adapted_cm),
                     "role": "adapted"})  # fmt: skip
    rows.append({"name": "freeze the free markers", "score_cm": _rounded(frozen),
                 "role": "reference"})  # fmt: skip
    return rows


def _rounded(value: float) -> float | None:
    return round(value, 4) if math.isfinite(value) else None


def _csv(rows: list[dict[str, Any]]) -> str:
    text = io.StringIO()
    writer = csv.DictWriter(text, ["name", "score_cm", "role"], lineterminator="\n")
    writer.writeheader()
    writer.writerows(rows)
    return text.getvalue()


def _write_metrics(path: Path, history: list[Any]) -> None:
    lines = ["step,k,train_loss_cm,score_cm,seconds"]
    lines += [f"{r.count},{r.k},{r.train_loss:.6g},{r.val_loss:.6g},{r.seconds:.2f}"
              for r in history]  # fmt: skip
    write_text_atomic(path, "\n".join(lines) + "\n")
