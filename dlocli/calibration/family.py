"""Many simulated cables from calibrated ones: a family of rods whose materials span and
exceed the calibrated rods', each driven by a recorded cable's held-marker motion (with
several source cables, cable k by source k mod their count).

Cable k's material is drawn log-uniformly, field by field (:data:`DRAWN`), between the
smallest calibrated value / ``widen`` and the largest * ``widen``, within the range the
simulator takes (:data:`BOUNDS`); calibrated rods of different radii are compared at the first
one's (E I and the mass per length kept). Its rod is the source cable's (the cable between its
grip markers) times a length factor drawn uniformly from ``length_scale``; the source's
recorded motion is scaled by that factor about its centre, so the grips stay as far apart,
relative to the rod, as the recorded ones. Its trajectories are :func:`simulate_markers`'s:
the source's train recordings (eval recordings for the eval split), moved rigidly, replayed
on the rod; a trajectory that diverges is dropped and counted, and a cable left with fewer
train trajectories than `dlo train` validates with (two, or one where one was asked) is not
written (:func:`keeps_dataset`).

Folder (every file written atomically)::

    spec.json               the resolved FamilySpec
    sim-NNN/dataset.h5      cable NNN's marker dataset (a `dlo import` run's layout: `dlo
                            train --data`, `dlo eval --data`); attrs: rate_hz, source, material
    sim-NNN/rod.yaml        its rod, a spec for any command's --spec
    summary.json            one row per cable: its material, source, trajectories kept and
                            dropped; the sources read
"""

from __future__ import annotations

import math
import shlex
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import yaml
from pydantic import ValidationError

from dlocli.calibration.fit import CALIBRATED_SPEC, calibrated_yaml, check_held, replay_settings
from dlocli.calibration.parameters import PARAMETERS
from dlocli.calibration.replay import (
    RecordedArcs,
    check_end_pairs,
    check_rod_fits,
    grip_markers,
)
from dlocli.calibration.simulate import simulate_markers
from dlocli.calibration.spec import FamilySpec
from dlocli.cancel import CancelToken
from dlocli.data import MarkerDataset
from dlocli.data.markers import DEFAULT_RATE_HZ
from dlocli.errors import BadInput, UnworkablePhysics
from dlocli.events import Began, Callback, Event, ignore
from dlocli.io import prepare_run_dir, remove_unwritten, write_json_atomic, write_text_atomic
from dlocli.recorded_cables import deform
from dlocli.registry import backends
from dlocli.rundir import owned, refuse_out_among
from dlocli.specs import BackendSpec, RodSpec, format_validation_error

#: the rod fields drawn per cable
DRAWN = ("young_bending", "density", "bending_damping", "air_damping")
#: where a drawn field may go: the calibration's range where it has one (below its bending
#: damping MuJoCo's explicit elasticity is unstable), else the rod spec's
BOUNDS = {
    "young_bending": (PARAMETERS["young_bending"].low, PARAMETERS["young_bending"].high),
    "density": (10.0, 1e5),
    "bending_damping": (PARAMETERS["bending_damping"].low, PARAMETERS["bending_damping"].high),
    "air_damping": (PARAMETERS["air_damping"].low, PARAMETERS["air_damping"].high),
}
SPLITS = ("train", "eval")


@dataclass
class Source:
    """A recorded cable that drives cables of the family: its recordings, where its markers
    sit on its rod, which it holds, and its frame rate."""

    path: Path
    recordings: dict[str, list[np.ndarray]]  # per split
    arc: np.ndarray  # marker arc lengths from the rod's left grip (m)
    rod_length: float
    held: np.ndarray
    rate_hz: float


def read_calibrated(path: Path) -> BackendSpec:
    """The rod of a calibrated spec (a file, or a run directory holding calibrated.yaml);
    BadInput unless it is a rod of a registered backend."""
    path = Path(path)
    file = path / CALIBRATED_SPEC if path.is_dir() else path
    try:
        fields = yaml.safe_load(file.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, yaml.YAMLError) as exc:
        reason = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise BadInput(f"--calibrated {path}: cannot read it ({reason}); pass a "
                       "calibrated.yaml of `dlo calibrate`") from None  # fmt: skip
    backend = fields.get("backend") if isinstance(fields, dict) else None
    if not isinstance(backend, dict):
        raise BadInput(f"--calibrated {path} holds no backend rod; pass a calibrated.yaml of "
                       "`dlo calibrate`")  # fmt: skip
    try:
        spec = BackendSpec.model_validate(backend)
    except ValidationError as exc:
        raise BadInput(f"--calibrated {path}: {format_validation_error(exc)}") from None
    backends.check(spec.name)
    return spec


