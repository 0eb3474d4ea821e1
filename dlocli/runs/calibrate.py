"""`dlo calibrate`: CMA-ES generations over the rod's material with a checkpoint each, then
the eval report; resumable after any finished generation, on any executor."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import numpy as np

from dlocli.calibration import parameters as params
from dlocli.calibration.fit import (
    CALIBRATED_SPEC,
    HISTORY_FILE,
    Cable,
    Replayer,
    calibrated_yaml,
    draw_train,
    freeze_reference_cm,
    load_cable,
    mean_score,
    recorded_task,
    recordings_digest,
    rod_spec,
)
from dlocli.calibration.history import read_history
from dlocli.calibration.report import write_report
from dlocli.calibration.spec import CalibrateSpec
from dlocli.cancel import CancelToken
from dlocli.errors import BadInput, DloError
from dlocli.events import Callback, Event, ignore
from dlocli.executors import ClusterLost, check_executor, open_executor
from dlocli.extras import require
from dlocli.io import (
    adopt_written,
    prepare_run_dir,
    write_json_atomic,
    write_text_atomic,
)
from dlocli.recorded_cables import deform
from dlocli.registry import backends
from dlocli.resume import resumed_run_spec
from dlocli.rundir import owned, refuse_out_by_source

#: a generation's record in history.json (its candidates and scores), a state read from it
Record = dict[str, Any]


def new_strategy(spec: CalibrateSpec, cable: Cable) -> Any:
    """A CMA-ES over [0, 1]^n started at the spec's material."""
    import cma

    x0 = params.encode(spec.parameters, cable.backend.rod, cable.backend.name)
    # pycma refuses a start exactly on a bound
    x0 = np.clip(x0, 1e-3, 1 - 1e-3)
    options = {
        "bounds": [0.0, 1.0],
        "popsize": spec.population,
        "seed": spec.seed + 1,
        "verbose": -9,
    }
    return cma.CMAEvolutionStrategy(x0.tolist(), spec.sigma0, options)


def replay_history(strategy: Any, history: list[Record], out: Path) -> None:
    """Feed the recorded generations to a fresh strategy; BadInput if it asks otherwise."""
    for generation in history:
        asked = np.array(strategy.ask())
        recorded = np.array(generation["candidates"])
        if asked.shape != recorded.shape or not np.allclose(asked, recorded, atol=1e-9):
            raise BadInput(
                f"--resume {out}: {HISTORY_FILE} does not match this CMA-ES (another seed or "
                "library version wrote it); start a new run"
            )
        strategy.tell(list(asked), generation["scores"])


def check_same_recordings(state: Record, digest: str, spec: CalibrateSpec) -> None:
    """BadInput when the recordings a resumed run started on have changed since."""
    if state.get("recordings", digest) != digest:
        raise BadInput(
            f"--resume {spec.out}: the recordings under {spec.source} changed since this run "
            "started; restore them, or start a new run with --overwrite"
        )


#: what a resumed calibration may change: where the replays run, and how many generations
FREE_FIELDS = frozenset({"workers", "generations", "executor", "ray_address"})


def resumed_spec(run_dir: Path, overrides: dict[str, Any]) -> CalibrateSpec:
    """`dlo calibrate --resume RUN`: the spec of the run in ``run_dir`` (pass it to
    :func:`run_calibration` with ``resume=True``); flags that contradict it are refused, but
    for :data:`FREE_FIELDS`."""
    return resumed_run_spec(
        CalibrateSpec, run_dir, overrides, "a calibration", "dlo calibrate", free=FREE_FIELDS
    )


def at_recorded_rate(spec: CalibrateSpec) -> CalibrateSpec:
    """``spec`` replaying at the frame rate of the dataset a `dlo import` run directory as
    --source states; BadInput if the spec sets another."""
    data = deform.imported(spec.source)
    if data is None or data.rate_hz == spec.rate_hz:
        return spec
    if "rate_hz" in spec.model_fields_set:
        raise BadInput(
            f"rate_hz {spec.rate_hz:g} in the spec, but {spec.source} was imported at "
            f"{data.rate_hz:g} Hz; drop rate_hz (the import's rate is used)"
        )
    return spec.model_copy(update={"rate_hz": data.rate_hz})


