"""`dlo online`'s entry points: start a run, or resume one, after the same checks."""

from __future__ import annotations

import json
import shutil
from pathlib import Path
from typing import Any

from dlocli.cancel import CancelToken
from dlocli.events import Callback
from dlocli.executors import check_executor, open_executor
from dlocli.io import adopt_written, prepare_run_dir, write_json_atomic
from dlocli.limits import refuse_oversized_dataset
from dlocli.resume import resumed_run_spec
from dlocli.rundir import check_fingerprints, owned, record_fingerprints
from dlocli.runs.checks import check_registered
from dlocli.runs.online.loop import OnlineRun
from dlocli.runs.online.spec import (
    FREE_FIELDS,
    OnlineSpec,
    RunLayout,
    job_threads,
    warn_if_threads_oversubscribe,
)


def refuse_oversized_run(spec: OnlineSpec) -> None:
    """BadInput if the model or the datasets the run ends with would not fit in memory."""
    from dlocli.models.base import refuse_oversized_model

    n_segments = spec.backend.rod.n_segments
    refuse_oversized_model(spec.model, n_segments)
    episodes = spec.initial_episodes + spec.iters * spec.trials
    datasets = 2 if spec.offline else 1  # the offline model's random data is as large
    refuse_oversized_dataset(datasets * episodes, spec.task.episode_steps, n_segments)


def check_online(spec: OnlineSpec) -> None:
    """What a run must pass to start or resume: registered names, sizes that fit, an
    executor that can run here (BadInput); a warning if --threads oversubscribes."""
    check_registered(spec)
    refuse_oversized_run(spec)
    check_executor(spec.executor, spec.ray_address)
    warn_if_threads_oversubscribe(spec)


def start_online(
    spec: OnlineSpec,
    overwrite: bool = False,
    progress: Callback | None = None,
    cancel: CancelToken | None = None,
) -> dict[str, Any]:
    """A new run in ``spec.out``; with ``overwrite``, a previous run's state there is dropped
    first (its trials and checkpoints would otherwise be taken as this run's, as on resume)."""
    check_online(spec)
    # the executor connects first: an address that fails leaves the directory as it was
    with open_executor(spec, job_threads(spec)) as executor, owned(spec.out):
        out = prepare_run_dir(spec.out, overwrite)
        for state in RunLayout(out).state_dirs():
            shutil.rmtree(state, ignore_errors=True)
        (out / "summary.json").unlink(missing_ok=True)  # its seconds would count as this run's
        RunLayout(out).references().unlink(missing_ok=True)
        write_json_atomic(out / "spec.json", spec.model_dump(mode="json"))
        record_fingerprints(out, spec)
        return OnlineRun(spec, progress, executor, cancel).run()


def resume_online(
    run_dir: Path,
    overrides: dict[str, Any],
    progress: Callback | None = None,
    accept_changes: bool = False,
    cancel: CancelToken | None = None,
) -> dict[str, Any]:
    """Continue the run in ``run_dir``; flags that contradict its spec are refused (but for
    where trials run: :data:`~dlocli.runs.online.spec.FREE_FIELDS`), and so is a changed
    spec.json or input file unless ``accept_changes``."""
    spec = resumed_run_spec(OnlineSpec, run_dir, overrides, "an online", "dlo online", FREE_FIELDS)
    check_online(spec)
    with open_executor(spec, job_threads(spec)) as executor, owned(run_dir):
        check_fingerprints(run_dir, spec, accept_changes)
        adopt_written(run_dir, RunLayout.TOPS)  # a killed run's files are this run's
        if _changed_free_fields(run_dir, spec):  # the saved spec says where trials run now
            write_json_atomic(Path(run_dir) / "spec.json", spec.model_dump(mode="json"))
            record_fingerprints(run_dir, spec)
        return OnlineRun(spec, progress, executor, cancel).run()


def _changed_free_fields(run_dir: Path, spec: OnlineSpec) -> bool:
    saved = json.loads((Path(run_dir) / "spec.json").read_text())
    now = spec.model_dump(mode="json")
    return any(saved.get(name, now[name]) != now[name] for name in FREE_FIELDS)
