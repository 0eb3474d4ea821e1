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
Fig. 4 protocol). The agents are in :mod:`dlocli.bench.agents`; the figures in
:mod:`dlocli.bench.report`.

Run directory (every file written atomically)::

    spec.json                   resolved BenchSpec
    jobs/AGENT-sSEED.json       one finished job: its evaluation rows (resume skips it)
    work/FINGERPRINT/AGENT-sSEED/   a job's own files (mpc's online run), local executor only
    work/FINGERPRINT/AGENT-sSEED/policy/   sac's and td3's final policy (`dlo control --policy`)
    work/locks/AGENT-sSEED/     held by the process running the job: several processes may
                                resume one bench, each skips the jobs another holds
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

from contextlib import ExitStack
from pathlib import Path
from typing import Any

from dlocli.bench.agents import agent_names, check_agent, is_reference
from dlocli.bench.checkpoint import JobCheckpoint
from dlocli.bench.jobs import RESUME_DIR, Job, run_job
from dlocli.bench.report import (
    draw_figures,
    read_results_csv,
    summary_table,
    write_results_csv,
    write_summary,
)
from dlocli.bench.spec import (
    FREE_FIELDS,
    BenchSpec,
    budget_of,
    fingerprint,
    mpc_schedule,
    option_agents,
    seeds_of,
)
from dlocli.cancel import CancelToken
from dlocli.controllers.base import controller_spec
from dlocli.controllers.sb3_specs import SB3Spec
from dlocli.env.shape_env import observation_space, observed_markers
from dlocli.errors import BadInput, DloError
from dlocli.events import Began, Callback, Event, ignore
from dlocli.executors import ClusterLost, check_executor, open_executor
from dlocli.io import adopt_written, prepare_run_dir, read_json, write_json_atomic
from dlocli.models.base import refuse_oversized_model
from dlocli.resume import resumed_run_spec
from dlocli.rundir import InUse, owned
from dlocli.runs.checks import check_registered
from dlocli.threads import machine_cpus, warn_if_oversubscribed

#: the top-level entries of a bench run (the layout above)
LAYOUT_TOPS = frozenset(
    {"spec.json", "jobs", "work", "results.csv", "summary.md", "summary.json", "plots"}
)


# ----------------------------------------------------------------------------- checks
def check_spec(spec: BenchSpec) -> None:
    """Refuse what cannot run, with one line naming the fix (BadInput)."""
    check_registered(spec)
    if not spec.agents:
        raise BadInput(f"--agents is empty; pass some of {', '.join(agent_names())}")
    for name in spec.agents:
        check_agent(name)
    if len(set(spec.agents)) != len(spec.agents):
        raise BadInput(f"--agents {','.join(spec.agents)} names an agent twice; list each once")
    steps = spec.task.episode_steps
    if spec.budget < steps:
        raise BadInput(
            f"--budget {spec.budget} is less than one episode ({steps} steps); "
            f"pass --budget {steps} or more"
        )
    for name, budget in spec.budgets.items():
        check_agent(name)
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
        if name not in option_agents():
            raise BadInput(
                f"options for '{name}': only {', '.join(option_agents())} take options "
                "(mpc uses the spec's model, fit and mpc fields)"
            )
        controller_spec(name, options)
    _refuse_oversized_agents(spec)
    check_executor(spec.executor, spec.ray_address)
    if spec.executor == "local":
        warn_if_oversubscribed(spec.threads, spec.workers or machine_cpus())


def _refuse_oversized_agents(spec: BenchSpec) -> None:
    """BadInput, before any job starts, if a model or an SB3 agent would not fit in memory."""
    n_segments = spec.backend.rod.n_segments
    if {"mpc", "mpc-offline"} & set(spec.agents):
        refuse_oversized_model(spec.model, n_segments)
    markers = observed_markers(spec.task)
    obs_dim = observation_space(n_segments, spec.task.observe_velocity, markers).shape[0]
    for name in set(spec.agents) & set(option_agents()):
        options = controller_spec(name, spec.options.get(name))
        if isinstance(options, SB3Spec):  # 12: two grippers' actions, the largest
            options.refuse_oversized(name, obs_dim, action_dim=12)


