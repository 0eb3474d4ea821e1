"""Online model learning with MPC: the paper's Algorithm 1 (``dlo online``).

    D <- initial random transitions
    for k = 1..K:
        update the model on D for E epochs (continuing from the previous weights, input noise)
        for j = 1..N: run a trial of T steps from a random start with MPC through the model;
                      with probability p add action noise a ~ A_noise; append (s, a, s') to D

Run directory (every file written atomically)::

    spec.json                      resolved OnlineSpec
    data/initial.h5                the initial random dataset
    data/iter_KK/trial_JJJ.h5      one file per finished trial: the dataset grows atomically
    checkpoints/iter_KK.pt         the model after iteration KK's training (+ Adam state)
    checkpoints/final.pt           the last iteration's model
    references.json                doing nothing and random actions from every trial's start
    metrics.csv                    iteration, trial, transitions, cumulative_reward, ...
    summary.json, plots/learning_curve.png

Resume (``--resume RUN``): an iteration whose checkpoint exists is not retrained; a trial
whose file exists is not rerun. Every random stream is derived from (seed, iteration, trial),
so a resumed run reproduces an uninterrupted one with the same seed.

Where trials run (:mod:`dlocli.executors`): in this process, a pool of local processes
(``workers``), or Ray tasks on a cluster (``executor``, ``ray_address``). Each trial gets the
model's checkpoint as bytes and one thread (``threads``: more), and returns its episode: this
process (the driver) writes every file and updates the model (on ``fit.device``; Ray's trials
plan on their CPUs), so a cluster needs no shared file system, and the same seed gives the
same trials on any executor. Executor and workers may change on resume.
"""

from __future__ import annotations

import csv
import io
import json
import shutil
import tempfile
import time
from collections.abc import Callable
from contextlib import AbstractContextManager, nullcontext
from pathlib import Path
from typing import Any, ClassVar

import numpy as np
from pydantic import Field

from dlocli.controllers.base import references
from dlocli.controllers.specs import (
    PlannerName,
    PlannerOptions,
    planner_name_field,
    planner_options_field,
)
from dlocli.data import Dataset, Episode, load_dataset
from dlocli.env.rollout import NoisyPolicy, episode_scores, random_episode, rollout, stream_seed
from dlocli.errors import DloError
from dlocli.executors import (
    ClusterLost,
    ExecutorChoice,
    LocalExecutor,
    check_executor,
    open_executor,
)
from dlocli.io import adopt_written, prepare_run_dir, write_json_atomic, write_text_atomic
from dlocli.limits import MAX_COUNT, MAX_PROCESSES, refuse_oversized_dataset
from dlocli.models.spec import ModelField, UpdateSpec, model_field
from dlocli.resume import resumed_run_spec
from dlocli.rundir import FINGERPRINTS_FILE, check_fingerprints, owned, record_fingerprints
from dlocli.runs.references import ReferenceTable, reference_episode_scores
from dlocli.specs import MODEL_OPTIONS, EnvSpec
from dlocli.tensorboard import TENSORBOARD_DIR, Scalars
from dlocli.threads import torch_threads, warn_if_oversubscribed

Progress = Callable[[str, dict[str, Any]], None]


