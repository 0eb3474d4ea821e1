"""Command-line flags generated from the run specs: one name, one meaning, in every command.

A run spec names the fields its command offers as flags (``cli_flags``, dotted paths);
:func:`spec_flags` adds
one Typer option per field to the command's signature — its name from :data:`ALIASES` or
else the path itself (``fit.batch_size`` -> ``--fit-batch-size``), its type, and the field's
description as help — and hands the command the given values as ``overrides``, a dict
``{dotted path: value}`` (None = not given), with ``--spec``, ``--overwrite`` and ``--json``, in
a :class:`RunFlags`. Every field, flag or not, is reachable through ``--spec FILE``;
``-o KEY=VALUE`` (:func:`parse_options`) sets the free-form option dicts.
"""

from __future__ import annotations

import functools
import inspect
import typing
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Any, Literal, get_args, get_origin

import typer
import yaml

from dlocli.backends.facts import BACKEND_DEFAULT
from dlocli.cli.common import JsonFlag, OverwriteFlag, SpecFile
from dlocli.errors import BadInput
from dlocli.models.spec import ModelSpec, model_spec_classes
from dlocli.rundir import refuse_outputs_in_inputs
from dlocli.specs import MODEL_OPTIONS, Spec, field_info, resolve_spec, strip_none

MODEL = "model"  # the field of the run specs that holds the model spec

#: the flags whose name is not their field's path; one table for every command
ALIASES: dict[str, str] = {
    "backend.name": "backend",
    "task.name": "task",
    "task.goal": "goal-mode",
    "task.goal_file": "goal",
    "task.episode_steps": "steps",
    "task.control_dt": "control-dt",
    "task.shapes": "shapes",
    "model.name": "model",
    "fit.schedule": "schedule",
    "fit.epochs": "epochs",
    "fit.update_steps": "update-steps",
    "fit.lr": "lr",
    "fit.device": "device",
    "fit.mirror": "mirror",
    "mpc.horizon": "horizon",
    "mpc.settle_steps": "settle-steps",
    "mpc.motion_cost": "motion-cost",
    "mpc.servo_cost": "servo-cost",
    "mpc.roll_search": "roll-search",
    "mpc.servo_above_mm": "servo-above-mm",
    "mpc.rest_roll": "rest-roll",
    "task.envelope.max_linear_speed": "max-linear-speed",
    "task.envelope.max_angular_speed": "max-angular-speed",
    "task.envelope.max_linear_acceleration": "max-linear-acceleration",
    "task.envelope.max_angular_acceleration": "max-angular-acceleration",
    "task.envelope.stop_after_lost_s": "stop-after-lost-s",
    "task.observation.kind": "observation",
    "task.observation.markers": "markers",
    "task.observation.gripper_markers": "gripper-markers",
    "task.observation.marker_arc_lengths": "marker-arc-lengths",
    "task.observation.noise_mm": "noise-mm",
    "task.observation.latency_steps": "latency-steps",
    "task.observation.dropout": "dropout",
    "task.observation.occlusion_probability": "occlusion-probability",
    "fit.rollout_steps": "rollout-steps",
}


def flag_name(dotted: str) -> str:
    """The flag of a spec field (without the leading dashes); a model's options are named
    as they are (``model.hidden`` -> ``--hidden``)."""
    if dotted in ALIASES:
        return ALIASES[dotted]
    if dotted.startswith(MODEL + "."):
        dotted = dotted[len(MODEL) + 1 :]
    return dotted.replace(".", "-").replace("_", "-")


def model_flags() -> list[str]:
    """The fields of every registered model's spec (``model.FIELD``), for the commands that
    build a model: the common ones first, then each model's own."""
    fields = {name: None for cls in model_spec_classes().values() for name in cls.model_fields}
    return [f"{MODEL}.{name}" for name in fields]


