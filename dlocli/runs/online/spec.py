"""The spec of `dlo online` and what follows from it alone: the thread policy, the seed
streams and where each file of a run lives."""

from __future__ import annotations

from contextlib import AbstractContextManager, nullcontext
from pathlib import Path
from typing import ClassVar

from pydantic import Field, ValidationInfo, model_validator

from dlocli.controllers.specs import (
    PlannerName,
    PlannerOptions,
    planner_name_field,
    planner_options_field,
)
from dlocli.executors import ExecutorChoice
from dlocli.limits import MAX_CLUSTER_WORKERS, MAX_COUNT, MAX_PROCESSES
from dlocli.models.spec import ModelField, UpdateSpec, model_field
from dlocli.rundir import FINGERPRINTS_FILE
from dlocli.specs import MODEL_OPTIONS, EnvSpec, is_given
from dlocli.tensorboard import TENSORBOARD_DIR
from dlocli.threads import torch_threads, warn_if_oversubscribed


class OnlineSpec(EnvSpec, ExecutorChoice):
    """`dlo online`: Algorithm 1 of the paper. Defaults are the paper's parameters. Its jobs
    are the trials and reference episodes; the model update stays in this process."""

    moved: ClassVar[dict[str, str]] = {"steps": "task.episode_steps"}
    cli_flags: ClassVar[tuple[str, ...]] = (
        "iters", "trials", "task.episode_steps", "fit.schedule", "fit.epochs", "fit.update_steps",
        "initial_episodes", "planner", "mpc.horizon", "mpc.settle_steps", "mpc.motion_cost",
        "mpc.servo_cost", "mpc.roll_search", "mpc.servo_above_mm", "mpc.rest_roll", "fit.lr",
        MODEL_OPTIONS, "task.goal", "task.name", "task.shapes", "backend.name", "fit.device",
        "noise_probability", "noise_std", "workers", "threads", "executor", "ray_address",
        "fit.mirror", "offline",
        "seed", "out", "task.observation.kind", "task.observation.markers",
        "task.observation.noise_mm", "task.observation.latency_steps", "task.observation.dropout",
        "task.observation.occlusion_probability", "fit.rollout_steps",
    )  # fmt: skip

    iters: int = Field(
        20, gt=0, le=MAX_COUNT, description="Iterations K of model update + MPC trials."
    )
    trials: int = Field(50, gt=0, le=MAX_COUNT, description="MPC trials N per iteration.")
    initial_episodes: int = Field(
        10,
        gt=1,
        le=MAX_COUNT,
        description="Random-action episodes (of T steps) in the initial dataset D; at least 2: "
        "the first model update holds one out for validation and trains on the rest.",
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
        1, gt=0, le=MAX_CLUSTER_WORKERS,
        description="Processes running an iteration's trials (at most one per CPU); with "
        "--executor ray and no --ray-address, the CPUs of the local Ray instance; with "
        "--ray-address, at most the cluster's CPUs.",
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

    @model_validator(mode="after")
    def _offline_needs_full(self) -> OnlineSpec:
        if self.offline and self.task.observation.reports_markers:
            raise ValueError("--offline compares rod models: drop it with --observation markers")
        return self

    @model_validator(mode="after")
    def _marker_updates_count_steps(self, info: ValidationInfo) -> OnlineSpec:
        # a marker model trains through rollouts, counted in gradient steps: epochs would be
        # silently ignored (saved runs load as saved)
        fit = self.fit
        if (self.task.observation.reports_markers and fit.schedule == "epochs"
                and "epochs" in fit.model_fields_set and is_given(info)):  # fmt: skip
            raise ValueError(
                "--epochs: a marker model's update counts gradient steps, not epochs; give "
                "--schedule steps --update-steps N instead"
            )
        return self


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
#: the seed streams of a run (:func:`dlocli.env.rollout.stream_seed`): the initial random
#: data, each model update, each trial's reset and planner, its action noise, the models
#: trained offline, the reference episodes
INITIAL, TRAIN, TRIAL, NOISE, OFFLINE, REFERENCE = 0, 1, 2, 3, 4, 5


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
