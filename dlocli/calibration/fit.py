"""`dlo calibrate`: fit a simulated rod's material to a recorded cable by CMA-ES.

The objective of a candidate material is its mean replay score (DEFORM protocol, cm) over a
seeded draw of the cable's train recordings; the replays run on the spec's executor (local
processes or Ray tasks on a cluster, :mod:`dlocli.executors`), and the same seed fits the same
material on either. After every generation the candidates and their scores are written
(atomically) to OUT/history.json: a resumed run replays that history through a CMA-ES of the
same seed (ask/tell are deterministic), so it continues exactly where the finished generations
left it. The best material is scored on every eval recording next to the spec's own (the
"default material"), written as a spec for any command's --spec (OUT/calibrated.yaml: the rod,
with the recordings' control period and marker layout, :func:`recorded_task`) and reported.
"""

from __future__ import annotations

import hashlib
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from pydantic import ValidationError

from dlocli.calibration import parameters as params
from dlocli.calibration.replay import (
    RecordedArcs,
    ReplaySettings,
    check_end_pairs,
    check_rod_fits,
    grip_markers,
    replay,
)
from dlocli.calibration.spec import CalibrateSpec, ReplaySpec
from dlocli.cancel import CancelToken
from dlocli.data import protocol
from dlocli.env.observation import marker_layout
from dlocli.errors import BadInput, UnworkablePhysics
from dlocli.events import Callback, Event
from dlocli.recorded_cables import deform
from dlocli.registry import backends
from dlocli.specs import BackendSpec, ObservationSpec, RodSpec, format_validation_error

HISTORY_FILE = "history.json"
CALIBRATED_SPEC = "calibrated.yaml"
#: score (cm) of a material the simulator cannot build: worse than any replay
UNWORKABLE_SCORE_CM = 100.0


@dataclass
class Cable:
    """A cable's recordings and the simulated rod that stands for it."""

    train: list[tuple[str, np.ndarray]]
    eval: list[tuple[str, np.ndarray]]
    arc: np.ndarray  # marker arc lengths from the rod's left grip (m)
    backend: BackendSpec  # the rod at the spec's (default) material
    held: np.ndarray  # (V,) which markers the grippers hold


def load_cable(spec: CalibrateSpec) -> Cable:
    """Read and check everything a calibration needs; BadInput before anything is written."""
    if spec.source is None:
        raise BadInput("no recordings given; pass --source FOLDER (holding train/ and eval/)")
    if spec.cable_length is None or spec.cable_mass is None:
        raise BadInput(
            "the cable's length and mass are needed; pass --cable-length and "
            "--cable-mass (metres, kilograms)"
        )
    found, held = deform.read_recordings(spec.source)
    check_held(held, spec.source)
    everything = {f"{spec.source}/{s}/{n}": r for s, items in found.items() for n, r in items}
    check_end_pairs(list(everything.values()), list(everything))
    train, evaluation = found["train"], found.get("eval") or found["train"]
    grip = grip_markers(held, spec.backend.rod.clamp_compliance)
    arcs = RecordedArcs.from_recordings([r for _, r in train]).between(grip)
    rod_length = spec.rod_length or arcs.span(grip)
    if spec.cable_length < rod_length:
        raise BadInput(
            f"cable_length {spec.cable_length:g} m is shorter than the rod between its "
            f"grip markers ({rod_length:.3f} m); pass the cable's real length"
        )
    check_rod_fits(rod_length, list(everything.values()), list(everything), grip)
    rod = spec.backend.rod
    density = spec.cable_mass / spec.cable_length / rod.area
    try:
        rod = RodSpec.model_validate({**rod.model_dump(), "length": rod_length, "density": density})
        backend = BackendSpec.model_validate({**spec.backend.model_dump(), "rod": rod})
    except ValidationError as exc:
        raise BadInput(f"the cable's rod: {format_validation_error(exc)}") from None
    arc = arcs.arc * (rod_length / arcs.span(grip))
    return Cable(train, evaluation, arc, backend, held)


