"""What every spec is and how specs are read: :class:`Spec` (unknown fields refused, values
validated on assignment, paths UTF-8, older saved layouts migrated where they are loaded),
spec files read with safe, bounded loaders, flags' dotted overrides, and validation errors as
one line. The specs themselves: :mod:`dlocli.specs`.
"""

from __future__ import annotations

import json
import os
from collections.abc import Callable
from pathlib import Path
from types import UnionType
from typing import Annotated, Any, ClassVar, TypeVar, Union, get_args, get_origin

import yaml
from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    ValidationError,
    ValidationInfo,
    field_validator,
    model_validator,
)
from pydantic.fields import FieldInfo

from dlocli.errors import BadInput


def new_default(spec_cls: type[Spec], name: str, default: Any) -> Any:
    """The field ``name`` of ``spec_cls`` with another default, its bounds and description
    kept: a subclass's own value of an inherited option."""
    return FieldInfo.merge_field_infos(spec_cls.model_fields[name], default=default)


#: in a spec's ``cli_flags``: the options of every registered model (``model.FIELD``)
MODEL_OPTIONS = "model.*"


class Spec(BaseModel):
    """Base of all specs: unknown fields are refused, values validated on assignment.

    ``moved`` maps the names of fields that moved to their new dotted path, so saved runs
    written before the move still load; a spec the user gives (:data:`GIVEN`) is told the
    new path instead.
    """

    model_config = ConfigDict(extra="forbid", validate_assignment=True, allow_inf_nan=False)
    moved: ClassVar[dict[str, str]] = {}
    #: the fields the spec's command offers as flags, dotted, in --help order (every field is
    #: reachable through --spec FILE); MODEL_OPTIONS stands for every registered model's options
    cli_flags: ClassVar[tuple[str, ...]] = ()
    #: the flagged fields the run cannot do without (--help says "required")
    cli_required: ClassVar[tuple[str, ...]] = ()

    def check_resolved(self) -> None:
        """Refuse (BadInput, one line) a combination of fields that does nothing, once the
        values other parts fill in (a backend's planner defaults) are in; none by default."""

    @classmethod
    def field_of(cls, name: str) -> Any:
        """The FieldInfo of the field ``name`` (KeyError if there is none)."""
        return cls.model_fields[name]

    @classmethod
    def saved_layout(cls, data: Any) -> Any:
        """``data`` (this spec as data, from a run's spec.json or a checkpoint)
        with the layouts of older saves migrated, nested specs included. The load boundaries
        call it; validating a spec migrates no layout (:mod:`dlocli.migrations`)."""
        if not isinstance(data, dict):
            return data
        nested = {name: strip_none(info.annotation) for name, info in cls.model_fields.items()}
        return {
            key: nested[key].saved_layout(value) if _is_spec(nested.get(key)) else value
            for key, value in data.items()
        }

    @model_validator(mode="before")
    @classmethod
    def _move_fields(cls, data: Any, info: ValidationInfo) -> Any:
        if not isinstance(data, dict) or not any(old in data for old in cls.moved):
            return data
        if is_given(info):  # only saved runs keep the old layout
            old = next(old for old in cls.moved if old in data)
            raise RetiredField(old, moved_to=cls.moved[old])
        data = dict(data)
        for old, dotted in cls.moved.items():
            if old in data:
                _set_dotted(data, dotted, data.pop(old), copy=True)
        return data

    @field_validator("*", mode="before")
    @classmethod
    def _no_booleans_for_numbers(cls, value: Any, info: ValidationInfo) -> Any:
        # pydantic's lax mode reads true as 1: a spec that says `seed: true` meant something else
        if isinstance(value, bool) and _numbers_only(cls.model_fields[info.field_name].annotation):
            raise ValueError("a boolean where a number belongs; write the number")
        return value

    @field_validator("*")
    @classmethod
    def _utf8_paths(cls, value: Any) -> Any:
        # a path of undecodable bytes cannot be saved in spec.json, nor the run re-run from it
        if isinstance(value, Path):
            require_utf8_path(value)
        return value


def _is_spec(annotation: Any) -> bool:
    return isinstance(annotation, type) and issubclass(annotation, Spec)


#: the torch device a run computes on (one meaning in every spec that has one)
Device = Annotated[
    str,
    Field(description="Torch device: auto (CUDA if present, else the CPU), cpu, cuda or cuda:K."),
]


