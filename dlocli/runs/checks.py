"""The checks every run makes before it starts or resumes, in one place."""

from __future__ import annotations

from typing import Any

from dlocli.registry import backends, models, tasks


def check_registered(spec: Any) -> None:
    """UnknownName, listing the valid names, if ``spec`` names a backend, task or model that
    is not registered (a spec without a model is checked for the others)."""
    backends.check(spec.backend.name)
    tasks.check(spec.task.name)
    model = getattr(spec, "model", None)
    if model is not None:
        models.check(model.name)