def check_held(held: np.ndarray, source: Path) -> None:
    """BadInput unless both end markers are held and some marker is free."""
    if not (held[0] and held[-1]) or held.all():
        raise BadInput(
            f"{source}: calibration needs both end markers held and a free one between them; "
            "import with --held naming the markers at the grippers"
        )


def replay_settings(spec: ReplaySpec, held: Sequence[bool]) -> ReplaySettings:
    """How ``spec`` replays recordings whose markers ``held`` (V,) the grippers hold."""
    return ReplaySettings(spec.roll, spec.approach_s, spec.settle_s, tuple(bool(h) for h in held))


# --------------------------------------------------------------------------- replays
def replay_named(
    backend_spec: dict[str, Any],
    arc: np.ndarray,
    settings: ReplaySettings,
    rate_hz: float,
    names: list[str],
    *recordings: np.ndarray,
) -> list[dict[str, Any]]:
    """Replay ``recordings`` (named ``names``) on one rod, an executor's call; one result
    dict per recording (score None where the simulator cannot build the rod)."""
    spec = BackendSpec.model_validate(backend_spec)
    try:
        backend = backends.get(spec.name)(spec, control_dt=1.0 / rate_hz)
    except UnworkablePhysics:
        return [{"name": n, "score_cm": None} for n in names]
    try:
        out = []
        for name, recording in zip(names, recordings, strict=True):
            result = replay(backend, recording, arc, settings)
            out.append(
                {
                    "name": name,
                    "score_cm": result.score_cm,
                    "start_error_mm": result.start_error_mm,
                    "held_error_mm": result.held_error_mm,
                    "diverged_at": result.diverged_at,
                }
            )
        return out
    finally:
        backend.close()