#: the name every run saves its resolved spec under
SAVED_SPEC = "spec.json"
#: the validation context of a spec the user gives (spec file and flags): retired and
#: misplaced fields are refused there, and accepted (migrated) only in saved runs
GIVEN = {"given": True}


def is_given(info: ValidationInfo) -> bool:
    """Whether the spec being validated is one the user gives (not one saved by a run)."""
    return bool(info.context and info.context.get("given"))


class RetiredField(ValueError):
    """A retired field in a given spec: where it moved (a path beside it), or why it went.
    :func:`format_validation_error` names both by their full paths."""

    def __init__(self, field: str, moved_to: str = "", why: str = "") -> None:
        super().__init__(f"'{field}' is retired")
        self.field, self.moved_to, self.why = field, moved_to, why


def _numbers_only(annotation: Any) -> bool:
    """Whether a field of ``annotation`` takes int or float values but no booleans."""
    options = get_args(annotation) if get_origin(annotation) in (Union, UnionType) else ()
    options = options or (annotation,)
    return bool not in options and any(o in (int, float) for o in options)


def require_utf8_path(path: Path) -> None:
    """Refuse a path whose name is not valid UTF-8 (bytes the shell passed undecoded)."""
    try:
        str(path).encode("utf-8")
    except UnicodeEncodeError:
        shown = os.fsencode(path).decode("utf-8", "backslashreplace")
        raise ValueError(
            f"the path {shown} is not valid UTF-8; use a name of UTF-8 characters"
        ) from None


SpecT = TypeVar("SpecT", bound=Spec)
ModelT = TypeVar("ModelT", bound=BaseModel)


#: limits of a spec file: a spec is a few hundred lines; YAML aliases can make a few hundred
#: bytes expand to gigabytes, so aliases and nodes are counted while the file is read
MAX_SPEC_BYTES = 1_000_000
MAX_YAML_NODES = 20_000
MAX_YAML_ALIASES = 20


class _BoundedLoader(yaml.SafeLoader):
    """yaml.SafeLoader that refuses documents with too many nodes or aliases."""

    def compose_node(self, parent: Any, index: Any) -> Any:
        if self.check_event(yaml.AliasEvent):
            self.aliases = getattr(self, "aliases", 0) + 1
            if self.aliases > MAX_YAML_ALIASES:
                raise yaml.YAMLError(f"more than {MAX_YAML_ALIASES} aliases")
        self.nodes = getattr(self, "nodes", 0) + 1
        if self.nodes > MAX_YAML_NODES:
            raise yaml.YAMLError(f"more than {MAX_YAML_NODES} nodes")
        return super().compose_node(parent, index)


def _load_yaml(text: str) -> Any:
    loader = _BoundedLoader(text)
    try:
        return loader.get_single_data()
    finally:
        loader.dispose()


def load_spec_file(path: Path) -> dict[str, Any]:
    """Read a YAML or JSON spec file with safe loaders; BadInput on any problem."""
    path = Path(path)
    if not path.is_file():
        raise BadInput(f"spec file {path} does not exist; pass an existing .yaml/.json file")
    if path.stat().st_size > MAX_SPEC_BYTES:
        raise BadInput(
            f"spec file {path} is {path.stat().st_size} bytes, more than a spec needs "
            f"({MAX_SPEC_BYTES}); pass the run spec file, not data"
        )
    try:
        text = path.read_text()
        data = json.loads(text) if path.suffix == ".json" else _load_yaml(text)
    except (OSError, ValueError, yaml.YAMLError, RecursionError) as exc:  # Recursion: nesting
        first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise BadInput(
            f"spec file {path} is not valid YAML/JSON ({first}); fix or remove it"
        ) from exc
    if data is None:
        data = {}
    if not isinstance(data, dict):
        raise BadInput(f"spec file {path} must hold a mapping of fields, not {type(data).__name__}")
    return data


def _set_dotted(data: dict[str, Any], dotted: str, value: Any, copy: bool = False) -> None:
    """Set ``data[a][b]... = value`` for ``dotted`` "a.b...", making the dicts on the way
    (with ``copy``: fresh copies of those there, so the caller's nested dicts stay as they were)."""
    keys = dotted.split(".")
    for key in keys[:-1]:
        node = data.get(key)
        if isinstance(node, BaseModel):  # a spec given as an instance, e.g. task=TaskSpec(...)
            node = node.model_dump()
        node = (dict(node) if copy else node) if isinstance(node, dict) else {}
        data[key] = node
        data = node
    data[keys[-1]] = value


