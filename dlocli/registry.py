"""One registry mechanism for every plugin kind (backends, models, controllers, tasks,
observers, cell clients).

Entries are lazy ``"module:attr"`` strings, so an optional dependency costs nothing until the
entry is used. Each kind's built-ins register themselves in their own package (its
``home``, imported on the registry's first use); third-party packages add entries through
the entry-point groups ``dlocli.backends``, ``dlocli.models`` and ``dlocli.controllers``.

An entry may name two light stand-ins that answer questions without importing it (``--help``
imports no torch or simulator): ``spec``, the class of its options, and ``facts``, a base
class of the entry whose class attributes are facts about it (a backend's segment limit, a
controller being a reference or a planner). Without them the entry itself answers.
"""

from __future__ import annotations

import difflib
import importlib
from collections.abc import Callable, Iterator
from importlib.metadata import entry_points
from typing import Any

from dlocli.errors import UnknownName


def import_target(target: str) -> Any:
    """The object a ``"module:attr"`` string names, its module imported."""
    module_name, _, attr = target.partition(":")
    return getattr(importlib.import_module(module_name), attr)


def _resolved(table: dict[str, Any], name: str) -> Any:
    """``table[name]``, a ``"module:attr"`` string imported once and kept."""
    value = table[name]
    if isinstance(value, str):
        value = table[name] = import_target(value)
    return value


class Registry:
    """Maps names to lazily imported factories of one plugin kind."""

    def __init__(self, kind: str, home: str) -> None:
        """``home``: the module whose import registers the built-ins of this kind."""
        self.kind = kind
        self.home = home
        self._targets: dict[str, str | Callable[..., Any]] = {}
        self._summaries: dict[str, str] = {}
        self._specs: dict[str, str | type] = {}
        self._facts: dict[str, str | type] = {}
        self._loaded = False

    def register(
        self,
        name: str,
        target: str | Callable[..., Any],
        summary: str = "",
        spec: str | type | None = None,
        facts: str | type | None = None,
    ) -> None:
        """Register ``target`` (a ``"module:attr"`` string or a callable) under ``name``;
        ``spec`` and ``facts`` name its light stand-ins (see the module's docstring)."""
        self._targets[name] = target
        self._summaries[name] = summary
        if spec is not None:
            self._specs[name] = spec
        if facts is not None:
            self._facts[name] = facts

    def unregister(self, name: str) -> None:
        """Remove ``name`` and its stand-ins (:class:`UnknownName` if it is not registered)."""
        self.check(name)
        for table in (self._targets, self._summaries, self._specs, self._facts):
            table.pop(name, None)

    def decorator(self, name: str, summary: str = "") -> Callable[[Any], Any]:
        """``@registry.decorator("name")`` registers a class or function where it is defined."""

        def wrap(obj: Any) -> Any:
            self.register(name, obj, summary or (obj.__doc__ or "").strip().split("\n")[0])
            return obj

        return wrap

    def names(self) -> list[str]:
        self._load()
        return sorted(self._targets)

    def summary(self, name: str) -> str:
        return self._summaries.get(name, "")

    def __contains__(self, name: object) -> bool:
        return name in self.names()

    def __iter__(self) -> Iterator[str]:
        return iter(self.names())

    def get(self, name: str) -> Any:
        """Return the factory registered under ``name``, importing it on first use."""
        self.check(name)
        return _resolved(self._targets, name)

    def spec_cls(self, name: str) -> Any:
        """The spec class of ``name``'s options: the one registered with it, else the entry's
        own ``spec_cls`` attribute (None if it has none)."""
        self.check(name)
        if name in self._specs:
            return _resolved(self._specs, name)
        return getattr(self.get(name), "spec_cls", None)

    def facts(self, name: str) -> Any:
        """The class whose attributes are ``name``'s facts: its registered light base class,
        else the entry itself."""
        self.check(name)
        return _resolved(self._facts, name) if name in self._facts else self.get(name)

    def check(self, name: str) -> None:
        """Raise :class:`UnknownName` listing the valid names if ``name`` is not registered."""
        names = self.names()
        if name in names:
            return
        close = difflib.get_close_matches(name, names, n=1)
        hint = f" Did you mean '{close[0]}'?" if close else ""
        raise UnknownName(
            f"unknown {self.kind} '{name}'; valid {self.kind}s: {', '.join(names)}.{hint}"
        )

    def _load(self) -> None:
        """The built-ins (their home registers them on import), then the entry points;
        a plugin does not replace a built-in of the same name."""
        if self._loaded:
            return
        self._loaded = True  # first: the home's import registers through this registry
        importlib.import_module(self.home)
        for ep in entry_points(group=f"dlocli.{self.kind}s"):
            self._targets.setdefault(ep.name, ep.value)


backends = Registry("backend", home="dlocli.backends")
models = Registry("model", home="dlocli.models")
controllers = Registry("controller", home="dlocli.controllers")
tasks = Registry("task", home="dlocli.env.tasks")
#: what turns a sensor's frames into the observation's markers, by observation kind (the env
#: asks for its kind's observer here and never imports the tracker)
observers = Registry("observer", home="dlocli.tracking")
#: the clients of a cell, by protocol: a backend reached by an address rather than picked by
#: name (the backends ask for the dlocli-cell protocol's client here and never import the bridge)
cells = Registry("cell", home="dlocli.bridge")