# ----------------------------------------------------------------------------- the run
class BenchRun:
    """The jobs of a bench over a run directory; :meth:`run` again resumes."""

    def __init__(
        self, spec: BenchSpec, progress: Callback | None = None, cancel: CancelToken | None = None
    ) -> None:
        """``progress`` gets a Began of the jobs to run (``values``: the bench's ``total``
        jobs, those ``continuing`` from a checkpoint, at how many transitions, and those left
        to another process, by PID: ``elsewhere``), then an Event per finished job (its
        ``job`` name and ``seconds``; a failed one: ``error``). ``cancel`` stops the bench
        between jobs, and a job run in this process between its physics and gradient steps;
        finished jobs are saved, a stopped job keeps its last evaluation point."""
        self.spec = spec
        self.out = Path(spec.out)
        self.progress = progress or ignore
        self.cancel = cancel or CancelToken()

    def job_file(self, agent: str, seed: int) -> Path:
        return self.out / "jobs" / f"{agent}-s{seed}.json"

    def finished(self, agent: str, seed: int) -> dict[str, Any] | None:
        """The job's saved result, if it was run with this spec."""

        path = self.job_file(agent, seed)
        if not path.is_file():
            return None
        result = read_json(path, dict)
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

    def checkpointed(self, job: Job) -> int | None:
        """The transitions a stopped job continues from (:mod:`dlocli.bench.checkpoint`)."""
        if job.scratch is None:
            return None
        checkpoint = JobCheckpoint(
            Path(job.scratch) / RESUME_DIR, fingerprint(self.spec, job.agent)
        )
        found = checkpoint.latest()
        return found[1].rows[-1]["transitions"] if found and found[1].rows else None

    def run(self, executor: Any) -> dict[str, Any]:
        """Run the missing jobs on ``executor`` (:mod:`dlocli.executors`), saving each
        as it finishes; then write the results."""
        todo = self.jobs()
        total = len(self.spec.agents) * self.spec.seeds
        with ExitStack() as locks:
            elsewhere = self._lock_jobs(locks, todo)
            todo = [job for job in todo if job.name not in elsewhere]
            continuing = {job.name: at for job in todo if (at := self.checkpointed(job))}
            self.progress(Began("job", 0, len(todo), {"total": total, "continuing": continuing,
                                                       "elsewhere": elsewhere}))  # fmt: skip
            failed = self._run_jobs(executor, todo)
        summary = self.write_results()
        if failed:
            # bad input if that is all the jobs met; else the machine's own failure (exit 1)
            error = BadInput if all(isinstance(e, BadInput) for e in failed.values()) else DloError
            causes = "; ".join(f"{name}: {_cause(exc)}" for name, exc in failed.items())
            raise error(
                f"{len(failed)} bench job(s) failed ({causes}); finished jobs are saved, rerun "
                f"with --resume {self.out}"
            )
        return summary

    def _lock_jobs(self, locks: ExitStack, todo: list[Job]) -> dict[str, str]:
        """Take the lock of every job in ``todo``; the jobs another process holds (name ->
        its PID) are left to it, so processes resuming one bench share out its jobs."""
        elsewhere: dict[str, str] = {}
        for job in todo:
            try:
                locks.enter_context(owned(self.out / "work" / "locks" / job.name))
            except InUse as busy:
                elsewhere[job.name] = busy.holder
        return elsewhere

    def _run_jobs(self, executor: Any, todo: list[Job]) -> dict[str, BaseException]:
        """Run ``todo``, saving each job as it finishes; what each failed job raised."""
        failed: dict[str, BaseException] = {}
        spec_json = self.spec.model_dump_json()
        calls = [(spec_json, job.agent, job.seed, job.scratch, self.cancel) for job in todo]
        self.cancel.raise_if_cancelled()  # before any job starts, here or in a worker
        try:
            for done, (index, result) in enumerate(executor.map(run_job, calls), 1):
                job = todo[index]
                if isinstance(result, BaseException):
                    failed[job.name] = result
                    error = {"job": job.name, "error": _cause(result)}
                    self.progress(Event("job", done, len(todo), error))
                    continue
                write_json_atomic(self.job_file(job.agent, job.seed), result)
                took = {"job": job.name, "seconds": result["seconds"]}
                self.progress(Event("job", done, len(todo), took))
                self.cancel.raise_if_cancelled()
        except ClusterLost as lost:
            raise DloError(lost.line(self.out)) from lost
        return failed

    def write_results_csv_from_jobs(self) -> None:
        """results.csv from every job file of this spec in jobs/, whatever the agents."""
        rows = []
        for path in sorted((self.out / "jobs").glob("*-s*.json")):
            agent, _, seed = path.stem.rpartition("-s")
            result = self.finished(agent, int(seed)) if seed.isdigit() else None
            rows += result["rows"] if result else []
        write_results_csv(self.out / "results.csv", rows)

    def rows(self) -> list[dict[str, Any]]:
        rows = []
        for agent in self.spec.agents:
            for seed in seeds_of(self.spec):
                result = self.finished(agent, seed)
                rows += result["rows"] if result else []
        return rows

    def write_results(self) -> dict[str, Any]:
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
    spec: BenchSpec,
    overwrite: bool = False,
    progress: Callback | None = None,
    cancel: CancelToken | None = None,
) -> dict[str, Any]:
    """A new bench in ``spec.out`` (with ``overwrite``: finished jobs of the same spec kept);
    ``progress`` and ``cancel`` as :class:`BenchRun` takes them."""
    check_spec(spec)
    if (Path(spec.out) / "spec.json").is_file() and not overwrite:
        if (Path(spec.out) / "jobs").is_dir():
            raise BadInput(
                f"--out {spec.out} holds a bench run; continue it with --resume "
                f"{spec.out}, or pass --overwrite or another --out"
            )
        raise BadInput(f"--out {spec.out} holds another command's run; pass another --out")
    # the executor connects first: a bad Ray address leaves the directory as it was
    with open_executor(spec, spec.threads) as executor, owned(spec.out):
        out = prepare_run_dir(spec.out, overwrite)
        write_json_atomic(out / "spec.json", spec.model_dump(mode="json"))
        return BenchRun(spec, progress, cancel).run(executor)


