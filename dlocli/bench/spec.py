"""The bench's spec and schedule: what every job of a ``dlo bench`` run learns and when it
is evaluated, and the fingerprint that says whether a saved job still holds."""

from __future__ import annotations

import hashlib
import json
from pathlib import Path
from typing import Annotated, Any, ClassVar

from pydantic import Field, TypeAdapter, model_validator

from dlocli.controllers.base import LearningAgent, controller_spec
from dlocli.controllers.specs import (
    PlannerName,
    PlannerOptions,
    planner_name_field,
    planner_options_field,
)
from dlocli.executors import ExecutorChoice
from dlocli.limits import (
    MAX_CLUSTER_WORKERS,
    MAX_COUNT,
    MAX_PROCESSES,
    MAX_SEEDS,
    MAX_TRANSITIONS,
)
from dlocli.migrations import (
    fit_fingerprint_form,
    model_fingerprint_form,
    without_legacy_values,
)
from dlocli.models.spec import ModelField, UpdateSpec, model_field
from dlocli.registry import controllers
from dlocli.specs import MODEL_OPTIONS, EnvSpec

#: compact JSON, the bytes fingerprints have always hashed
_JSON = TypeAdapter(Any)

#: fields that may change between runs of one directory: they do not change any result
#: (``budgets`` enters the fingerprint of each job through that agent's own budget)
FREE_FIELDS = {"agents", "seeds", "executor", "workers", "ray_address", "out", "budgets"}


class BenchSpec(EnvSpec, ExecutorChoice):
    """`dlo bench`: every agent x seed learns under the same transition budget."""

    cli_flags: ClassVar[tuple[str, ...]] = (
        "agents", "budget", "seeds", "task.goal", "task.name", "task.shapes", "backend.name",
        "task.episode_steps", "evals", "eval_trials", MODEL_OPTIONS, "fit.epochs", "planner",
        "transfer", "executor", "ray_address", "workers", "threads", "seed", "out",
    )  # fmt: skip

    agents: list[str] = Field(
        default_factory=lambda: ["zero", "random", "held-end", "sac", "td3", "pilco", "mpc"],
        description="Agents to compare: zero, random, held-end, sac, td3, pilco, mpc, "
        "mpc-offline (zero, random and held-end, the no-model servo to where the goal holds "
        "the rod's ends, are the references every result is read against).",
    )
    budget: int = Field(
        5000, gt=0, le=MAX_TRANSITIONS, description="Env transitions each agent may learn from."
    )
    budgets: dict[str, Annotated[int, Field(gt=0, le=MAX_TRANSITIONS)]] = Field(
        default_factory=dict,
        description="Per-agent budgets overriding `budget`, e.g. {sac: 50000, td3: 50000}; "
        "evaluation points stay `budget / evals` apart, so curves share their x values.",
    )
    seeds: int = Field(3, gt=0, le=MAX_SEEDS, description="Seeds per agent: seed, seed+1, ...")
    evals: int = Field(
        10,
        gt=0,
        le=MAX_COUNT,
        description="Evaluation points, at regular transition counts (whole episodes).",
    )
    eval_trials: int = Field(
        5, gt=0, le=MAX_COUNT, description="Noise-free episodes per evaluation point."
    )
    options: dict[str, dict[str, Any]] = Field(
        default_factory=dict,
        description="Options of the learning agents by name, e.g. {sac: {net_arch: [64, 64]}}.",
    )
    model: ModelField = model_field("Dynamics model of mpc.")
    fit: UpdateSpec = Field(
        default_factory=UpdateSpec, description="mpc's model update per iteration."
    )
    planner: PlannerName = planner_name_field()
    mpc: PlannerOptions = planner_options_field("Options of the planner of mpc and mpc-offline.")
    noise_probability: float = Field(
        0.2, ge=0, le=1, description="Probability that an mpc training step gets action noise."
    )
    noise_std: float = Field(0.3, ge=0, description="Std of mpc's training action noise.")
    transfer: bool = Field(
        True,
        description="Also evaluate final agents on random goals (after a fixed goal) and "
        "model-based ones on the bimanual task (after the single one).",
    )
    workers: int | None = Field(
        None,
        gt=0,
        le=MAX_CLUSTER_WORKERS,
        description="Parallel jobs (local processes or Ray CPUs; at most this machine's CPUs, "
        "or with --ray-address the cluster's); None = CPU count.",
    )
    threads: int = Field(1, gt=0, le=MAX_PROCESSES, description="Torch threads per job.")
    out: Path = Field(Path("runs/bench"), description="Run directory.")

    @model_validator(mode="before")
    @classmethod
    def _same_information(cls, data: Any) -> Any:
        """The RL observation holds the segment velocities exactly when the model reads them,
        unless a spec says otherwise (which check_spec then refuses)."""
        model = data.get("model") if isinstance(data, dict) else None
        if isinstance(model, dict) and "velocity_input" in model:
            task = dict(data.get("task") or {})
            task.setdefault("observe_velocity", model["velocity_input"])
            data = {**data, "task": task}
        return data