class OnlineSpec(EnvSpec, ExecutorChoice):
    """`dlo online`: Algorithm 1 of the paper. Defaults are the paper's parameters. Its jobs
    are the trials and reference episodes; the model update stays in this process."""

    moved: ClassVar[dict[str, str]] = {"steps": "task.episode_steps"}
    cli_flags: ClassVar[tuple[str, ...]] = (
        "iters", "trials", "task.episode_steps", "fit.schedule", "fit.epochs", "fit.update_steps",
        "initial_episodes", "planner", "mpc.horizon", "fit.lr", MODEL_OPTIONS, "task.goal",
        "task.name", "task.shapes", "backend.name", "fit.device", "noise_probability",
        "noise_std", "workers", "threads", "executor", "ray_address", "fit.mirror", "offline",
        "seed", "out",
    )  # fmt: skip

    iters: int = Field(
        20, gt=0, le=MAX_COUNT, description="Iterations K of model update + MPC trials."
    )
    trials: int = Field(50, gt=0, le=MAX_COUNT, description="MPC trials N per iteration.")
    initial_episodes: int = Field(
        10,
        gt=1,
        le=MAX_COUNT,
        description="Random-action episodes (of T steps) in the initial dataset D.",
    )
    noise_probability: float = Field(
        0.2, ge=0, le=1, description="Probability that a step's MPC action gets action noise."
    )
    noise_std: float = Field(
        0.3, ge=0, description="A_noise: std of the Gaussian noise added to the action."
    )
    model: ModelField = model_field("Dynamics model.")
    fit: UpdateSpec = Field(
        default_factory=UpdateSpec,
        description="Model update per iteration: E = fit.epochs over all the data (the "
        "paper), or fit.update_steps gradient steps (fit.schedule=steps).",
    )
    planner: PlannerName = planner_name_field()
    mpc: PlannerOptions = planner_options_field("Options of the planner that explores.")
    workers: int = Field(
        1, gt=0, le=MAX_PROCESSES,
        description="Processes running an iteration's trials (at most one per CPU); with "
        "--executor ray and no --ray-address, the CPUs of the local Ray instance.",
    )  # fmt: skip
    threads: int | None = Field(
        None, gt=0, le=MAX_PROCESSES,
        description="Torch threads per job (a trial, a share of reference episodes) and for "
        "the model update; None = chosen from the CPUs: 1 per job, all for the update.",
    )  # fmt: skip
    offline: bool = Field(
        False,
        description="Also train a model offline on as many random transitions as D holds "
        "after each iteration, from scratch and as long as the online model had trained "
        "(epochs or steps, per fit.schedule), and evaluate it with the same trials "
        "(paper Fig. 7).",
    )
    out: Path = Field(Path("runs/online"), description="Run directory.")


#: fields that may change when a run resumes: they change where trials run, not the results
FREE_FIELDS = frozenset({"executor", "ray_address", "workers"})
#: torch threads of a trial, on every executor, unless --threads says otherwise: the planner
#: is fastest with one at these sizes, and the same number everywhere gives the same floats
TRIAL_THREADS = 1


def job_threads(spec: OnlineSpec) -> int:
    """Torch threads of each trial and reference job."""
    return spec.threads or TRIAL_THREADS


def update_threads(spec: OnlineSpec) -> AbstractContextManager[None]:
    """The model update's threads: --threads if given, else the ones this process chose
    (:func:`dlocli.threads.fit_this_process`: the CPUs it may use)."""
    return nullcontext() if spec.threads is None else torch_threads(spec.threads)


def warn_if_threads_oversubscribe(spec: OnlineSpec) -> None:
    """One warning when --threads oversubscribes this machine: the local executor's workers,
    or the update in this process."""
    if spec.threads is not None:
        local = spec.executor == "local"
        warn_if_oversubscribed(spec.threads, min(spec.workers, spec.trials) if local else 1)


# ----------------------------------------------------------------------------- seeds
INITIAL, TRAIN, TRIAL, NOISE, OFFLINE, REFERENCE = 0, 1, 2, 3, 4, 5


def random_data_episode(env: Any, seed: int, e: int) -> Episode:
    """Random episode ``e`` of the run ``seed``: the initial data D_0, and its continuation
    for the models trained offline on as much random data (paper Fig. 7)."""
    return random_episode(env, stream_seed(seed, INITIAL, e), stream_seed(seed, INITIAL, e, 1))


