"""``dlo bench``: sample efficiency of the agents under one transition budget (paper Sec. V).

Every agent x seed is one *job*: the agent learns for its budget of env transitions
(``budget``, or its entry in ``budgets``) and is evaluated at regular transition counts with
``eval_trials`` noise-free episodes from fixed random starts (the same starts for every agent
of a seed; evaluation transitions are not counted). Each seed has its own fixed goal. With
``transfer``, the agent is also evaluated where it did not learn: on random goals after
learning a fixed goal, at every evaluation point (paper Fig. 6), and, at the end, the
model-based agents on the bimanual task after learning the single-gripper one (paper Fig. 5).
Every row carries its reference: the evaluation episodes' initial error (what doing nothing
keeps) and the score ``1 - final/initial``; ``zero`` (do nothing) and ``random`` run by
default. Next to the noise-free evaluation, each row holds the mean cumulative reward of the
agent's own training episodes since the previous point (with their exploration: the paper's
Fig. 4 protocol). The agents are in :mod:`dlocli.bench_agents`; the figures in
:mod:`dlocli.bench_plots`.

Run directory (every file written atomically)::

    spec.json                   resolved BenchSpec
    jobs/AGENT-sSEED.json       one finished job: its evaluation rows (resume skips it)
    work/FINGERPRINT/AGENT-sSEED/   a job's own files (mpc's online run), local executor only
    results.csv                 agent, seed, eval, transitions, train_task, train_goals,
                                eval_task, eval_goals, cumulative_reward(_std), final_error_mm,
                                wall_seconds (learning time so far), eval_seconds, initial_error_mm,
                                score(_std), train_reward, train_episodes
    summary.md, summary.json    final results per agent and evaluation setting
    plots/fig4_learning_curves.png, fig5_bimanual.png, fig6_random_goals.png,
    plots/fig7_online_offline.png   (those the results allow)

Seeds: job i uses seed ``seed + i``; every random stream of a job derives from it, and the
global generators are reseeded at the start of each job, so results do not depend on the
executor (local processes or Ray) or on the order of jobs. The fixed goal of job seed s comes
from s alone: one goal shape per seed, the same for every agent.
"""

from __future__ import annotations

import hashlib
import json
import tempfile
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import numpy as np
from pydantic import Field, model_validator

from dlocli.bench_agents import make_bench_env
from dlocli.controllers.mpc import MPCSpec
from dlocli.errors import BadInput, DloError
from dlocli.io import prepare_run_dir, versions, write_json_atomic
from dlocli.models.spec import LEGACY_VALUES, ModelSpec, saved_spec
from dlocli.registry import Registry
from dlocli.rollout import episode_scores, rollout, stream_seed
from dlocli.specs import TASK_LEGACY_VALUES, EnvSpec, refuse_resume_conflicts
from dlocli.train_spec import FitSpec

Progress = Callable[[str, dict[str, Any]], None]

agents = Registry("agent")
agents.register("zero", "dlocli.bench_agents:ZeroLearner", "all-zero actions: do nothing")
agents.register("random", "dlocli.bench_agents:RandomLearner", "uniform random actions")
agents.register("sac", "dlocli.bench_agents:AgentLearner", "Soft Actor-Critic (SB3)")
agents.register("td3", "dlocli.bench_agents:AgentLearner", "TD3 (SB3)")
agents.register("pilco", "dlocli.bench_agents:AgentLearner", "PILCO (GP dynamics, RBF policy)")
agents.register(
    "mpc",
    "dlocli.bench_agents:OnlineMPCLearner",
    "online model learning + gradient MPC (paper Algorithm 1)",
)
agents.register(
    "mpc-offline",
    "dlocli.bench_agents:OfflineMPCLearner",
    "gradient MPC, model trained offline on as many random transitions (Fig. 7)",
)

#: fields that may change between runs of one directory: they do not change any result
#: (``budgets`` enters the fingerprint of each job through that agent's own budget)
FREE_FIELDS = {"agents", "seeds", "executor", "workers", "ray_address", "out", "budgets"}
EVAL = 5  # seed stream of evaluation starts
#: the agents that take options (their controllers' specs); mpc's are the spec's own fields
OPTION_AGENTS = ("sac", "td3", "pilco")