# ----------------------------------------------------------------------------- schedule
def eval_interval(spec: BenchSpec) -> int:
    """Transitions between evaluations: budget / evals, rounded down to whole episodes."""
    steps = spec.task.episode_steps
    return max(1, spec.budget // steps // spec.evals) * steps


def budget_of(spec: BenchSpec, agent: str) -> int:
    """The transitions ``agent`` may learn from."""
    return spec.budgets.get(agent, spec.budget)


def eval_points(spec: BenchSpec, agent: str | None = None) -> list[int]:
    """Transition counts of the evaluations of ``agent``: every interval, and its budget last."""
    budget = spec.budget if agent is None else budget_of(spec, agent)
    points = list(range(eval_interval(spec), budget + 1, eval_interval(spec)))
    return points if points and points[-1] == budget else [*points, budget]


def fingerprint(spec: BenchSpec, agent: str | None = None) -> str:
    """Hash of the fields that determine a job's result; with ``agent``, of that agent's job:
    its own budget and its own options, resolved (so a new default reruns its jobs only)."""
    text = _JSON.dump_json(fingerprint_data(spec, with_options=agent is None)).decode()
    if agent is not None:
        if agent in option_agents():
            options = fingerprinted_options(spec, agent)
            text += f"|options={json.dumps(options, sort_keys=True)}"
        if budget_of(spec, agent) != spec.budget:
            text += f"|budget={budget_of(spec, agent)}"
    return hashlib.sha256(text.encode()).hexdigest()[:12]


def fingerprint_data(spec: BenchSpec, with_options: bool = True) -> dict[str, Any]:
    """The fields a fingerprint hashes, in the layout fingerprints were first computed in:
    fields at the value they had before they existed are left out (:mod:`dlocli.migrations`),
    so the jobs of runs made before a field was added keep their fingerprint; so are fields
    without effect (the free ones, the task's inert ones)."""
    free = FREE_FIELDS if with_options else {*FREE_FIELDS, "options"}
    data = without_legacy_values("bench", spec.model_dump(mode="json", exclude=free))
    task = without_legacy_values("task", data["task"])
    data["task"] = {k: v for k, v in task.items() if k not in spec.task.inert_fields()}
    backend = without_legacy_values("backend", data["backend"])
    data["backend"] = {**backend, "rod": without_legacy_values("rod", backend["rod"])}
    data["model"] = model_fingerprint_form(data["model"], type(spec.model).moved)
    data["fit"] = fit_fingerprint_form(data["fit"])
    data["mpc"] = without_legacy_values("mpc", data["mpc"])
    return data


def option_agents() -> list[str]:
    """The agents that take options: the learning agents with a spec (sac, td3, pilco, ...);
    mpc's are the bench spec's own model, fit and mpc fields."""
    return [
        name
        for name in controllers.names()
        if issubclass(cls := controllers.get(name), LearningAgent) and cls.spec_cls is not None
    ]


def resolved_options(spec: BenchSpec, agent: str) -> dict[str, Any] | None:
    """The options ``agent`` ran with, defaults filled in (None for agents without any)."""
    if agent not in option_agents():
        return None
    options = controller_spec(agent, spec.options.get(agent))
    return options.model_dump(mode="json") if options else None


def fingerprinted_options(spec: BenchSpec, agent: str) -> dict[str, Any]:
    """``agent``'s resolved options less those at the value they had before they existed
    (:mod:`dlocli.migrations`): jobs that predate an option keep their fingerprint."""
    return without_legacy_values(agent, resolved_options(spec, agent) or {})


def seeds_of(spec: BenchSpec) -> list[int]:
    return [spec.seed + i for i in range(spec.seeds)]


def mpc_schedule(spec: BenchSpec, agent: str = "mpc") -> tuple[int, int, int]:
    """(initial episodes I, trials per iteration N, iterations K) of ``agent`` (mpc or
    mpc-offline) in its budget.

    Iterations are as long as the bench's evaluation interval; the initial dataset as well,
    but at least two episodes (a validation split needs two). ``mpc`` uses I*T + K*N*T
    transitions: at most the budget, less by a remainder shorter than one iteration.
    """
    steps = spec.task.episode_steps
    trials = eval_interval(spec) // steps
    initial = max(2, trials)
    iterations = max(0, (budget_of(spec, agent) // steps - initial) // trials)
    return initial, trials, iterations


def mpc_points(spec: BenchSpec, agent: str = "mpc") -> list[int]:
    """Where ``agent`` is evaluated: after the initial data and after every iteration."""
    initial, trials, iterations = mpc_schedule(spec, agent)
    steps = spec.task.episode_steps
    return [(initial + k * trials) * steps for k in range(iterations + 1)]