# ----------------------------------------------------------------------------- paths
class RunLayout:
    """Where each file of an online run lives."""

    def __init__(self, out: Path) -> None:
        self.out = Path(out)

    def initial(self) -> Path:
        return self.out / "data" / "initial.h5"

    def trial(self, k: int, j: int, offline: bool = False) -> Path:
        kind = "offline" if offline else "data"
        return self.out / kind / f"iter_{k:02d}" / f"trial_{j:03d}.h5"

    def checkpoint(self, k: int, offline: bool = False) -> Path:
        name = f"offline_{k:02d}.pt" if offline else f"iter_{k:02d}.pt"
        return self.out / "checkpoints" / name

    def offline_data(self, k: int) -> Path:
        return self.out / "offline" / f"random_{k:02d}.h5"

    def references(self) -> Path:
        return self.out / "references.json"

    def state_dirs(self) -> list[Path]:
        """The folders whose files a resumed run takes as already done."""
        return [self.out / "data", self.out / "offline", self.out / "checkpoints"]

    #: every top-level entry a run writes
    TOPS = frozenset({"spec.json", FINGERPRINTS_FILE, "data", "offline", "checkpoints",
                      "references.json", "metrics.csv", "offline_metrics.csv", "summary.json",
                      "plots", TENSORBOARD_DIR})  # fmt: skip


# ----------------------------------------------------------------------------- trials
class _TimedController:
    """A controller whose ``act`` time is added up (the MPC's share of a trial)."""

    def __init__(self, controller: Any) -> None:
        self.controller = controller
        self.seconds = 0.0

    def __getattr__(self, name: str) -> Any:
        return getattr(self.controller, name)

    def act(self, obs: np.ndarray) -> np.ndarray:
        start = time.perf_counter()
        try:
            return self.controller.act(obs)
        finally:
            self.seconds += time.perf_counter() - start


def _trial_episode(spec: OnlineSpec, checkpoint: Path, k: int, j: int) -> tuple[Episode, float]:
    """One trial of the spec's planner through the model in ``checkpoint`` (seeds from
    (seed, k, j)), and the seconds the planner took in it."""
    from dlocli.controllers.base import make_controller
    from dlocli.env.shape_env import make_env_from_spec
    from dlocli.models.base import load_model

    env = make_env_from_spec(_env_spec(spec))
    try:
        model = load_model(checkpoint, spec.fit.device)
        seed = stream_seed(spec.seed, TRIAL, k, j)
        planner = make_controller(spec.planner, env, options=spec.mpc, seed=seed, model=model)
        timed = _TimedController(planner)
        noise_rng = np.random.default_rng(stream_seed(spec.seed, NOISE, k, j))
        policy = NoisyPolicy(timed, noise_rng, spec.noise_probability, spec.noise_std)
        return rollout(env, policy, stream_seed(spec.seed, TRIAL, k, j)), timed.seconds
    finally:
        env.close()


def _env_spec(spec: OnlineSpec) -> EnvSpec:
    return EnvSpec(backend=spec.backend, task=spec.task, seed=spec.seed)


def _run_trial(spec_json: str, checkpoint: bytes, k: int, j: int) -> tuple[Episode, dict[str, Any]]:
    """Trial j of iteration k through the model whose checkpoint file holds ``checkpoint``:
    its episode and scores (an executor's task; the driver writes the file)."""
    import torch

    spec = OnlineSpec.model_validate_json(spec_json)
    start = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="dlo-trial-") as tmp, torch_threads(job_threads(spec)):
        model = Path(tmp) / "model.pt"
        model.write_bytes(checkpoint)
        episode, mpc_seconds = _trial_episode(spec, model, k, j)
        threads = torch.get_num_threads()
    attrs = {
        **episode_scores(episode, spec.task.episode_steps),
        "trial_seconds": round(time.perf_counter() - start, 3),
        "mpc_seconds": round(mpc_seconds, 3),
        "threads": threads,
    }
    return episode, attrs


def _reference_episodes(
    spec_json: str, k: int, runs: list[tuple[str, int]]
) -> list[tuple[str, int, dict[str, float]]]:
    """The reference episodes ``runs`` ((controller, trial) pairs) of iteration k, on one
    env, from the trials' starts (a worker-process entry point)."""
    from dlocli.env.shape_env import make_env_from_spec

    spec = OnlineSpec.model_validate_json(spec_json)
    env = make_env_from_spec(_env_spec(spec))
    try:
        return [
            (name, j, reference_episode_scores(env, name, stream_seed(spec.seed, TRIAL, k, j),
                                               stream_seed(spec.seed, REFERENCE, k, j)))
            for name, j in runs
        ]  # fmt: skip
    finally:
        env.close()