def _model_help(dotted: str, info: Any) -> str:
    """Help of a model option: which models have it, and their defaults."""
    field = dotted.split(".")[-1]
    owners = {n: c for n, c in model_spec_classes().items() if field in c.model_fields}
    if field == "name":
        return f"{info.description} One of: {', '.join(owners)}."
    defaults = {n: c.model_fields[field].default for n, c in owners.items()}
    if len(set(map(repr, defaults.values()))) == 1:
        default = f"[default: {next(iter(defaults.values()))}]"
    else:
        default = "[default: " + ", ".join(f"{n} {d}" for n, d in defaults.items()) + "]"
    shared = field in ModelSpec.model_fields
    return f"{'' if shared else ', '.join(owners) + ': '}{info.description}  {default}"


#: the metavar of each plain flag type (Click's words, not Python's types)
METAVARS: dict[Any, str] = {int: "INTEGER", float: "FLOAT", bool: "", str: "TEXT", Path: "PATH"}


def _flag_type(annotation: Any) -> tuple[Any, str, str]:
    """(the Python type Typer parses, its metavar, a note for --help) of a field's annotation."""
    annotation = strip_none(annotation)
    if get_origin(annotation) is Literal:
        return str, "|".join(str(a) for a in get_args(annotation)), ""
    if annotation == list[Path]:
        return list[Path], "PATH", ""  # a repeatable flag (its description says so)
    if get_origin(annotation) in (list, tuple):
        return str, "A,B,...", " Comma-separated."
    if annotation in METAVARS:
        return annotation, METAVARS[annotation], ""
    raise TypeError(f"no flag type for {annotation!r}; offer the field through --spec only")


def shown_default(info: Any, flag: str, required: bool) -> str:
    """What --help says after a field's description, in Click's own format: ``[required]``
    for an input the run cannot do without, else ``[default: VALUE]`` (a factory's value
    too; a bool as its flag); nothing for an optional input that is absent by default."""
    if required:
        return "  [required]"
    value = info.default_factory() if info.default_factory is not None else info.default
    if value is None or (isinstance(value, (list, tuple)) and not value):
        return ""
    if isinstance(value, bool):
        value = flag if value else f"no-{flag}"
    elif isinstance(value, (list, tuple)):
        value = ",".join(str(v) for v in value)
    elif isinstance(value, Spec):  # a nested spec: its fields are flags of their own
        return ""
    if info.json_schema_extra == BACKEND_DEFAULT:
        return f"  [default: {value}, or the backend's planner default]"
    return f"  [default: {value}]"


def _option(spec_cls: type[Spec], dotted: str, required: bool = False) -> tuple[str, Any]:
    """(parameter name, Annotated type) of the flag of ``dotted``."""
    name, info = flag_name(dotted), field_info(spec_cls, dotted)
    kind, metavar, note = _flag_type(info.annotation)
    if dotted.startswith(MODEL + "."):
        text = _model_help(dotted, info)
    else:
        text = f"{info.description}{note}{shown_default(info, name, required)}"
    if kind is bool:
        option = typer.Option(f"--{name}/--no-{name}", help=text)
    else:
        option = typer.Option(f"--{name}", help=text, metavar=metavar)
    return name.replace("-", "_"), Annotated[kind | None, option]


def _value(spec_cls: type[Spec], dotted: str, value: Any) -> Any:
    """A flag's value as the field takes it (a comma-separated list split)."""
    annotation = strip_none(field_info(spec_cls, dotted).annotation)
    if isinstance(value, list):  # a repeated flag
        return value or None
    if value is not None and get_origin(annotation) in (list, tuple):
        return [part.strip() for part in str(value).split(",") if part.strip()]
    return value


