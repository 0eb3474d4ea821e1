"""One registry mechanism for every plugin kind (backends, models, controllers).

Entries are lazy ``"module:attr"`` strings, so an optional dependency costs nothing until the
entry is used. Third-party packages can add entries through the entry-point groups
``dlocli.backends``, ``dlocli.models`` and ``dlocli.controllers``.
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


class Registry:
    """Maps names to lazily imported factories of one plugin kind."""

    def __init__(self, kind: str) -> None:
        self.kind = kind
        self._targets: dict[str, str | Callable[..., Any]] = {}
        self._summaries: dict[str, str] = {}
        self._specs: dict[str, str | type] = {}
        self._loaded_entry_points = False

    def register(
        self,
        name: str,
        target: str | Callable[..., Any],
        summary: str = "",
        spec: str | type | None = None,
    ) -> None:
        """Register ``target`` (a ``"module:attr"`` string or a callable) under ``name``;
        ``spec`` names its options' spec class where importing ``target`` for its
        ``spec_cls`` would cost (--help imports no torch)."""
        self._targets[name] = target
        self._summaries[name] = summary
        if spec is not None:
            self._specs[name] = spec

    def decorator(self, name: str, summary: str = "") -> Callable[[Any], Any]:
        """``@registry.decorator("name")`` registers a class or function where it is defined."""

        def wrap(obj: Any) -> Any:
            self.register(name, obj, summary or (obj.__doc__ or "").strip().split("\n")[0])
            return obj

        return wrap

    def names(self) -> list[str]:
        self._load_entry_points()
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
        target = self._targets[name]
        if isinstance(target, str):
            target = import_target(target)
            self._targets[name] = target
        return target

    def spec_cls(self, name: str) -> Any:
        """The spec class of ``name``'s options: the one registered with it, else the entry's
        own ``spec_cls`` attribute (None if it has none)."""
        self.check(name)
        spec = self._specs.get(name)
        if isinstance(spec, str):
            spec = self._specs[name] = import_target(spec)
        return spec if spec is not None else getattr(self.get(name), "spec_cls", None)

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

    def _load_entry_points(self) -> None:
        if self._loaded_entry_points:
            return
        self._loaded_entry_points = True
        for ep in entry_points(group=f"dlocli.{self.kind}s"):
            self._targets.setdefault(ep.name, ep.value)


backends = Registry("backend")
models = Registry("model")
controllers = Registry("controller")
tasks = Registry("task")

backends.register(
    "mujoco",
    "dlocli.backends.mujoco_cable:MujocoCable",
    "MuJoCo 3.x composite cable (elasticity plugin), grippers as mocap bodies",
)
backends.register(
    "mujoco-flex",
    "dlocli.backends.mujoco_flex:MujocoFlex",
    "MuJoCo 4 flex rod (1D flex, discrete elastic rod with twist), grippers as welded pads",
)
backends.register(
    "pybullet",
    "dlocli.backends.pybullet_chain:PybulletChain",
    "PyBullet chain of capsules, joint stiffness from EI/l and GJ/l",
)
tasks.register("single", "dlocli.env.tasks:SingleGripperTask", "6-D action: right gripper moves")
tasks.register("bimanual", "dlocli.env.tasks:BimanualTask", "12-D action: both grippers move")
models.register(
    "in-bilstm",
    "dlocli.models.in_bilstm:INBiLSTM",
    "Interaction Network + bi-LSTM along the rod (the paper's model)",
    spec="dlocli.models.spec:INBiLSTMSpec",
)
models.register(
    "mlp",
    "dlocli.models.mlp:MLPDynamics",
    "flattened state + action MLP baseline",
    spec="dlocli.models.spec:MLPSpec",
)
controllers.register(
    "mpc",
    "dlocli.controllers.mpc:GradientMPC",
    "gradient-based shooting MPC through the learned model (paper eqs. 8-10)",
    spec="dlocli.controllers.specs:MPCSpec",
)
controllers.register(
    "mppi",
    "dlocli.controllers.mppi:MPPI",
    "sampling MPC (MPPI) through the learned model",
    spec="dlocli.controllers.specs:MPPISpec",
)
controllers.register("random", "dlocli.controllers.base:RandomController", "uniform random actions")
controllers.register(
    "zero", "dlocli.controllers.base:ZeroController", "all-zero actions: do nothing (reference)"
)
controllers.register(
    "sac",
    "dlocli.controllers.sb3_agents:SACAgent",
    "Soft Actor-Critic (stable-baselines3) on the flat observation",
)
controllers.register(
    "td3",
    "dlocli.controllers.sb3_agents:TD3Agent",
    "TD3 (stable-baselines3) with Gaussian exploration noise",
)
controllers.register(
    "pilco",
    "dlocli.controllers.pilco:PilcoAgent",
    "PILCO: GP dynamics, moment matching, RBF policy (Deisenroth 2011)",
    spec="dlocli.controllers.specs:PilcoSpec",
)