# ----------------------------------------------------------------------------- the loop
class OnlineRun:
    """Algorithm 1 over a run directory; :meth:`run` can be called again to resume."""

    def __init__(
        self, spec: OnlineSpec, progress: Progress | None = None, executor: Any = None
    ) -> None:
        """``executor``: where trials run (:mod:`dlocli.executors`), connected; None: the
        local processes of ``spec.workers``, ended with :meth:`run`."""
        self.spec = spec
        self.paths = RunLayout(spec.out)
        self.progress = progress or (lambda event, info: None)
        self._own_executor = executor is None
        self.executor = executor or LocalExecutor(spec.workers, job_threads(spec))
        self.scalars = Scalars(None)
        self._train_seconds: dict[int, float] = {}

    # ------------------------------------------------------------------ data
    def initial_dataset(self) -> Dataset:
        """Collect (or reload) the initial random dataset D_0."""
        path = self.paths.initial()
        if path.is_file():
            return load_dataset(path)
        from dlocli.env.shape_env import make_env_from_spec
        from dlocli.runs.collect import dataset_attrs

        env = make_env_from_spec(_env_spec(self.spec))
        episodes = []
        try:
            for e in range(self.spec.initial_episodes):
                episodes.append(random_data_episode(env, self.spec.seed, e))
                self.progress("initial", {"episode": e + 1, "total": self.spec.initial_episodes})
        finally:
            env.close()
        data = Dataset.from_episodes(episodes, dataset_attrs(_env_spec(self.spec)))
        data.save(path)
        return data

    def dataset_until(self, k: int) -> Dataset:
        """D after iteration k's trials (k = 0: the initial data)."""
        trials = [
            load_dataset(self.paths.trial(it, j))
            for it in range(1, k + 1)
            for j in range(1, self.spec.trials + 1)
        ]
        return load_dataset(self.paths.initial()).concat(*trials)  # one copy, not K·N

    # ------------------------------------------------------------------ steps of Alg. 1
    def update_model(self, k: int, data: Dataset) -> None:
        """Update the model on D (= D_{k-1}) from iteration k-1's weights and Adam state;
        checkpoint it as iteration k. Schedule "epochs": E passes over D (the paper's);
        "steps": a fixed number of steps, weighted to iteration k-1's trials (the last N
        episodes of D; for k = 1 all of D is new), seeded per iteration like the epochs."""
        import torch

        from dlocli.models.base import (
            build_model,
            load_model,
            read_checkpoint,
            resolve_device,
            save_checkpoint,
        )
        from dlocli.models.fitting import FitRecord
        from dlocli.models.update_steps import update_model

        if self.paths.checkpoint(k).is_file():
            return
        device = resolve_device(self.spec.fit.device)
        if k == 1:
            torch.manual_seed(stream_seed(self.spec.seed, TRAIN, 0))
            model, opt_state = build_model(self.spec.model, data.n_segments).to(device), None
        else:
            previous = self.paths.checkpoint(k - 1)
            model = load_model(previous, device).train()
            opt_state = read_checkpoint(previous).get("optimizer")
        fit = self.spec.fit.model_copy(
            update={"seed": stream_seed(self.spec.seed, TRAIN, k) % 2**31}
        )
        start = time.perf_counter()
        self.progress("update", {"iteration": k, "unit": fit.unit, "total": fit.length})

        def log(record: FitRecord, *_: Any) -> None:
            at = (k - 1) * fit.length + record.count  # over the run
            self.scalars.add(at, "loss", train=record.train_loss, val=record.val_loss)

        first_new = 0 if k == 1 else max(data.n_episodes - self.spec.trials, 0)
        with update_threads(self.spec):
            result = update_model(
                model,
                data,
                fit,
                recent_episodes=np.arange(first_new, data.n_episodes),
                optimizer_state=opt_state,
                progress=self._validations(k),
                on_validation=log,
            )
            threads = torch.get_num_threads()
        extra = {"steps": result.steps, "best_step": result.best_step} if result.steps else {}
        save_checkpoint(
            model,
            self.paths.checkpoint(k),
            {
                "optimizer": result.optimizer_state,
                "iteration": k,
                "val_loss": result.val_loss,
                "train_seconds": time.perf_counter() - start,
                "threads": threads,
                "device": str(device),
                **extra,
            },
        )

    def _validations(self, k: int) -> Callable[[Any], None]:
        """A fit's progress callback that reports its validations as iteration k's."""
        from dlocli.models.fitting import Validated

        def report(event: Any) -> None:
            if isinstance(event, Validated):
                self.progress("validation", {"iteration": k, **event.as_dict()})

        return report

    def run_trials(self, k: int, checkpoint: Path, offline: bool = False) -> None:
        """The N trials of iteration k; those whose files exist are kept, not rerun."""
        todo = [
            j
            for j in range(1, self.spec.trials + 1)
            if not self.paths.trial(k, j, offline).is_file()
        ]
        done = self.spec.trials - len(todo)
        self.progress("trials", {"iteration": k, "done": done, "total": self.spec.trials})
        if not todo:
            return
        spec_json = self.trial_spec().model_dump_json()
        model = self.executor.share(Path(checkpoint).read_bytes())
        calls = [(spec_json, model, k, j) for j in todo]
        for index, result in self.executor.map(_run_trial, calls):
            episode, attrs = _returned(result)
            j = todo[index]
            Dataset.from_episodes([episode], {**attrs, "iteration": k, "trial": j}).save(
                self.paths.trial(k, j, offline)
            )
            done += 1
            self.progress(
                "trial", {"iteration": k, "trial": done, "total": self.spec.trials, **attrs}
            )

    def trial_spec(self) -> OnlineSpec:
        """The spec the trials get: the model on the device the executor's calls may use
        (a Ray task sees no GPU: ``--device cuda`` updates the model on the driver's GPU,
        and the trials plan on their CPUs)."""
        device = self.executor.calls_device(self.spec.fit.device)
        if device == self.spec.fit.device:
            return self.spec
        fit = self.spec.fit.model_copy(update={"device": device})
        return self.spec.model_copy(update={"fit": fit})

    def run_references(self, k: int) -> None:
        """Doing nothing and random actions from the starts of iteration k's trials
        (:mod:`dlocli.runs.references`), shared among the trial workers; those already in
        the table are kept."""
        table = ReferenceTable(self.paths.references())
        missing = table.missing(k, self.spec.trials)
        if not missing:
            return
        self.progress("references", {"iteration": k, "total": len(missing)})
        spec_json = self.spec.model_dump_json()
        shares = [missing[w :: self.spec.workers] for w in range(self.spec.workers)]
        calls = [(spec_json, k, share) for share in shares if share]
        for _, result in self.executor.map(_reference_episodes, calls):
            for name, j, scores in _returned(result):
                table.add(name, k, j, scores)
        table.save()

    def offline_comparison(self, k: int, n_transitions: int) -> None:
        """Paper Fig. 7: a model trained from scratch on ``n_transitions`` random transitions."""
        import torch

        from dlocli.models.base import build_model, resolve_device, save_checkpoint
        from dlocli.models.update_steps import train_like_online

        ckpt = self.paths.checkpoint(k, offline=True)
        if not ckpt.is_file():
            data = self._random_data(k, n_transitions)
            torch.manual_seed(stream_seed(self.spec.seed, OFFLINE, k))
            model = build_model(self.spec.model, data.n_segments).to(
                resolve_device(self.spec.fit.device)
            )
            fit = self.spec.fit.model_copy(
                update={"seed": stream_seed(self.spec.seed, OFFLINE, k) % 2**31}
            )
            with update_threads(self.spec):
                train_like_online(  # as long as the online model had trained by iteration k
                    model, data, fit, k, progress=self._validations(k)
                )
            save_checkpoint(model, ckpt, {"iteration": k, "offline": 1})
        self.run_trials(k, ckpt, offline=True)

    def _random_data(self, k: int, n_transitions: int) -> Dataset:
        """Random episodes up to ``n_transitions`` (the initial data first, then more)."""
        path = self.paths.offline_data(k)
        if path.is_file():
            return load_dataset(path)
        from dlocli.env.shape_env import make_env_from_spec

        data = load_dataset(self.paths.initial())
        env = make_env_from_spec(_env_spec(self.spec))
        try:
            e = self.spec.initial_episodes
            while data.n_transitions < n_transitions:
                data = data.concat(
                    Dataset.from_episodes([random_data_episode(env, self.spec.seed, e)])
                )
                e += 1
        finally:
            env.close()
        data.save(path)
        return data

    # ------------------------------------------------------------------ driver
    def run(self) -> dict[str, Any]:
        """Run (or resume) to the end; ``seconds`` in the summary counts every part's time."""
        earlier = self.earlier_summary()
        start = time.perf_counter() - float(earlier.get("seconds") or 0.0)
        logged = len(earlier.get("curve") or [])  # iterations whose curves a run before wrote
        self.scalars = Scalars(self.spec.out)
        data = self.initial_dataset()
        try:
            for k in range(1, self.spec.iters + 1):
                self.progress("iteration", {"iteration": k, "total": self.spec.iters})
                self.update_model(k, data)
                self.run_trials(k, self.paths.checkpoint(k))
                self.run_references(k)
                data = self.dataset_until(k)
                if self.spec.offline:
                    self.offline_comparison(k, data.n_transitions)
                summary = self.write_results(time.perf_counter() - start)
                if k > logged:  # TensorBoard gets each iteration once across resumes
                    self.log_iteration(summary["curve"][k - 1])
                self.progress("iteration done", {"iteration": k, "total": self.spec.iters})
            return self.write_results(time.perf_counter() - start, final=True)
        except ClusterLost as lost:
            raise DloError(lost.line(self.spec.out)) from lost
        finally:
            self.scalars.close()
            if self._own_executor:
                self.executor.close()

    def earlier_summary(self) -> dict[str, Any]:
        """The summary the run wrote before it was stopped (empty for a new run)."""
        try:
            summary = json.loads((self.spec.out / "summary.json").read_text())
        except (OSError, ValueError):
            return {}
        return summary if isinstance(summary, dict) else {}

    def log_iteration(self, point: dict[str, Any]) -> None:
        self.scalars.add(
            point["transitions"],
            "trials",
            final_error_mm=point["final_error_mm_mean"],
            initial_error_mm=point["initial_error_mm_mean"],
            score=point["score_mean"],
            cumulative_reward=point["cumulative_reward_mean"],
        )

    # ------------------------------------------------------------------ results
    def rows(self, offline: bool = False) -> list[dict[str, Any]]:
        """One metrics row per finished trial, read back from the trial files."""
        rows, transitions = [], load_dataset(self.paths.initial()).n_transitions
        for k in range(1, self.spec.iters + 1):
            for j in range(1, self.spec.trials + 1):
                path = self.paths.trial(k, j, offline)
                if not path.is_file():
                    return rows
                data = load_dataset(path)
                transitions += data.n_transitions
                rows.append(
                    {
                        "iteration": k,
                        "trial": j,
                        "transitions": transitions if not offline else None,
                        # from the recorded episode: trial files of older runs lack the score
                        **episode_scores(data.episode(0), self.spec.task.episode_steps),
                        "trial_seconds": data.attrs["trial_seconds"],
                        "mpc_seconds": data.attrs.get("mpc_seconds"),  # older runs: none
                    }
                )
        return rows

    def train_seconds(self, k: int) -> float:
        """The time iteration k's model update took (0 before it is done); read once from
        its checkpoint, which never changes after it is written."""
        from dlocli.models.base import read_checkpoint

        if k not in self._train_seconds:
            path = self.paths.checkpoint(k)
            if not path.is_file():
                return 0.0
            self._train_seconds[k] = float(read_checkpoint(path).get("train_seconds", 0.0))
        return self._train_seconds[k]

    def time_shares(self, rows: list[dict[str, Any]]) -> dict[str, float | None]:
        """Seconds spent training the model, planning (MPC) and simulating (the rest of the
        trials: physics, resets), over every part of the run."""
        train = sum(self.train_seconds(k) for k in range(1, self.spec.iters + 1))
        timed = [r for r in rows if r["mpc_seconds"] is not None]
        mpc = sum(r["mpc_seconds"] for r in timed)
        simulation = sum(r["trial_seconds"] for r in timed) - mpc
        return {
            "train_seconds": round(train, 3),
            "mpc_seconds": round(mpc, 3) if timed else None,
            "simulation_seconds": round(simulation, 3) if timed else None,
        }

    def write_results(self, wall: float, final: bool = False) -> dict[str, Any]:
        from dlocli.plots import plot_learning_curve

        rows = self.rows()
        offline_rows = self.rows(offline=True) if self.spec.offline else []
        _write_csv(self.spec.out / "metrics.csv", rows)
        if offline_rows:
            _write_csv(self.spec.out / "offline_metrics.csv", offline_rows)
        curve = iteration_curve(rows)
        table = ReferenceTable(self.paths.references())
        for point in curve:
            for name in references():
                point.update(table.iteration(name, point["iteration"], self.spec.trials) or {})
        last = curve[-1] if curve else {}
        summary: dict[str, Any] = {
            "iterations_done": len(curve),
            "transitions": rows[-1]["transitions"] if rows else 0,
            "curve": curve,
            "initial_error_mm": curve[-1]["initial_error_mm_mean"] if curve else None,
            "final_error_mm": curve[-1]["final_error_mm_mean"] if curve else None,
            "score": curve[-1]["score_mean"] if curve else None,
            "cumulative_reward": curve[-1]["cumulative_reward_mean"] if curve else None,
            # the same starts and goals, doing nothing and random actions
            "zero_final_error_mm": last.get("zero_final_error_mm_mean"),
            "random_final_error_mm": last.get("random_final_error_mm_mean"),
            "seconds": round(wall, 1),
            **self.time_shares(rows),
            "reference_seconds": round(table.seconds(), 1),
            "out": str(self.spec.out),
        }
        if offline_rows:
            summary["offline_curve"] = iteration_curve(offline_rows, transitions_from=curve)
        if final and self.paths.checkpoint(len(curve)).is_file():
            import shutil

            final_ckpt = self.spec.out / "checkpoints" / "final.pt"
            tmp = final_ckpt.with_suffix(".pt.tmp")
            shutil.copyfile(self.paths.checkpoint(len(curve)), tmp)
            tmp.replace(final_ckpt)
        if curve:
            plot_learning_curve(
                curve, summary.get("offline_curve"), self.spec.out / "plots" / "learning_curve.png"
            )
        write_json_atomic(self.spec.out / "summary.json", summary)
        return summary


