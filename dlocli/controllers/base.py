"""The controller contract shared by MPC, sampling MPC, RL agents and PILCO.

A controller is built for one environment (its task fixes the action size), is reset with a
goal shape (N,3) in metres, and maps the env's flat observation to an action in [-1, 1]^A.
``last_latency_ms`` is the wall time of the latest :meth:`act`, for live displays and the
latency statistics of ``dlo control``; ``last_stats`` holds the controller's own numbers about
that step (e.g. a planner's iterations and model time), empty if it has none.

Build one by registry name with :func:`make_controller`: a class declares what it needs
besides the env in ``needs`` (e.g. ``("model",)`` for planners through a learned model) and
its options as a pydantic ``spec_cls``. A reference (doing nothing, random actions) says so
in ``reference``: every bench and online run shows its results beside the learners'.
"""

from __future__ import annotations

import time
from abc import ABC, abstractmethod
from dataclasses import dataclass
from pathlib import Path
from typing import Any, ClassVar, TypeVar

import numpy as np
from pydantic import ValidationError

from dlocli.errors import BadInput
from dlocli.registry import backends, controllers
from dlocli.specs import Spec, format_validation_error

SpecT = TypeVar("SpecT", bound=Spec)


@dataclass(frozen=True)
class Reference:
    """How results and plots show a reference controller."""

    #: what it does, in words ("doing nothing")
    label: str
    #: its place among the references in tables and legends (0 first)
    rank: int
    #: its matplotlib line format in learning curves (a thin line, no band)
    line: str
    #: its matplotlib colour
    colour: str


class Controller(ABC):
    """Observation in, action out. Subclasses implement :meth:`_act`."""

    name: str = ""
    #: what the constructor needs besides the env, as keyword arguments (e.g. "model")
    needs: ClassVar[tuple[str, ...]] = ()
    #: the options of this controller (passed as ``spec=``); None if it has none
    spec_cls: ClassVar[type[Spec] | None] = None
    #: set on the references every result is read against (they learn nothing)
    reference: ClassVar[Reference | None] = None

    def __init__(self, env: Any) -> None:
        self.env = env
        self.task = env.task
        self.action_dim = int(env.action_space.shape[0])
        self.goal: np.ndarray | None = None
        self.last_latency_ms = 0.0
        self.last_stats: dict[str, float] = {}

    @classmethod
    def warm_up(cls) -> None:
        """Import what building and acting need where that is slow, before a robot cell is
        claimed: a session idle while a library loads may end under the controller."""
        return None  # most controllers import nothing slow

    def reset(self, goal: np.ndarray) -> None:
        """Start a new episode towards ``goal`` (N,3) metres."""
        self.goal = np.asarray(goal, dtype=np.float64)

    def act(self, obs: np.ndarray) -> np.ndarray:
        """Action in [-1, 1]^A for the flat observation ``obs``; times itself."""
        start = time.perf_counter()
        action = np.clip(np.asarray(self._act(obs), dtype=np.float32), -1.0, 1.0)
        self.last_latency_ms = 1000.0 * (time.perf_counter() - start)
        return action

    @abstractmethod
    def _act(self, obs: np.ndarray) -> np.ndarray: ...


class RandomController(Controller):
    """Uniform random actions (a floor every method must beat)."""

    name = "random"
    # dotted with crosses: it often coincides with doing nothing, and stays visible on it
    reference = Reference("random actions", rank=1, line=":x", colour="0.45")

    def __init__(self, env: Any, seed: int = 0, **_: Any) -> None:
        super().__init__(env)
        self.rng = np.random.default_rng(seed)

    def _act(self, obs: np.ndarray) -> np.ndarray:
        return self.rng.uniform(-1.0, 1.0, self.action_dim)


class ZeroController(Controller):
    """All-zero actions: do nothing, the reference every result is scored against."""

    name = "zero"
    reference = Reference("doing nothing", rank=0, line="--", colour="black")

    def __init__(self, env: Any, seed: int = 0, **_: Any) -> None:
        super().__init__(env)

    def _act(self, obs: np.ndarray) -> np.ndarray:
        return np.zeros(self.action_dim)


class Planner(Controller):
    """A controller that plans through a learned dynamics model (gradient MPC, MPPI, ...):
    the online loop explores with one, and the bench's model-based agents act with it,
    chosen by name (a run spec's ``planner``)."""

    needs: ClassVar[tuple[str, ...]] = ("model",)


def references() -> dict[str, Reference]:
    """The registered references by name, in their rank order."""
    found = {name: controllers.facts(name).reference for name in controllers.names()}
    ranked = sorted((ref.rank, name) for name, ref in found.items() if ref is not None)
    return {name: found[name] for _, name in ranked}


def is_planner(name: str) -> bool:
    """Whether the registered controller ``name`` plans through a learned model."""
    return issubclass(controllers.facts(name), Planner)