class Replayer:
    """Replays rods on the cable's recordings through an executor (:mod:`dlocli.executors`):
    each recording travels to it once (shared), each call replays some of them on one rod;
    ``cancel`` stops :meth:`scores` after the call that finishes once it is cancelled."""

    def __init__(
        self, cable: Cable, spec: CalibrateSpec, executor: Any, cancel: CancelToken | None = None
    ) -> None:
        self.executor = executor
        self.cancel = cancel
        self.recordings = {
            f"{split}/{n}": executor.share(r)
            for split, items in (("train", cable.train), ("eval", cable.eval))
            for n, r in items
        }
        self.fixed = (cable.arc, replay_settings(spec, cable.held), spec.rate_hz)
        # a cluster's CPUs are its own: there every recording is a call of its own
        self.slots = spec.workers if spec.ray_address is None else None

    def scores(
        self, rods: list[BackendSpec], names: list[str], progress: Callback, unit: str
    ) -> list[list[dict[str, Any]]]:
        """Per rod, the replay results of every recording of ``names``; ``progress`` gets an
        Event counting ``unit`` after each finished call. Each rod's recordings are split into
        chunks so that every worker has work even for a single rod (how they are split changes
        no number)."""
        slots = self.slots or len(rods) * len(names)
        chunks = max(1, min(len(names), -(-slots // len(rods))))
        parts = [names[i::chunks] for i in range(chunks)]
        calls, owners = [], []
        for r, rod in enumerate(rods):
            rod_json = rod.model_dump(mode="json")
            for part in parts:
                frames = [self.recordings[n] for n in part]
                calls.append((rod_json, *self.fixed, part, *frames))
                owners.append(r)
        out: list[list[dict[str, Any]]] = [[] for _ in rods]
        for k, (index, result) in enumerate(self.executor.map(replay_named, calls), start=1):
            if isinstance(result, BaseException):
                raise result
            out[owners[index]].extend(result)
            if self.cancel is not None:
                self.cancel.raise_if_cancelled()
            progress(Event(unit, k, len(calls)))
        order = {n: i for i, n in enumerate(names)}
        return [sorted(results, key=lambda x: order[x["name"]]) for results in out]


def mean_score(results: list[dict[str, Any]]) -> float:
    """The mean replay score (cm) over recordings; an unbuildable rod scores the penalty."""
    scores = [r["score_cm"] for r in results]
    return UNWORKABLE_SCORE_CM if None in scores else float(np.mean(scores))


def recordings_digest(cable: Cable) -> str:
    """A SHA-256 of every recording's name and frames: a resumed run checks its data is the
    same as when it started."""
    digest = hashlib.sha256()
    for split, recordings in (("train", cable.train), ("eval", cable.eval)):
        for name, frames in recordings:
            digest.update(f"{split}/{name}{frames.shape}".encode())
            digest.update(np.ascontiguousarray(frames, dtype=np.float64).tobytes())
    return digest.hexdigest()


def draw_train(cable: Cable, spec: CalibrateSpec) -> list[str]:
    """The seeded draw of train recordings the optimiser replays."""
    rng = np.random.default_rng(spec.seed)
    count = min(spec.train_trajectories, len(cable.train))
    picked = sorted(rng.choice(len(cable.train), size=count, replace=False))
    return [f"train/{cable.train[i][0]}" for i in picked]


def freeze_reference_cm(cable: Cable) -> float:
    """The freeze reference on the eval recordings (free markers stay at frame 1)."""
    scores = []
    for _, rec in cable.eval:
        held = cable.held
        scores.append(protocol.deform_score_cm(protocol.freeze(rec, held), rec))
    return float(np.mean(scores))


def rod_spec(cable: Cable, names: list[str], unit: np.ndarray) -> BackendSpec:
    """The cable's backend spec with the fitted fields from a point in [0, 1]^n, each field
    as the backend simulates it (:meth:`~dlocli.backends.facts.BackendFacts.effective_rod`)."""
    rod = params.decode(names, unit, cable.backend.rod)
    facts = backends.facts(cable.backend.name)
    return cable.backend.model_copy(update={"rod": facts.effective_rod(rod)})


def calibrated_yaml(backend: BackendSpec, task: dict[str, Any] | None = None) -> str:
    """The spec any command takes through --spec: the fitted rod (its ``backend`` field) and
    what ``task`` (:func:`recorded_task`) says of the recordings."""
    import yaml

    fields = {"backend": backend.model_dump(mode="json"), **({"task": task} if task else {})}
    return yaml.safe_dump(fields, sort_keys=False)


def recorded_task(cable: Cable, rate_hz: float) -> tuple[dict[str, Any], str | None]:
    """The task fields a calibrated spec carries from the recordings, and why the observation
    is left out, if it is: the control period of the recordings (the models trained on them
    step by it), and where their markers sit (the layout `--observation markers` observes:
    marker i at its arc length from the left grip over the rod's length, a held marker behind
    a grip on its gripper), unless the simulated rod's ends would hold other markers than the
    recording's."""
    task: dict[str, Any] = {"control_dt": 1.0 / rate_hz}
    rod = cable.backend.rod
    arcs = [round(float(a), 6) for a in cable.arc / rod.length]
    try:
        observation = ObservationSpec(markers=len(arcs), marker_arc_lengths=tuple(arcs),
                                      gripper_markers=0.0)  # fmt: skip
        held = marker_layout(observation, rod.length, rod.n_segments, (True, True)).held
    except (ValidationError, BadInput) as exc:
        return task, f"the markers cannot be placed on the rod ({str(exc).splitlines()[0]})"
    if not np.array_equal(held, cable.held):
        return task, (
            f"the rod's held ends hold markers {np.flatnonzero(held).tolist()}, the recording "
            f"{np.flatnonzero(cable.held).tolist()} (see clamp_compliance)"
        )
    fields = observation.model_dump(mode="json", include={"markers", "marker_arc_lengths",
                                                          "gripper_markers"})  # fmt: skip
    return {**task, "observation": fields}, None
