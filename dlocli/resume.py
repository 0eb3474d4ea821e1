"""Resuming a run from its directory: the saved spec (its older layouts migrated, completed
with the fields it predates) and the check that flags given with ``--resume`` do not
contradict it."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any, TypeVar

from dlocli.errors import BadInput
from dlocli.migrations import completed
from dlocli.specs import Spec, validated

SpecT = TypeVar("SpecT", bound=Spec)


def saved_spec(path: Path) -> Any:
    """A run's spec.json as data, its model, task, rod and fit specs completed with the fields they
    predate (ValueError if it is not JSON): a run keeps its meaning when a default changes."""
    data = json.loads(Path(path).read_text())
    if not isinstance(data, dict):
        return data
    for kind in ("model", "task", "fit"):
        if isinstance(data.get(kind), dict):
            data[kind] = completed(kind, data[kind])
    backend = data.get("backend")
    if isinstance(backend, dict):
        rod = backend.get("rod", {})
        data["backend"] = completed("backend", backend)
        if isinstance(rod, dict):
            data["backend"]["rod"] = completed("rod", rod)
    planner = data.get("planner", "mpc")  # runs saved before the planner could be chosen: mpc
    if isinstance(planner, str) and isinstance(data.get("mpc"), dict):  # an online or bench run
        data["mpc"] = completed(planner, data["mpc"])
    if "epochs" in data:  # a train run: the fit fields are its own
        data = completed("fit", data)
    return data


def load_saved_spec(cls: type[SpecT], path: Path) -> SpecT:
    """The run spec.json at ``path`` as a ``cls`` spec: older layouts migrated, the fields it
    predates at their legacy values (ValueError if it is not JSON or not a ``cls`` spec)."""
    return cls.model_validate(cls.saved_layout(saved_spec(path)))


def resumed_run_spec(
    cls: type[SpecT],
    run_dir: Path,
    overrides: dict[str, Any],
    kind: str,
    command: str,
    free: frozenset = frozenset(),
) -> SpecT:
    """The saved spec of the ``command`` run (a ``kind`` run) in ``run_dir``, its ``out`` set
    to ``run_dir`` and the ``free`` fields given in ``overrides`` applied; BadInput if there is
    none or a flag contradicts it."""
    spec_path = Path(run_dir) / "spec.json"
    if not spec_path.is_file():
        raise BadInput(
            f"--resume {run_dir} is not {kind} run (no spec.json); "
            f"pass the --out directory of an earlier `{command}`"
        )
    try:
        saved = cls.saved_layout(saved_spec(spec_path))  # the load boundary of a resume
    except ValueError as exc:
        raise BadInput(
            f"--resume {run_dir}: spec.json is not JSON; pass the directory of a `{command}` run"
        ) from exc
    data = validated(cls, saved, f"--resume {run_dir}: spec.json (not {kind} spec?)").model_dump()
    refuse_resume_conflicts(data, overrides, run_dir, free)
    changed = {k: v for k, v in overrides.items() if k in free and v is not None}
    if changed.get("executor") == "local" and "ray_address" in free:
        changed.setdefault("ray_address", None)  # back from a cluster: its address stays behind
    # the flags a resume takes are checked as a fresh run checks them
    return validated(cls, {**data, **changed, "out": Path(run_dir)}, f"--resume {run_dir}")


def refuse_resume_conflicts(
    saved: dict[str, Any], overrides: dict[str, Any], run_dir: Path, free: frozenset = frozenset()
) -> None:
    """BadInput if a flag given with ``--resume`` contradicts the run's saved spec.

    ``saved`` is the spec as data, ``overrides`` the flags (dotted paths, None = not given);
    fields whose first part is in ``free`` may change on resume.
    """
    for dotted, value in overrides.items():
        if value is None or dotted.split(".")[0] in free:
            continue
        current: Any = saved
        for key in dotted.split("."):
            current = current.get(key) if isinstance(current, dict) else None
        if str(current) != str(value):
            raise BadInput(
                f"--resume {run_dir}: {dotted}={value!r} conflicts with the run's "
                f"{dotted}={current!r}; drop the flag or start a new run"
            )