class LearningAgent(Controller):
    """A controller that learns from its own interaction with ``env`` (benchmark agents).

    ``learn(n)`` interacts with the training env for exactly ``n`` more transitions (env
    steps) and updates the agent; ``transitions`` counts all transitions used so far. The
    benchmark alternates ``learn`` with evaluation episodes on a separate env (evaluation
    transitions are not counted), so every agent gets the same transition budget.
    """

    def __init__(self, env: Any, seed: int = 0) -> None:
        super().__init__(env)
        self.seed = seed
        self.transitions = 0

    @abstractmethod
    def learn(self, transitions: int) -> None:
        """Use ``transitions`` more env steps of ``self.env`` to improve the agent."""

    def log_to(self, directory: Path) -> None:  # noqa: B027 (optional hook)
        """Write the learner's own TensorBoard curves into ``directory`` (if it has any)."""

    def save_policy(self, directory: Path) -> bool:
        """Write what :meth:`load_policy` needs to act as now into ``directory``; False if
        this agent cannot (the default)."""
        return False

    def load_policy(self, directory: Path) -> None:
        """Act with the policy :meth:`save_policy` wrote (BadInput if this agent cannot)."""
        raise BadInput(
            f"controller '{self.name}' cannot load a saved policy; it runs inside `dlo bench` only"
        )

    def save_state(self, slot: Path, shared: Path) -> bool:
        """Write everything needed to continue learning exactly as if never stopped into
        ``slot`` (growing parts into ``shared``, see :mod:`dlocli.bench.checkpoint`), between
        episodes; False if this agent cannot (the default) or is inside an episode."""
        return False

    def load_state(self, slot: Path, shared: Path) -> None:
        """Continue from :meth:`save_state`'s files, on an agent built like the saved one."""
        raise NotImplementedError(f"controller '{self.name}' cannot resume learning")


def controller_spec(
    name: str, options: dict[str, Any] | None = None, backend: str | None = None
) -> Spec | None:
    """Validate ``options`` against the registered controller's spec class (BadInput if wrong);
    the options it leaves unset that ``backend`` has defaults for take them."""
    spec_cls = controllers.spec_cls(name)
    if spec_cls is None:
        if options:
            raise BadInput(f"controller '{name}' takes no options; remove {sorted(options)}")
        return None
    try:
        spec = spec_cls.model_validate(options or {})
    except ValidationError as exc:
        raise BadInput(format_validation_error(exc, f"controller '{name}' options")) from exc
    return spec if backend is None else with_backend_defaults(spec, name, backend)


def with_backend_defaults(options: Spec, planner: str, backend: str) -> Spec:
    """``options`` of ``planner`` with each field it leaves unset that ``backend`` has a
    default for (:attr:`~dlocli.backends.facts.BackendFacts.planner_defaults`) set to that
    default; the fields a run sets are kept, and a resolved spec saves them all."""
    if backend not in backends:  # the run refuses it by name, with the valid ones
        return options
    defaults = backends.facts(backend).planner_defaults.get(planner, {})
    unset = {
        name: value
        for name, value in defaults.items()
        if name in type(options).model_fields and name not in options.model_fields_set
    }
    resolved = options.model_copy(update=unset) if unset else options
    resolved.check_resolved()
    return resolved


def make_controller(
    name: str,
    env: Any,
    *,
    options: dict[str, Any] | Spec | None = None,
    seed: int = 0,
    **provided: Any,
) -> Controller:
    """Build the registered controller ``name`` for ``env``.

    ``options`` are its spec's fields (dict or spec instance; a dict or None leaves the fields
    it does not name to ``env``'s backend's planner defaults, a spec instance is taken whole);
    ``provided`` holds what controllers may need (``model=``); only the names in the class's
    ``needs`` are passed on.
    """
    cls = controllers.get(name)
    missing = [need for need in cls.needs if provided.get(need) is None]
    if missing:
        needed = " and a ".join(missing)
        raise BadInput(f"controller '{name}' needs a {needed}; pass --{missing[0]}")
    kwargs: dict[str, Any] = {need: provided[need] for need in cls.needs}
    backend = getattr(getattr(env, "backend_spec", None), "name", None)
    if isinstance(options, Spec):
        options, backend = options.model_dump(), None
    if cls.spec_cls is not None:
        kwargs["spec"] = controller_spec(name, options, backend)
    return cls(env, seed=seed, **kwargs)


def resolve_agent_spec(cls: type[SpecT], spec: Spec | None, fields: dict[str, Any]) -> SpecT:
    """The agent's spec from a spec instance and/or keyword fields (fields override)."""
    data = spec.model_dump() if spec is not None else {}
    try:
        return cls.model_validate({**data, **fields})
    except ValidationError as exc:
        raise BadInput(format_validation_error(exc, f"{cls.__name__} options")) from exc