def read_rods(paths: list[Path]) -> list[BackendSpec]:
    """The calibrated rods, every input checked; BadInput if there are none or their
    backends differ."""
    if not paths:
        raise BadInput("no calibrated rods given; pass --calibrated FILE (a `dlo calibrate` "
                       "run's calibrated.yaml), once per rod")  # fmt: skip
    rods = [read_calibrated(p) for p in paths]
    names = sorted({r.name for r in rods})
    if len(names) > 1:
        raise BadInput(f"the calibrated rods are of different backends ({', '.join(names)}); "
                       "pass rods calibrated on one")  # fmt: skip
    return rods


def read_sources(spec: FamilySpec, clamp_compliance: str) -> list[Source]:
    """Every source cable's recordings, marker layout and rate; BadInput before anything is
    written."""
    if not spec.source:
        raise BadInput("no recordings given; pass --source FOLDER (holding train/ and eval/, "
                       "or a `dlo import` run)")  # fmt: skip
    lengths = spec.rod_length or [None] * len(spec.source)
    return [read_source(path, length, spec.rate_hz, clamp_compliance)
            for path, length in zip(spec.source, lengths, strict=True)]  # fmt: skip


def read_source(
    path: Path, rod_length: float | None, rate_hz: float | None, clamp_compliance: str
) -> Source:
    """One source cable's recordings, marker layout and rate (as `dlo calibrate` reads a
    cable); its rod ``rod_length`` long, else its markers' mean span between the grips."""
    found, held = deform.read_recordings(path)
    check_held(held, path)
    named = {f"{path}/{s}/{n}": r for s, items in found.items() for n, r in items}
    check_end_pairs(list(named.values()), list(named))
    train = [r for _, r in found["train"]]
    evaluation = [r for _, r in found.get("eval") or found["train"]]
    grip = grip_markers(held, clamp_compliance)
    arcs = RecordedArcs.from_recordings(train).between(grip)
    rod_length = rod_length or arcs.span(grip)
    check_rod_fits(rod_length, list(named.values()), list(named), grip)
    imported = deform.imported(path)
    rate = rate_hz or (imported.rate_hz if imported is not None else DEFAULT_RATE_HZ)
    if imported is not None and rate_hz and rate_hz != imported.rate_hz:
        raise BadInput(f"--rate-hz {rate_hz:g}, but {path} was imported at "
                       f"{imported.rate_hz:g} Hz; drop --rate-hz")  # fmt: skip
    arc = arcs.arc * (rod_length / arcs.span(grip))
    return Source(Path(path), {"train": train, "eval": evaluation}, arc, rod_length, held, rate)


def at_radius(rod: RodSpec, radius: float, backend: str) -> dict[str, float]:
    """The drawn fields of ``rod`` for a rod of ``radius`` with its E I and mass per length
    (a None field: what the backend says it stands for)."""
    facts = backends.facts(backend)
    values = {}
    for name in DRAWN:
        value = getattr(rod, name)
        value = facts.unset_rod_values.get(name) if value is None else value
        values[name] = float(value if value is not None else 0.0)
    values["young_bending"] *= (rod.radius / radius) ** 4
    values["density"] *= (rod.radius / radius) ** 2
    return values


def material_span(rods: list[BackendSpec], widen: float) -> dict[str, tuple[float, float]]:
    """Per drawn field, the (low, high) it is drawn between."""
    radius = rods[0].rod.radius
    values = [at_radius(r.rod, radius, r.name) for r in rods]
    span = {}
    for name in DRAWN:
        low, high = BOUNDS[name]
        given = [max(v[name], low) for v in values]  # an unset (zero) damping: the bound
        span[name] = (min(max(min(given) / widen, low), high),
                      max(min(max(given) * widen, high), low))  # fmt: skip
    return span