class BenchSpec(EnvSpec):
    """`dlo bench`: every agent x seed learns under the same transition budget."""

    agents: list[str] = Field(
        default_factory=lambda: ["zero", "random", "sac", "td3", "pilco", "mpc"],
        description="Agents to compare: zero, random, sac, td3, pilco, mpc, mpc-offline "
        "(zero and random are the references every result is read against).",
    )
    budget: int = Field(5000, gt=0, description="Env transitions each agent may learn from.")
    budgets: dict[str, int] = Field(
        default_factory=dict,
        description="Per-agent budgets overriding `budget`, e.g. {sac: 50000, td3: 50000}; "
        "evaluation points stay `budget / evals` apart, so curves share their x values.",
    )
    seeds: int = Field(3, gt=0, description="Seeds per agent: seed, seed+1, ...")
    evals: int = Field(
        10, gt=0, description="Evaluation points, at regular transition counts (whole episodes)."
    )
    eval_trials: int = Field(5, gt=0, description="Noise-free episodes per evaluation point.")
    options: dict[str, dict[str, Any]] = Field(
        default_factory=dict,
        description="Options of the learning agents by name, e.g. {sac: {net_arch: [64, 64]}}.",
    )
    model: ModelSpec = Field(default_factory=ModelSpec, description="Dynamics model of mpc.")
    fit: FitSpec = Field(default_factory=FitSpec, description="mpc's model update per iteration.")
    mpc: MPCSpec = Field(default_factory=MPCSpec, description="The MPC of mpc and mpc-offline.")
    noise_probability: float = Field(
        0.2, ge=0, le=1, description="Probability that an mpc training step gets action noise."
    )
    noise_std: float = Field(0.3, ge=0, description="Std of mpc's training action noise.")
    transfer: bool = Field(
        True,
        description="Also evaluate final agents on random goals (after a fixed goal) and "
        "model-based ones on the bimanual task (after the single one).",
    )
    executor: Literal["local", "ray"] = Field(
        "local", description="Where jobs run: local processes, or Ray tasks."
    )
    workers: int | None = Field(
        None, gt=0, description="Parallel jobs (local processes or Ray CPUs); None = CPU count."
    )
    ray_address: str | None = Field(
        None,
        description="Ray cluster to join (host:port, ray://host:port or auto); None = "
        "start a local Ray instance.",
    )
    threads: int = Field(1, gt=0, description="Torch threads per job.")
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
    # fields at the value they had before they existed are left out, so the jobs of runs
    # made before a field was added keep their fingerprint; so are fields without effect
    legacy_model = {k for k, v in LEGACY_VALUES.items() if getattr(spec.model, k) == v}
    legacy_task = {k for k, v in TASK_LEGACY_VALUES.items() if getattr(spec.task, k) == v}
    legacy_task |= spec.task.inert_fields()
    exclude = {**dict.fromkeys(FREE_FIELDS, True), "model": legacy_model, "task": legacy_task}
    if agent is None:
        text = spec.model_dump_json(exclude=exclude)
    else:
        text = spec.model_dump_json(exclude={**exclude, "options": True})
        if agent in OPTION_AGENTS:
            text += f"|options={json.dumps(resolved_options(spec, agent), sort_keys=True)}"
        if budget_of(spec, agent) != spec.budget:
            text += f"|budget={budget_of(spec, agent)}"
    return hashlib.sha256(text.encode()).hexdigest()[:12]


def resolved_options(spec: BenchSpec, agent: str) -> dict[str, Any] | None:
    """The options ``agent`` ran with, defaults filled in (None for agents without any)."""
    from dlocli.controllers.base import controller_spec

    if agent not in OPTION_AGENTS:
        return None
    options = controller_spec(agent, spec.options.get(agent))
    return options.model_dump(mode="json") if options else None


def seeds_of(spec: BenchSpec) -> list[int]:
    return [spec.seed + i for i in range(spec.seeds)]