def format_validation_error(exc: ValidationError, source: str = "spec") -> str:
    """One line naming the first bad field and what is expected."""
    err = exc.errors()[0]
    field = ".".join(str(p) for p in err["loc"]) or "(root)"
    retired = err.get("ctx", {}).get("error")
    if isinstance(retired, RetiredField):
        at = "".join(f"{p}." for p in err["loc"])
        fix = f"write it as '{at}{retired.moved_to}'" if retired.moved_to else "remove it"
        why = f" ({retired.why})" if retired.why else ""
        return f"{source}: field '{at}{retired.field}' is retired{why}; {fix}"
    if err["type"] == "extra_forbidden":
        return f"{source}: unknown field '{field}'; remove it (see --help for valid fields)"
    if not err["loc"]:  # a check across fields: its message names them; the input is the spec
        return f"{source}: {err['msg'].removeprefix('Value error, ')}"
    return f"{source}: field '{field}': {err['msg']} (got {bounded_repr(err.get('input'))})"


def flag_error(exc: ValidationError, flag: str) -> str:
    """One line blaming ``flag`` for the first bad value and saying what is expected."""
    err = exc.errors()[0]
    what = err["msg"].removeprefix("Value error, ")
    return f"{flag}: {what} (got {bounded_repr(err.get('input'))})"


def bounded_repr(value: Any) -> str:
    """repr of a value cut to a few elements and levels: an input built from YAML aliases
    can expand to gigabytes if printed whole."""
    import reprlib

    short = reprlib.Repr()
    short.maxlevel, short.maxlist, short.maxdict, short.maxstring, short.maxother = 2, 4, 4, 60, 60
    return short.repr(value)


def resolve_spec(
    cls: type[SpecT],
    spec_file: Path | None = None,
    overrides: dict[str, Any] | None = None,
    flag_name: Callable[[str], str] | None = None,
) -> SpecT:
    """Build a spec: defaults, then the spec file, then non-None overrides (dotted field paths).

    A spec the user writes is strict: a retired or misplaced field is refused. A run's own
    ``spec.json`` (``--spec RUN/spec.json`` re-runs it) is read as runs are: the layout of
    the version that saved it is migrated (:meth:`Spec.saved_layout`, its load boundary).
    With ``flag_name`` (a field's flag), a bad value an override gave is blamed on its flag."""
    saved = spec_file is not None and Path(spec_file).name == SAVED_SPEC
    data: dict[str, Any] = load_spec_file(spec_file) if spec_file is not None else {}
    if saved:
        data = cls.saved_layout(data)
    given = {dotted: value for dotted, value in (overrides or {}).items() if value is not None}
    for dotted, value in given.items():
        _set_dotted(data, dotted, value)
    try:
        return cls.model_validate(data, context=None if saved else GIVEN)
    except ValidationError as exc:
        first = exc.errors()[0]
        field = ".".join(str(part) for part in first["loc"])
        # an option the chosen model lacks is named by its field (model.depth), not its flag
        if flag_name is not None and field in given and first["type"] != "extra_forbidden":
            raise BadInput(flag_error(exc, f"--{flag_name(field)}")) from None
        raise BadInput(format_validation_error(exc, str(spec_file or "spec"))) from exc


def validated(
    cls: type[ModelT], data: Any, source: str, context: dict[str, Any] | None = None
) -> ModelT:
    """``data`` as a ``cls``; BadInput naming ``source`` and the first bad field if not one.
    ``context``: :data:`GIVEN` for a spec the user gives."""
    try:
        return cls.model_validate(data, context=context)
    except ValidationError as exc:
        raise BadInput(format_validation_error(exc, source)) from exc


def field_info(cls: type[Spec], dotted: str) -> Any:
    """The pydantic FieldInfo of a possibly nested field (``task.episode_steps``)."""
    model: Any = cls
    info = None
    for key in dotted.split("."):
        info = model.field_of(key)
        model = strip_none(info.annotation)
    return info


def strip_none(annotation: Any) -> Any:
    """``X`` of ``X | None``; other annotations as they are."""
    if get_origin(annotation) in (Union, UnionType):
        return next(a for a in get_args(annotation) if a is not type(None))
    return annotation