def draw_materials(spec: FamilySpec, span: dict[str, tuple[float, float]],
                   base_lengths: list[float]) -> list[dict[str, float]]:  # fmt: skip
    """Each cable's drawn fields, its length factor and rod length (cable k's source's rod,
    ``base_lengths[k mod their count]``, times the factor): the same for a seed."""
    rng = np.random.default_rng([spec.seed, 1])
    out = []
    for k in range(spec.cables):
        base_length = base_lengths[k % len(base_lengths)]
        row = {n: float(math.exp(rng.uniform(math.log(lo), math.log(hi))))
               for n, (lo, hi) in span.items()}  # fmt: skip
        row["length_scale"] = float(rng.uniform(*spec.length_scale))
        row["length"] = base_length * row["length_scale"]
        out.append(row)
    return out


def cable_rod(base: BackendSpec, material: dict[str, float]) -> BackendSpec:
    """The first calibrated rod with ``material``'s fields, as its backend simulates them;
    BadInput if the rod spec refuses it (a length beyond its range)."""
    fields = {n: material[n] for n in (*DRAWN, "length")}
    try:
        rod = RodSpec.model_validate({**base.rod.model_dump(), **fields})
    except ValidationError as exc:
        raise BadInput(f"a drawn rod: {format_validation_error(exc)}; narrow --length-scale "
                       "or pass another --rod-length") from None  # fmt: skip
    return base.model_copy(update={"rod": backends.facts(base.name).effective_rod(rod)})


def scaled(recording: np.ndarray, factor: float) -> np.ndarray:
    """A (T,V,3) recording scaled about its centre."""
    centre = recording.reshape(-1, 3).mean(0)
    return (recording - centre) * factor + centre


def run_family(
    spec: FamilySpec,
    overwrite: bool = False,
    progress: Callback | None = None,
    cancel: CancelToken | None = None,
) -> dict[str, Any]:
    """Write ``spec.cables`` simulated cables into ``spec.out`` (module docstring); return the
    summary. ``progress`` gets a Began (unit "trajectory"), then an Event after each simulated
    trajectory (``values``: its ``cable``). ``cancel`` stops it between trajectories: the
    cables finished are kept with a summary of them marked ``stopped``."""
    progress, cancel = progress or ignore, cancel or CancelToken()
    rods = read_rods(spec.calibrated)
    base = rods[0]
    sources = read_sources(spec, base.rod.clamp_compliance)
    refuse_out_among(spec.out, spec.source)
    span = material_span(rods, spec.widen)
    materials = draw_materials(spec, span, [s.rod_length for s in sources])
    built = [cable_rod(base, m) for m in materials]  # every rod checked before writing
    rows: list[dict[str, Any]] = []
    with owned(spec.out):
        out = prepare_run_dir(spec.out, overwrite)
        write_json_atomic(out / "spec.json", spec.model_dump(mode="json"))
        total = spec.cables * (spec.train + spec.eval)
        progress(Began("trajectory", 0, total))
        try:
            for k, (material, rod) in enumerate(zip(materials, built, strict=True)):
                cancel.raise_if_cancelled()
                done = k * (spec.train + spec.eval)
                source = sources[k % len(sources)]
                rows.append(_cable(spec, source, k, material, rod, out, progress, cancel, done))
        except KeyboardInterrupt as stop:
            if rows:
                remove_unwritten(out, ["sim-*"], _written(out, rows))
                summary = _summary(spec, sources, span, rows, out, type(stop).__name__)
                write_json_atomic(out / "summary.json", summary)
            raise
        remove_unwritten(out, ["sim-*"], _written(out, rows))
        summary = _summary(spec, sources, span, rows, out)
        write_json_atomic(out / "summary.json", summary)
    return summary