@dataclass
class RunFlags:
    """What every run command is given: the flags' field values, ``--spec``, ``--overwrite``
    and ``--json``."""

    spec_cls: type[Spec]
    overrides: dict[str, Any]
    spec_file: Path | None
    overwrite: bool
    json: bool

    def spec(self) -> Any:
        """The run's spec: defaults, then the spec file, then the flags given; BadInput if
        it would write into a run it reads."""
        spec = resolve_spec(self.spec_cls, self.spec_file, self.overrides, flag_name)
        refuse_outputs_in_inputs(spec)
        return spec

    def refuse_with_resume(self, resume: Path | None) -> None:
        """BadInput if flags that only make sense for a new run come with ``--resume``."""
        if resume is None:
            return
        if self.spec_file is not None:
            raise BadInput(
                f"--spec with --resume {resume}: a resumed run follows its own spec.json; "
                "drop --spec"
            )
        if self.overwrite:
            raise BadInput(f"--overwrite with --resume {resume}: they contradict; drop one")


COMMON: dict[str, Any] = {"spec_file": SpecFile, "overwrite": OverwriteFlag, "json_out": JsonFlag}
COMMON_DEFAULTS = {"spec_file": None, "overwrite": False, "json_out": False}


def spec_flags(spec_cls: type[Spec]) -> Callable[[Callable], Callable]:
    """Decorate a command ``fn(run: RunFlags, **own_flags)``: add a flag per field of the
    spec's ``cli_flags``, and ``--spec``, ``--overwrite`` and ``--json``. The fields in its
    ``cli_required`` are inputs the run refuses to go without (from the flag or the spec
    file): --help says so."""
    fields = [
        expanded
        for dotted in spec_cls.cli_flags
        for expanded in (model_flags() if dotted == MODEL_OPTIONS else [dotted])
    ]
    required = spec_cls.cli_required

    def decorate(fn: Callable) -> Callable:
        generated = dict(_option(spec_cls, dotted, dotted in required) for dotted in fields)
        if len(generated) < len(fields):
            raise TypeError(f"{fn.__name__}: two of the fields {fields} have one flag name")
        params = {name: dotted for name, dotted in zip(generated, fields, strict=True)}
        hints = typing.get_type_hints(fn, include_extras=True)  # resolved in fn's module
        own = [
            p.replace(kind=inspect.Parameter.KEYWORD_ONLY, annotation=hints[p.name])
            for p in inspect.signature(fn).parameters.values()
            if p.name != "run"
        ]
        clash = set(generated) & {p.name for p in own}
        if clash:
            raise TypeError(f"{fn.__name__}: flags {sorted(clash)} are also its own parameters")

        @functools.wraps(fn)
        def command(**kwargs: Any) -> Any:
            overrides = {
                dotted: _value(spec_cls, dotted, kwargs.pop(name))
                for name, dotted in params.items()
            }
            common = [kwargs.pop(name) for name in COMMON]
            return fn(RunFlags(spec_cls, overrides, *common), **kwargs)

        keyword = inspect.Parameter.KEYWORD_ONLY
        options = [
            inspect.Parameter(name, keyword, default=None, annotation=kind)
            for name, kind in generated.items()
        ]
        common = [
            inspect.Parameter(name, keyword, default=COMMON_DEFAULTS[name], annotation=kind)
            for name, kind in COMMON.items()
        ]
        signature = inspect.Signature([*options, *own, *common])
        command.__signature__ = signature  # type: ignore[attr-defined]
        command.__annotations__ = {**generated, **{p.name: p.annotation for p in own}, **COMMON}
        del command.__wrapped__  # Typer must read the generated signature, not fn's
        command.spec_cls = spec_cls  # type: ignore[attr-defined]
        command.spec_fields = {flag_name(d): d for d in fields}  # type: ignore[attr-defined]
        return command

    return decorate


def parse_options(pairs: list[str], prefix: str) -> dict[str, Any]:
    """``["iterations=50", "warm_start=false"]`` -> ``{prefix.iterations: 50, ...}``."""
    parsed: dict[str, Any] = {}
    for pair in pairs:
        key, sep, text = pair.partition("=")
        if not sep or not key.strip():
            raise BadInput(f"--option {pair!r} must look like KEY=VALUE, e.g. -o iterations=50")
        try:
            value = yaml.safe_load(text)
        except yaml.YAMLError:
            value = text
        parsed[f"{prefix}.{key.strip()}"] = value
    return parsed