def run_calibration(
    spec: CalibrateSpec,
    overwrite: bool,
    progress: Callback | None = None,
    resume: bool = False,
    cancel: CancelToken | None = None,
) -> dict[str, Any]:
    """Calibrate (see :mod:`dlocli.calibration.fit`); return the summary. ``progress`` gets
    an Event per finished generation (``best_cm``: the best train score so far), per replay
    of a generation's candidates ("replay") and per eval replay ("eval"); ``cancel`` stops it
    between replays."""
    progress = progress or ignore
    backends.check(spec.backend.name)
    require("calibrate", "dlo calibrate (CMA-ES from pycma)")
    check_executor(spec.executor, spec.ray_address)
    refuse_out_by_source(spec)
    spec = at_recorded_rate(spec)
    cable = load_cable(spec)  # every input checked before OUT is touched
    task, unobserved = recorded_task(cable, spec.rate_hz)
    names = draw_train(cable, spec)
    strategy = new_strategy(spec, cable)
    # the executor connects first: an address that fails leaves the directory as it was
    with open_executor(spec) as executor, owned(spec.out):
        out = Path(spec.out) if resume else prepare_run_dir(spec.out, overwrite)
        history_file = out / HISTORY_FILE
        state = read_history(history_file, spec) if resume and history_file.is_file() else {}
        digest = recordings_digest(cable)
        check_same_recordings(state, digest, spec)
        if resume:  # a run killed outright could not record its files as dlo's
            adopt_written(out, {HISTORY_FILE, "spec.json"})
        write_json_atomic(out / "spec.json", spec.model_dump(mode="json"))
        history: list[Record] = state.get("generations", [])
        elapsed = float(state.get("seconds", 0.0))
        try:
            replayer = Replayer(cable, spec, executor, cancel)
            replay_history(strategy, history, out)
            started = time.perf_counter()
            for g in range(len(history), spec.generations):
                history.append(_generation(strategy, replayer, cable, spec, names, progress))
                seconds = elapsed + time.perf_counter() - started
                write_json_atomic(
                    history_file, {"generations": history, "seconds": seconds, "recordings": digest}
                )
                best_cm = min(min(h["scores"]) for h in history)
                progress(Event("generation", g + 1, spec.generations, {"best_cm": best_cm}))
            fit_seconds = elapsed + time.perf_counter() - started
            best = _best(history)
            calibrated = rod_spec(cable, spec.parameters, np.array(best["candidate"]))
            eval_names = [f"eval/{n}" for n, _ in cable.eval]
            before, after = replayer.scores(
                [cable.backend, calibrated],
                eval_names,
                progress,
                "eval",
            )
        except ClusterLost as lost:  # the finished generations are in history.json
            raise DloError(lost.line(out)) from lost
        summary = _summary(spec, cable, names, history, best, before, after, fit_seconds)
        summary["recordings_sha256"] = digest
        summary["calibrated"] = calibrated.model_dump(mode="json")
        summary["task"] = task
        if unobserved is not None:
            summary["observation_left_out"] = unobserved
        write_text_atomic(out / CALIBRATED_SPEC, calibrated_yaml(calibrated, task))
        write_report(out, summary)
        summary["out"] = str(out)
    return summary


def _generation(
    strategy: Any,
    replayer: Replayer,
    cable: Cable,
    spec: CalibrateSpec,
    names: list[str],
    progress: Callback,
) -> Record:
    """Ask for candidates, replay the train draw on each, tell the scores; the record."""
    candidates = np.array(strategy.ask())
    rods = [rod_spec(cable, spec.parameters, x) for x in candidates]
    results = replayer.scores(rods, names, progress, "replay")
    scores = [mean_score(r) for r in results]
    strategy.tell(list(candidates), scores)
    return {"candidates": candidates.tolist(), "scores": scores}


def _best(history: list[Record]) -> Record:
    """The best candidate ever scored (on the train draw)."""
    flat = [(s, c) for h in history for s, c in zip(h["scores"], h["candidates"], strict=True)]
    score, candidate = min(flat, key=lambda x: x[0])
    return {"score_cm": score, "candidate": candidate}


def _summary(
    spec: CalibrateSpec,
    cable: Cable,
    names: list[str],
    history: list[Record],
    best: Record,
    before: list[Record],
    after: list[Record],
    seconds: float,
) -> dict[str, Any]:
    start = params.encode(spec.parameters, cable.backend.rod, cable.backend.name)
    fitted = params.decode(spec.parameters, np.array(best["candidate"]), cable.backend.rod)
    return {
        "cable": Path(spec.source).name if spec.source else None,
        "backend": cable.backend.name,
        "rod_length_m": round(cable.backend.rod.length, 4),
        "density_kg_m3": round(cable.backend.rod.density, 2),
        "parameters": {n: getattr(fitted, n) for n in spec.parameters},
        "default_parameters": {
            n: params.start_value(n, cable.backend.rod, cable.backend.name) for n in spec.parameters
        },
        "start_point": start.tolist(),
        "train_recordings": names,
        "generations": len(history),
        "evaluations": sum(len(h["scores"]) for h in history),
        "fit_seconds": round(seconds, 1),
        "train_best_cm": round(best["score_cm"], 4),
        "eval_default_cm": round(mean_score(before), 4),
        "eval_calibrated_cm": round(mean_score(after), 4),
        "eval_freeze_cm": round(freeze_reference_cm(cable), 4),
        "eval_start_error_mm": round(
            float(
                np.mean([r["start_error_mm"] for r in after if r["score_cm"] is not None] or [0])
            ),
            2,
        ),
        "eval_held_error_mm": round(
            float(np.mean([r["held_error_mm"] for r in after if r["score_cm"] is not None] or [0])),
            2,
        ),
        "eval_diverged": sum(r.get("diverged_at") is not None for r in after),
        "eval_per_recording": {
            r["name"]: [b["score_cm"], r["score_cm"]] for b, r in zip(before, after, strict=True)
        },
    }