def _cable(
    spec: FamilySpec,
    source: Source,
    k: int,
    material: dict[str, float],
    rod: BackendSpec,
    out: Path,
    progress: Callback,
    cancel: CancelToken,
    done: int,
) -> dict[str, Any]:
    """Simulate cable ``k`` and write its folder; its summary row."""
    name = f"sim-{k:03d}"
    row: dict[str, Any] = {"cable": name, **{n: material[n] for n in (*DRAWN, "length")},
                           "length_scale": material["length_scale"],
                           "source": str(source.path)}  # fmt: skip
    factor = material["length_scale"]
    settings = replay_settings(spec, source.held)
    counts = {"train": spec.train, "eval": spec.eval}
    kept: dict[str, list[tuple[str, np.ndarray]]] = {}
    dropped = 0
    try:
        backend = backends.get(rod.name)(rod, control_dt=1.0 / source.rate_hz)
    except UnworkablePhysics as exc:
        total = spec.cables * sum(counts.values())
        progress(Event("trajectory", done + sum(counts.values()), total, {"cable": name}))
        return {**row, "train_trajectories": 0, "eval_trajectories": 0,
                "dropped_diverged": 0, "dataset": None, "unworkable": str(exc)}  # fmt: skip
    try:
        for s, split in enumerate(SPLITS):
            if not counts[split]:
                continue
            start = done + (spec.train if split == "eval" else 0)

            def tick(event: Event, start: int = start) -> None:
                cancel.raise_if_cancelled()
                total = spec.cables * (spec.train + spec.eval)
                progress(Event("trajectory", start + event.done, total, {"cable": name}))

            seed = int(np.random.SeedSequence([spec.seed, k, s]).generate_state(1)[0])
            recordings = [scaled(r, factor) for r in source.recordings[split]]
            sims, lost = simulate_markers(backend, recordings, source.arc * factor,
                                          counts[split], seed, settings, tick)  # fmt: skip
            dropped += lost
            if sims:
                kept[split] = [(f"{name}-{split}{i}", a) for i, a in enumerate(sims)]
    finally:
        backend.close()
    row["train_trajectories"] = len(kept.get("train", []))
    row["eval_trajectories"] = len(kept.get("eval", []))
    row["dropped_diverged"] = dropped
    if not keeps_dataset(row["train_trajectories"], spec.train):
        return {**row, "dataset": None}
    attrs = {"rate_hz": source.rate_hz, "source": str(source.path), "material": row}
    (out / name).mkdir(exist_ok=True)
    MarkerDataset.from_trajectories(kept, source.held, attrs).save(out / name / "dataset.h5")
    write_text_atomic(out / name / "rod.yaml",
                      calibrated_yaml(rod, {"control_dt": 1.0 / source.rate_hz}))  # fmt: skip
    return {**row, "dataset": str(out / name)}


def keeps_dataset(kept: int, asked: int) -> bool:
    """Whether a cable that kept ``kept`` of ``asked`` train trajectories is written: `dlo
    train` holds trajectories of each dataset out for validation, so it needs two (one where
    only one was asked: that family is trained with --val-fraction 0)."""
    return kept >= min(2, asked)


def _written(out: Path, rows: list[dict[str, Any]]) -> set[Path]:
    """The cable folders this run wrote (a cable that kept no trajectory has none)."""
    return {out / row["cable"] for row in rows if row["dataset"]}


def _source_row(source: Source) -> dict[str, Any]:
    """A source cable as the summary lists it."""
    return {"source": str(source.path), "rate_hz": source.rate_hz,
            "markers": len(source.held), "rod_length": source.rod_length}  # fmt: skip


def _summary(
    spec: FamilySpec,
    sources: list[Source],
    span: dict[str, tuple[float, float]],
    rows: list[dict[str, Any]],
    out: Path,
    stopped: str | None = None,
) -> dict[str, Any]:
    """The counts, the span drawn from, each cable's row, and a command that trains on them."""
    written = [r["dataset"] for r in rows if r["dataset"]]
    data = " ".join(f"--data {shlex.quote(d)}" for d in written[:2])
    data = f"--data RECORDED {data}{' ...' if len(written) > 2 else ''}"
    summary: dict[str, Any] = {
        "cables": len(rows),
        "datasets": len(written),
        "sources": [_source_row(s) for s in sources],
        "span": {n: list(v) for n, v in span.items()},
        "rows": rows,
        "next": f"dlo train {data} --cable-code 8 --out runs/NAME",
        "out": str(out),
    }
    if stopped is not None:
        summary["stopped"] = stopped
    return summary
