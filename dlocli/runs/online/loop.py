"""Algorithm 1 over a run directory (:class:`OnlineRun`): the initial data, then per iteration
a model update, the trials, the references, and results; resumable at every step.

The loop keeps D in memory and appends each iteration's trials to it; the trials get the
model's checkpoint as bytes, loaded in memory where they run."""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Any

import numpy as np

import dlocli.runs.online.trials as trials
from dlocli.cancel import CancelToken
from dlocli.controllers.rest_roll import rest_states
from dlocli.data import Dataset, load_dataset
from dlocli.env.rollout import stream_seed
from dlocli.env.shape_env import make_env_from_spec
from dlocli.env.tasks import make_task
from dlocli.errors import DloError
from dlocli.events import Began, Callback, Event, ignore
from dlocli.executors import ClusterLost, LocalExecutor
from dlocli.runs.collect import dataset_attrs
from dlocli.runs.online.results import OnlineResults
from dlocli.runs.online.spec import (
    OFFLINE,
    TRAIN,
    OnlineSpec,
    RunLayout,
    job_threads,
    update_threads,
)
from dlocli.runs.references import ReferenceTable
from dlocli.tensorboard import Scalars


class OnlineRun:
    """Algorithm 1 over a run directory; :meth:`run` can be called again to resume."""

    def __init__(
        self,
        spec: OnlineSpec,
        progress: Callback | None = None,
        executor: Any = None,
        cancel: CancelToken | None = None,
    ) -> None:
        """``executor``: where trials run (:mod:`dlocli.executors`), connected; None: the
        local processes of ``spec.workers``, ended with :meth:`run`. ``progress`` gets the
        iterations, the random episodes ("random"), each update's fit (its start and
        validations, in epochs or steps) and the trials, as :class:`~dlocli.events.Event`;
        ``cancel`` stops the updates between gradient steps and the envs of this process
        between physics steps (a trial in another process ends with it)."""
        self.spec = spec
        self.paths = RunLayout(spec.out)
        self.results = OnlineResults(spec)
        self.progress = progress or ignore
        self.cancel = cancel
        self._own_executor = executor is None
        self.executor = executor or LocalExecutor(spec.workers, job_threads(spec))
        self.scalars = Scalars(None)

    # ------------------------------------------------------------------ data
    def initial_dataset(self) -> Dataset:
        """Collect (or reload) the initial random dataset D_0."""
        path = self.paths.initial()
        if path.is_file():
            return load_dataset(path)

        env = make_env_from_spec(trials.env_spec(self.spec), cancel=self.cancel)
        episodes = []
        try:
            for e in range(self.spec.initial_episodes):
                episodes.append(trials.random_data_episode(env, self.spec.seed, e))
                self.progress(Event("random", e + 1, self.spec.initial_episodes))
        finally:
            env.close()
        data = Dataset.from_episodes(episodes, dataset_attrs(trials.env_spec(self.spec)))
        data.save(path)
        return data

    def dataset_until(self, k: int) -> Dataset:
        """D after iteration k's trials (k = 0: the initial data), read from the run's files
        (for a caller that does not hold D, like the bench's learner after a resume)."""
        found = [
            load_dataset(self.paths.trial(it, j))
            for it in range(1, k + 1)
            for j in range(1, self.spec.trials + 1)
        ]
        return load_dataset(self.paths.initial()).concat(*found)  # one copy, not K·N

    # ------------------------------------------------------------------ steps of Alg. 1
    def update_model(self, k: int, data: Dataset) -> None:
        """Update the model on D (= D_{k-1}) from iteration k-1's weights and Adam state;
        checkpoint it as iteration k. Schedule "epochs": E passes over D (the paper's);
        "steps": a fixed number of steps, weighted to iteration k-1's trials (the last N
        episodes of D; for k = 1 all of D is new), seeded per iteration like the epochs."""
        import torch

        from dlocli.models.base import build_model, resolve_device
        from dlocli.models.checkpoints import (
            REST_STATES,
            load_model,
            read_checkpoint,
            save_checkpoint,
        )
        from dlocli.models.update_steps import update_model

        if self.paths.checkpoint(k).is_file():
            return
        if self.spec.task.observation.reports_markers:
            self.update_marker_model(k, data)
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
        first_new = 0 if k == 1 else max(data.n_episodes - self.spec.trials, 0)
        with update_threads(self.spec):
            result = update_model(
                model,
                data,
                fit,
                recent_episodes=np.arange(first_new, data.n_episodes),
                optimizer_state=opt_state,
                progress=self._validations(at=(k - 1) * fit.length),
                cancel=self.cancel,
            )
            threads = torch.get_num_threads()
        extra = {"steps": result.steps, "best_step": result.best_step} if result.steps else {}
        extra[REST_STATES] = self.rest_states(data)
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
                "control_dt": self.spec.task.control_dt,
                **extra,
            },
        )

    def rest_states(self, data: Dataset) -> dict[str, Any]:
        """Where the rod came to rest in ``data`` (:mod:`dlocli.controllers.rest_roll`), as
        tensors for the checkpoint: the planner's ``rest_roll`` reads the roll from them."""
        import torch

        moving = make_task(self.spec.task.name).moving
        found = rest_states(data, moving, self.spec.task.control_dt)
        return {name: torch.from_numpy(array) for name, array in found.items()}

    def update_marker_model(self, k: int, data: Dataset) -> None:
        """The update of the marker form (the markers observation,
        :mod:`dlocli.runs.online.marker_update`): ``fit.update_steps`` steps from iteration k-1's
        weights; checkpointed as iteration k."""
        import torch

        from dlocli.models.base import resolve_device
        from dlocli.models.checkpoints import load_marker_model, save_checkpoint
        from dlocli.models.fitting import RolloutValidated
        from dlocli.runs.online.marker_update import new_marker_model, update_marker_model

        if k == 1:
            torch.manual_seed(stream_seed(self.spec.seed, TRAIN, 0))
            model = new_marker_model(self.spec)
        else:
            model = load_marker_model(self.paths.checkpoint(k - 1))
        fit = self.spec.fit.model_copy(
            update={"seed": stream_seed(self.spec.seed, TRAIN, k) % 2**31}
        )
        start = time.perf_counter()

        def report(event: Event) -> None:
            if isinstance(event, RolloutValidated):
                self.scalars.add((k - 1) * fit.update_steps + int(event.done), "loss",
                                 train=event.values["train_loss"],
                                 val=event.values["val_loss"])  # fmt: skip
            if isinstance(event, Began | RolloutValidated):
                self.progress(event)

        with update_threads(self.spec):
            result = update_marker_model(model, data, self.spec, fit, report, self.cancel)
            threads = torch.get_num_threads()
        best = result.best_val_loss  # the best validation score (cm)
        save_checkpoint(model, self.paths.checkpoint(k), {
            "iteration": k, "val_score_cm": best, "threads": threads,
            "train_seconds": time.perf_counter() - start,
            "device": str(resolve_device(self.spec.fit.device)),
            "control_dt": self.spec.task.control_dt,
        })  # fmt: skip

    def _validations(self, at: int | None = None) -> Callback:
        """A fit's progress callback that passes on its start and validations (not its
        batches); from an update whose count starts ``at`` over the run, it also logs each
        validation's losses."""
        from dlocli.models.fitting import Validated

        def report(event: Event) -> None:
            if isinstance(event, Began | Validated):
                self.progress(event)
            # a step fit's validations (a rollout fit's carry k; the stop repeats the last)
            if at is not None and type(event) is Validated and not event.values["stopped_early"]:
                values = event.values
                self.scalars.add(at + event.done, "loss", train=values["train_loss"],
                                 val=values["val_loss"])  # fmt: skip

        return report

    def run_trials(self, k: int, checkpoint: Path, offline: bool = False) -> list[Dataset]:
        """The N trials of iteration k, each as its one-episode dataset, in order; those
        whose files exist are read, not rerun."""
        found = {}
        for j in range(1, self.spec.trials + 1):
            path = self.paths.trial(k, j, offline)
            if path.is_file():
                found[j] = load_dataset(path)
                self.results.add_trial(k, j, found[j], offline)
        todo = [j for j in range(1, self.spec.trials + 1) if j not in found]
        done = len(found)
        self.progress(Began("trial", done, self.spec.trials))
        if todo:
            spec_json = self.trial_spec().model_dump_json()
            model = self.executor.share(Path(checkpoint).read_bytes())
            calls = [(spec_json, model, k, j, self.cancel) for j in todo]
            for index, result in self.executor.map(trials.run_trial, calls):
                episode, attrs = trials.returned(result)
                j = todo[index]
                found[j] = Dataset.from_episodes([episode], {**attrs, "iteration": k, "trial": j})
                found[j].save(self.paths.trial(k, j, offline))
                self.results.add_trial(k, j, found[j], offline)
                done += 1
                self.progress(Event("trial", done, self.spec.trials, {"iteration": k, **attrs}))
        return [found[j] for j in range(1, self.spec.trials + 1)]

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
        spec_json = self.spec.model_dump_json()
        shares = [missing[w :: self.spec.workers] for w in range(self.spec.workers)]
        calls = [(spec_json, k, share, self.cancel) for share in shares if share]
        for _, result in self.executor.map(trials.reference_episodes, calls):
            for name, j, scores in trials.returned(result):
                table.add(name, k, j, scores)
        table.save()

    def offline_comparison(self, k: int, n_transitions: int) -> None:
        """Paper Fig. 7: a model trained from scratch on ``n_transitions`` random transitions."""
        import torch

        from dlocli.models.base import build_model, resolve_device
        from dlocli.models.checkpoints import save_checkpoint
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
                    model, data, fit, k, progress=self._validations(), cancel=self.cancel
                )
            save_checkpoint(model, ckpt, {"iteration": k, "offline": 1,
                                          "control_dt": self.spec.task.control_dt})  # fmt: skip
        self.run_trials(k, ckpt, offline=True)

    def _random_data(self, k: int, n_transitions: int) -> Dataset:
        """Random episodes up to ``n_transitions`` (the initial data first, then more)."""
        path = self.paths.offline_data(k)
        if path.is_file():
            return load_dataset(path)

        data = load_dataset(self.paths.initial())
        env = make_env_from_spec(trials.env_spec(self.spec), cancel=self.cancel)
        try:
            e = self.spec.initial_episodes
            while data.n_transitions < n_transitions:
                data = data.concat(
                    Dataset.from_episodes([trials.random_data_episode(env, self.spec.seed, e)])
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
                self.progress(Event("iteration", k - 1, self.spec.iters, {"running": k}))
                self.update_model(k, data)
                new = self.run_trials(k, self.paths.checkpoint(k))
                self.run_references(k)
                data = data.concat(*new)
                if self.spec.offline:
                    self.offline_comparison(k, data.n_transitions)
                summary = self.results.write(time.perf_counter() - start)
                if k > logged:  # TensorBoard gets each iteration once across resumes
                    self.log_iteration(summary["curve"][k - 1])
                self.progress(Event("iteration", k, self.spec.iters))
            return self.results.write(time.perf_counter() - start, final=True)
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