def load_bench_spec(run_dir: Path, overrides: dict[str, Any] | None = None) -> BenchSpec:
    """The spec of the bench run in ``run_dir``, the free fields of ``overrides`` applied."""
    free = frozenset(FREE_FIELDS)
    return resumed_run_spec(BenchSpec, run_dir, overrides or {}, "a bench", "dlo bench", free)


def resume_bench(
    run_dir: Path,
    overrides: dict[str, Any],
    progress: Callback | None = None,
    cancel: CancelToken | None = None,
) -> dict[str, Any]:
    """Run the missing jobs of ``run_dir``. Agents, seeds and the executor may change;
    ``progress`` and ``cancel`` as :class:`BenchRun` takes them."""
    spec = load_bench_spec(run_dir, overrides)
    check_spec(spec)
    with open_executor(spec, spec.threads) as executor, owned(run_dir, shared=True):
        adopt_written(Path(run_dir), LAYOUT_TOPS)  # a run killed outright could not record them
        write_json_atomic(Path(run_dir) / "spec.json", spec.model_dump(mode="json"))
        return BenchRun(spec, progress, cancel).run(executor)


def _cause(exc: BaseException) -> str:
    """What a job raised, on one line: our own errors by their message (it names the fix),
    any other by its type too."""
    message = " ".join(str(exc).split())
    return message if isinstance(exc, DloError) else f"{type(exc).__name__}: {message}"


def report_bench(run_dirs: list[Path]) -> dict[str, Any]:
    """Redraw figures and table of one run (or several, merged into the first): a run's
    results.csv is first rewritten from its finished job files, so a run still in progress
    (or one whose jobs ran in several processes) reports everything finished so far.

    The first directory may be a new, empty one that only receives the merged report (e.g.
    Fig. 5 from a single-gripper run and a bimanual one). Where two runs hold the same agent
    learned on the same task and goals (say ``mpc`` with and without ``fit.mirror``), each
    is labelled with its run directory's name: ``mpc [bench_paper_mirror]``; the references
    (``zero``, ``random``) keep their names, a seed's evaluation counted once."""
    if not run_dirs:
        raise BadInput("--report needs a run directory")
    for run in run_dirs:
        if (Path(run) / "spec.json").is_file() and (Path(run) / "jobs").is_dir():
            BenchRun(load_bench_spec(Path(run))).write_results_csv_from_jobs()
    out = Path(run_dirs[0])
    sources = run_dirs[:1] if (out / "results.csv").is_file() or len(run_dirs) == 1 else []
    sources += run_dirs[1:]
    if not out.is_dir():
        raise BadInput(f"--report {out}: not a directory; create it or pass a run directory")
    rows = _label_shared_agents({Path(r): read_results_csv(Path(r) / "results.csv")
                                 for r in sources})  # fmt: skip
    table = summary_table(rows)
    figures = draw_figures(rows, out / "plots")
    return write_summary(out, table, figures, {"runs": [str(r) for r in sources]})


def _label_shared_agents(rows_by_run: dict[Path, list[dict[str, Any]]]) -> list[dict[str, Any]]:
    """All rows, an agent's name suffixed with its run's where several runs hold it learned
    on the same task and goals (they are different agents: different specs). A reference
    that learns nothing is the same measurement in every run: it keeps its name, and an
    evaluation two runs share (same seed, setting and point) is counted once."""

    def key(row: dict[str, Any]) -> tuple:
        return row["agent"], row["train_task"], row["train_goals"]

    runs_of: dict[tuple, set[Path]] = {}
    for run, rows in rows_by_run.items():
        for row in rows:
            runs_of.setdefault(key(row), set()).add(run)
    merged, seen = [], set()
    for run, rows in rows_by_run.items():
        for row in rows:
            if len(runs_of[key(row)]) == 1:
                merged.append(row)
            elif not is_reference(row["agent"]):
                merged.append({**row, "agent": f"{row['agent']} [{run.name}]"})
            elif (evaluation := _evaluation_key(row)) not in seen:
                seen.add(evaluation)
                merged.append(row)
    return merged


def _evaluation_key(row: dict[str, Any]) -> tuple:
    return tuple(row[k] for k in ("agent", "seed", "train_task", "train_goals", "eval_task",
                                  "eval_goals", "transitions"))  # fmt: skip