def iteration_curve(
    rows: list[dict[str, Any]], transitions_from: list[dict[str, Any]] | None = None
) -> list[dict[str, Any]]:
    """Per finished iteration: transitions, mean/std of cumulative reward and final error."""
    curve = []
    for k in sorted({r["iteration"] for r in rows}):
        its = [r for r in rows if r["iteration"] == k]
        rewards = np.array([r["cumulative_reward"] for r in its])
        errors = np.array([r["final_error_mm"] for r in its])
        scores = np.array([r["score"] for r in its])
        transitions = (
            transitions_from[k - 1]["transitions"]
            if transitions_from and len(transitions_from) >= k
            else its[-1]["transitions"]
        )
        curve.append(
            {
                "iteration": k,
                "trials": len(its),
                "transitions": transitions,
                "cumulative_reward_mean": float(rewards.mean()),
                "cumulative_reward_std": float(rewards.std()),
                "initial_error_mm_mean": float(np.mean([r["initial_error_mm"] for r in its])),
                "final_error_mm_mean": float(errors.mean()),
                "final_error_mm_median": float(np.median(errors)),
                "score_mean": float(scores.mean()),
                "score_std": float(scores.std()),
            }
        )
    return curve


def _returned(result: Any) -> Any:
    """An executor's result, raised if it is the error the call raised."""
    if isinstance(result, BaseException):
        raise result
    return result