# ----------------------------------------------------------------------------- checks
def check_spec(spec: BenchSpec) -> None:
    """Refuse what cannot run, with one line naming the fix (BadInput)."""
    from dlocli.bench_agents import mpc_schedule
    from dlocli.bench_executors import check_executor
    from dlocli.controllers.base import controller_spec
    from dlocli.registry import backends, tasks

    backends.check(spec.backend.name)
    tasks.check(spec.task.name)
    if not spec.agents:
        raise BadInput(f"--agents is empty; pass some of {', '.join(agents.names())}")
    for name in spec.agents:
        agents.check(name)
    if len(set(spec.agents)) != len(spec.agents):
        raise BadInput(f"--agents {','.join(spec.agents)} names an agent twice; list each once")
    steps = spec.task.episode_steps
    if spec.budget < steps:
        raise BadInput(
            f"--budget {spec.budget} is less than one episode ({steps} steps); "
            f"pass --budget {steps} or more"
        )
    for name, budget in spec.budgets.items():
        agents.check(name)
        if budget < spec.budget:
            raise BadInput(
                f"budgets: {name}={budget} is below --budget {spec.budget}; per-agent budgets "
                "extend the common one (lower --budget instead)"
            )
    for name in {"mpc", "mpc-offline"} & set(spec.agents):
        if mpc_schedule(spec, name)[0] * steps > budget_of(spec, name):
            raise BadInput(
                f"--budget {spec.budget}: mpc needs at least two episodes "
                f"({2 * steps} transitions); raise --budget or drop mpc"
            )
    if spec.task.observe_velocity != spec.model.velocity_input:
        raise BadInput(
            f"task.observe_velocity={spec.task.observe_velocity} but "
            f"model.velocity_input={spec.model.velocity_input}: every agent must get the same "
            "information; set both to the same value"
        )
    for name, options in spec.options.items():
        if name not in OPTION_AGENTS:
            raise BadInput(
                f"options for '{name}': only sac, td3 and pilco take options "
                "(mpc uses the spec's model, fit and mpc fields)"
            )
        controller_spec(name, options)
    check_executor(spec.executor, spec.ray_address)


# ----------------------------------------------------------------------------- evaluation
def eval_episode(controller: Any, env: Any, seed: int) -> dict[str, float]:
    """Initial and final error, score and cumulative reward of one noise-free episode from
    ``seed`` (a diverged episode stops there; its missing steps count at the clip)."""
    return episode_scores(rollout(env, controller, seed), env.task_spec.episode_steps)


def evaluate(controller: Any, env: Any, spec: BenchSpec, seed: int) -> dict[str, float]:
    """Mean (and std) over ``eval_trials`` episodes from the seed's evaluation starts."""
    start = time.perf_counter()
    results = [
        eval_episode(controller, env, stream_seed(seed, EVAL, i)) for i in range(spec.eval_trials)
    ]
    column = {key: np.array([r[key] for r in results]) for key in results[0]}
    return {
        "cumulative_reward": float(column["cumulative_reward"].mean()),
        "cumulative_reward_std": float(column["cumulative_reward"].std()),
        "initial_error_mm": float(column["initial_error_mm"].mean()),
        "final_error_mm": float(column["final_error_mm"].mean()),
        "score": float(column["score"].mean()),
        "score_std": float(column["score"].std()),
        "eval_seconds": round(time.perf_counter() - start, 3),
    }


def curve_settings(spec: BenchSpec) -> list[tuple[str, str]]:
    """(task, goals) where agents are evaluated at every point: where they learn, and random
    goals after a fixed one (paper Fig. 6)."""
    settings = [(spec.task.name, spec.task.goal)]
    if spec.transfer and spec.task.goal == "fixed":
        settings.append((spec.task.name, "random"))
    return settings


def final_settings(spec: BenchSpec) -> list[tuple[str, str]]:
    """(task, goals) where final agents are also evaluated: the bimanual task after the
    single-gripper one (paper Fig. 5)."""
    if spec.transfer and spec.task.name == "single":
        return [("bimanual", spec.task.goal)]
    return []


# ----------------------------------------------------------------------------- one job
def _seed_globals(seed: int) -> None:
    import random

    import torch

    random.seed(seed)
    np.random.seed(seed % 2**32)
    torch.manual_seed(seed)


@contextmanager
def _workdir(scratch: str | None) -> Iterator[Path]:
    if scratch is not None:
        yield Path(scratch)  # created by the agents that write there
        return
    with tempfile.TemporaryDirectory(prefix="dlo-bench-") as tmp:
        yield Path(tmp)


