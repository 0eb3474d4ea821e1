"""The env's keyword arguments: validated into specs, an unknown one refused as Python does."""

from __future__ import annotations

import difflib
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
from pydantic import ValidationError

from dlocli.errors import BadOption, UnknownOption
from dlocli.registry import backends as backend_registry
from dlocli.registry import tasks as task_registry
from dlocli.specs import BackendSpec, TaskSpec, format_validation_error

#: keyword arguments of DLOShapeEnv (and gym.make) besides the TaskSpec fields
ENV_KEYWORDS = ("backend", "task", "goal", "seed", "render_mode")


def env_keywords() -> list[str]:
    """Every keyword DLOShapeEnv, ``make_env`` and ``gym.make`` of a dlocli id accept."""
    return [*ENV_KEYWORDS, *(f for f in TaskSpec.model_fields if f not in ("name", "goal"))]


def resolve_env_options(
    backend: BackendSpec | str | None,
    task: TaskSpec | str,
    goal: np.ndarray | Path | str | None,
    task_options: dict[str, Any],
) -> tuple[BackendSpec, TaskSpec, np.ndarray | Path | str | None]:
    """Validated specs from the env's keyword arguments: ``task_options`` set TaskSpec fields,
    ``goal`` "fixed" or "random" sets the goal mode. UnknownOption, BadOption, UnknownName."""
    valid = env_keywords()
    for key in task_options:
        if key not in valid:
            # Python's own wording: wrappers such as TorchRL's GymEnv retry without a keyword
            # (frameskip) only when the TypeError says "unexpected keyword argument"
            hint = _did_you_mean(key, valid)
            raise UnknownOption(
                f"DLOShapeEnv() got an unexpected keyword argument '{key}'{hint}; "
                f"valid ones: {', '.join(valid)}"
            )
    modes = ("fixed", "random")
    if isinstance(goal, str) and goal in modes:
        task_options, goal = {**task_options, "goal": goal}, None
    elif isinstance(goal, str) and not goal.endswith(".npy"):
        raise BadOption(
            f"DLOShapeEnv: goal={goal!r} is neither a goal mode ('fixed' or 'random') nor a "
            f".npy file{_did_you_mean(goal, modes)}; pass a mode, an (N, 3) array or a .npy path"
        )
    try:  # validated as a whole: a bad value is refused, not silently dropped
        if backend is None:  # the MuJoCo rod of the installed MuJoCo
            backend_spec = BackendSpec()
        else:
            backend_spec = BackendSpec(name=backend) if isinstance(backend, str) else backend
        backend_spec = BackendSpec.model_validate(backend_spec)
        task_spec = TaskSpec(name=task) if isinstance(task, str) else task
        task_spec = TaskSpec.model_validate(
            {**TaskSpec.model_validate(task_spec).model_dump(), **task_options}
            if task_options
            else task_spec
        )
    except ValidationError as exc:
        raise BadOption(format_validation_error(exc, "DLOShapeEnv")) from exc
    backend_registry.check(backend_spec.name)
    task_registry.check(task_spec.name)
    return backend_spec, task_spec, goal


def _did_you_mean(name: str, valid: Sequence[str]) -> str:
    close = difflib.get_close_matches(name, valid, n=1)
    return f" (did you mean '{close[0]}'?)" if close else ""