def _write_csv(path: Path, rows: list[dict[str, Any]]) -> None:
    if not rows:
        return
    buffer = io.StringIO()
    writer = csv.DictWriter(buffer, fieldnames=list(rows[0]))
    writer.writeheader()
    writer.writerows(rows)
    write_text_atomic(path, buffer.getvalue())


# ----------------------------------------------------------------------------- entry points
def refuse_oversized_run(spec: OnlineSpec) -> None:
    """BadInput if the model or the datasets the run ends with would not fit in memory."""
    from dlocli.models.base import refuse_oversized_model

    n_segments = spec.backend.rod.n_segments
    refuse_oversized_model(spec.model, n_segments)
    episodes = spec.initial_episodes + spec.iters * spec.trials
    datasets = 2 if spec.offline else 1  # the offline model's random data is as large
    refuse_oversized_dataset(datasets * episodes, spec.task.episode_steps, n_segments)


def start_online(
    spec: OnlineSpec, overwrite: bool = False, progress: Progress | None = None
) -> dict[str, Any]:
    """A new run in ``spec.out``; with ``overwrite``, a previous run's state there is dropped
    first (its trials and checkpoints would otherwise be taken as this run's, as on resume)."""
    from dlocli.registry import backends, models, tasks

    backends.check(spec.backend.name)
    tasks.check(spec.task.name)
    models.check(spec.model.name)
    refuse_oversized_run(spec)
    check_executor(spec.executor, spec.ray_address)
    warn_if_threads_oversubscribe(spec)
    # the executor connects first: an address that fails leaves the directory as it was
    with open_executor(spec, job_threads(spec)) as executor, owned(spec.out):
        out = prepare_run_dir(spec.out, overwrite)
        for state in RunLayout(out).state_dirs():
            shutil.rmtree(state, ignore_errors=True)
        (out / "summary.json").unlink(missing_ok=True)  # its seconds would count as this run's
        RunLayout(out).references().unlink(missing_ok=True)
        write_json_atomic(out / "spec.json", spec.model_dump(mode="json"))
        record_fingerprints(out, spec)
        return OnlineRun(spec, progress, executor).run()