def run_job(spec_json: str, agent: str, seed: int, scratch: str | None = None) -> dict[str, Any]:
    """Learn and evaluate one agent x seed; returns its result (rows of results.csv)."""
    import torch

    spec = BenchSpec.model_validate_json(spec_json)
    threads = torch.get_num_threads()
    torch.set_num_threads(spec.threads)
    _seed_globals(seed)
    start = time.perf_counter()
    try:
        with _workdir(scratch) as work:
            rows = _learn_and_evaluate(spec, agent, seed, work)
    finally:
        torch.set_num_threads(threads)
    return {
        "agent": agent,
        "seed": seed,
        "fingerprint": fingerprint(spec, agent),
        "options": resolved_options(spec, agent),
        "rows": rows,
        "seconds": round(time.perf_counter() - start, 1),
        "versions": versions(),
    }


def _learn_and_evaluate(spec: BenchSpec, agent: str, seed: int, work: Path) -> list[dict]:
    learner = agents.get(agent)(agent, spec, seed, work)
    envs = {setting: make_bench_env(spec, *setting, seed) for setting in curve_settings(spec)}
    rows, wall, trained = [], 0.0, 0
    try:
        for index, point in enumerate(learner.points()):
            start = time.perf_counter()
            learner.learn_to(point)
            wall += time.perf_counter() - start
            returns = learner.training_returns()
            point_row = {
                "agent": agent,
                "seed": seed,
                "train_task": spec.task.name,
                "train_goals": spec.task.goal,
                "eval": index,
                "transitions": learner.transitions,
                "wall_seconds": round(wall, 3),
                "train_reward": float(np.mean(returns[trained:])) if returns[trained:] else None,
                "train_episodes": len(returns) - trained,
            }
            trained = len(returns)
            for setting, env in envs.items():
                rows += _evaluation_rows(spec, learner, env, setting, seed, point_row)
        for setting in final_settings(spec):
            env = make_bench_env(spec, *setting, seed)
            try:
                rows += _evaluation_rows(spec, learner, env, setting, seed, point_row)
            finally:
                env.close()
    finally:
        for env in envs.values():
            env.close()
        learner.close()
    return rows


def _evaluation_rows(
    spec: BenchSpec, learner: Any, env: Any, setting: tuple[str, str], seed: int, point: dict
) -> list[dict[str, Any]]:
    """The row of one evaluation of ``learner`` on ``env`` (none where it cannot act)."""
    controller = learner.controller(env)
    if controller is None:
        return []
    task, goals = setting
    return [
        {**point, "eval_task": task, "eval_goals": goals, **evaluate(controller, env, spec, seed)}
    ]


# ----------------------------------------------------------------------------- jobs
@dataclass(frozen=True)
class Job:
    """One agent x seed; ``scratch``: its work directory (None: a temporary one)."""

    agent: str
    seed: int
    scratch: str | None = None

    @property
    def name(self) -> str:
        return f"{self.agent}-s{self.seed}"


# ----------------------------------------------------------------------------- the run
class BenchRun:
    """The jobs of a bench over a run directory; :meth:`run` again resumes."""

    def __init__(self, spec: BenchSpec, progress: Progress | None = None) -> None:
        self.spec = spec
        self.out = Path(spec.out)
        self.progress = progress or (lambda event, info: None)

    def job_file(self, agent: str, seed: int) -> Path:
        return self.out / "jobs" / f"{agent}-s{seed}.json"

    def finished(self, agent: str, seed: int) -> dict[str, Any] | None:
        """The job's saved result, if it was run with this spec."""

        path = self.job_file(agent, seed)
        if not path.is_file():
            return None
        result = json.loads(path.read_text())
        return result if result.get("fingerprint") == fingerprint(self.spec, agent) else None

    def jobs(self) -> list[Job]:
        """The jobs still to run (finished ones are kept), seed-major so seeds finish early."""
        local = self.spec.executor == "local"
        work = self.out / "work" / fingerprint(self.spec)
        return [
            Job(agent, seed, str(work / f"{agent}-s{seed}") if local else None)
            for seed in seeds_of(self.spec)
            for agent in self.spec.agents
            if self.finished(agent, seed) is None
        ]

    def run(self, executor: Any) -> dict[str, Any]:
        """Run the missing jobs on ``executor`` (:mod:`dlocli.bench_executors`), saving each
        as it finishes; then write the results."""
        todo, failed = self.jobs(), []
        total = len(self.spec.agents) * self.spec.seeds
        self.progress("start", {"total": total, "todo": len(todo)})
        if todo:
            for job, result in executor.run(self.spec.model_dump_json(), todo):
                if isinstance(result, BaseException):
                    failed.append(f"{job.name}: {type(result).__name__}: {result}")
                    self.progress("failed", {"job": job.name, "error": failed[-1]})
                    continue
                write_json_atomic(self.job_file(job.agent, job.seed), result)
                self.progress("job", {"job": job.name, "seconds": result["seconds"]})
        summary = self.write_results()
        if failed:
            raise DloError(
                f"{len(failed)} job(s) failed (finished ones are saved; rerun with "
                f"--resume {self.out}): {failed[0]}"
            )
        return summary

    def rows(self) -> list[dict[str, Any]]:
        rows = []
        for agent in self.spec.agents:
            for seed in seeds_of(self.spec):
                result = self.finished(agent, seed)
                rows += result["rows"] if result else []
        return rows

    def write_results(self) -> dict[str, Any]:
        from dlocli.bench_plots import draw_figures, summary_table, write_results_csv, write_summary

        rows = self.rows()
        write_results_csv(self.out / "results.csv", rows)
        table = summary_table(rows)
        figures = draw_figures(rows, self.out / "plots")
        return write_summary(
            self.out,
            table,
            figures,
            {
                "jobs_done": len({(r["agent"], r["seed"]) for r in rows}),
                "jobs": len(self.spec.agents) * self.spec.seeds,
            },
        )