def resume_online(
    run_dir: Path,
    overrides: dict[str, Any],
    progress: Progress | None = None,
    accept_changes: bool = False,
) -> dict[str, Any]:
    """Continue the run in ``run_dir``; flags that contradict its spec are refused (but for
    where trials run: :data:`FREE_FIELDS`), and so is a changed spec.json or input file
    unless ``accept_changes``."""
    spec = resumed_run_spec(OnlineSpec, run_dir, overrides, "an online", "dlo online", FREE_FIELDS)
    refuse_oversized_run(spec)
    check_executor(spec.executor, spec.ray_address)
    warn_if_threads_oversubscribe(spec)
    with open_executor(spec, job_threads(spec)) as executor, owned(run_dir):
        check_fingerprints(run_dir, spec, accept_changes)
        adopt_written(run_dir, RunLayout.TOPS)  # a killed run's files are this run's
        if _changed_free_fields(run_dir, spec):  # the saved spec says where trials run now
            write_json_atomic(Path(run_dir) / "spec.json", spec.model_dump(mode="json"))
            record_fingerprints(run_dir, spec)
        return OnlineRun(spec, progress, executor).run()


def _changed_free_fields(run_dir: Path, spec: OnlineSpec) -> bool:
    saved = json.loads((Path(run_dir) / "spec.json").read_text())
    now = spec.model_dump(mode="json")
    return any(saved.get(name, now[name]) != now[name] for name in FREE_FIELDS)