# ----------------------------------------------------------------------------- entry points
def start_bench(
    spec: BenchSpec, overwrite: bool = False, progress: Progress | None = None
) -> dict[str, Any]:
    """A new bench in ``spec.out`` (with ``overwrite``: finished jobs of the same spec kept)."""
    from dlocli.bench_executors import open_executor

    check_spec(spec)
    if (Path(spec.out) / "spec.json").is_file() and not overwrite:
        raise BadInput(
            f"--out {spec.out} holds a bench run; continue it with --resume "
            f"{spec.out}, or pass --overwrite or another --out"
        )
    with open_executor(spec) as executor:  # a Ray address that fails is refused before writing
        out = prepare_run_dir(spec.out, overwrite)
        write_json_atomic(out / "spec.json", spec.model_dump(mode="json"))
        return BenchRun(spec, progress).run(executor)


def load_bench_spec(run_dir: Path) -> BenchSpec:
    path = Path(run_dir) / "spec.json"
    if not path.is_file():
        raise BadInput(
            f"{run_dir} is not a bench run (no spec.json); "
            "pass the --out directory of an earlier `dlo bench`"
        )
    try:
        return BenchSpec.model_validate(saved_spec(path))
    except ValueError as exc:
        raise BadInput(
            f"{path} is not a bench spec; pass the directory of a `dlo bench` run"
        ) from exc


def resume_bench(
    run_dir: Path, overrides: dict[str, Any], progress: Progress | None = None
) -> dict[str, Any]:
    """Run the missing jobs of ``run_dir``. Agents, seeds and the executor may change."""
    from dlocli.bench_executors import open_executor

    spec = load_bench_spec(run_dir)
    data = spec.model_dump()
    refuse_resume_conflicts(data, overrides, run_dir, frozenset(FREE_FIELDS))
    free = {k: v for k, v in overrides.items() if k in FREE_FIELDS and v is not None}
    spec = BenchSpec.model_validate({**data, **free, "out": Path(run_dir)})
    check_spec(spec)
    with open_executor(spec) as executor:
        write_json_atomic(Path(run_dir) / "spec.json", spec.model_dump(mode="json"))
        return BenchRun(spec, progress).run(executor)


def report_bench(run_dirs: list[Path]) -> dict[str, Any]:
    """Redraw figures and table from results.csv of one run (or several, merged into the first)."""
    from dlocli.bench_plots import draw_figures, read_results_csv, summary_table, write_summary

    if not run_dirs:
        raise BadInput("--report needs a run directory")
    rows = [row for run in run_dirs for row in read_results_csv(Path(run) / "results.csv")]
    out = Path(run_dirs[0])
    table = summary_table(rows)
    figures = draw_figures(rows, out / "plots")
    return write_summary(out, table, figures, {"runs": [str(r) for r in run_dirs]})
