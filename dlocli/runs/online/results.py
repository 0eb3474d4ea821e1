"""What an online run reports: a metrics row per finished trial, the learning curve per
iteration, its references beside it, the time shares, and the files that hold them
(metrics.csv, summary.json, the plot, checkpoints/final.pt)."""

from __future__ import annotations

import csv
import io
import shutil
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

from dlocli.controllers.base import references
from dlocli.data import Dataset, load_dataset
from dlocli.env.rollout import episode_scores
from dlocli.io import write_json_atomic, write_text_atomic
from dlocli.plots import plot_learning_curve
from dlocli.runs.online.spec import OnlineSpec, RunLayout
from dlocli.runs.references import ReferenceTable


class TrialRecord(NamedTuple):
    """What a metrics row takes from one trial's data."""

    transitions: int
    scores: dict[str, float]
    trial_seconds: float
    mpc_seconds: float | None


def trial_record(data: Dataset, episode_steps: int) -> TrialRecord:
    return TrialRecord(
        data.n_transitions,
        # from the recorded episode: trial files of older runs lack the score
        episode_scores(data.episode(0), episode_steps),
        data.attrs["trial_seconds"],
        data.attrs.get("mpc_seconds"),  # older runs: none
    )


class OnlineResults:
    """The results of the run in ``spec.out``: each trial's record is kept from when it is
    written (or read once from its file, on resume), so a summary reads no trial again."""

    def __init__(self, spec: OnlineSpec) -> None:
        self.spec = spec
        self.paths = RunLayout(spec.out)
        self._records: dict[tuple[int, int, bool], TrialRecord] = {}
        self._initial_transitions: int | None = None
        self._train_seconds: dict[int, float] = {}

    def add_trial(self, k: int, j: int, data: Dataset, offline: bool = False) -> None:
        """Keep the record of trial j of iteration k (its file just written or read)."""
        self._records[(k, j, offline)] = trial_record(data, self.spec.task.episode_steps)

    def _record(self, k: int, j: int, offline: bool) -> TrialRecord | None:
        if (k, j, offline) not in self._records:
            path = self.paths.trial(k, j, offline)
            if not path.is_file():
                return None
            self.add_trial(k, j, load_dataset(path), offline)
        return self._records[(k, j, offline)]

    def initial_transitions(self) -> int:
        if self._initial_transitions is None:
            self._initial_transitions = load_dataset(self.paths.initial()).n_transitions
        return self._initial_transitions

    def rows(self, offline: bool = False) -> list[dict[str, Any]]:
        """One metrics row per finished trial, in order, up to the first one missing."""
        rows, transitions = [], self.initial_transitions()
        for k in range(1, self.spec.iters + 1):
            for j in range(1, self.spec.trials + 1):
                record = self._record(k, j, offline)
                if record is None:
                    return rows
                transitions += record.transitions
                rows.append(
                    {
                        "iteration": k,
                        "trial": j,
                        "transitions": transitions if not offline else None,
                        **record.scores,
                        "trial_seconds": record.trial_seconds,
                        "mpc_seconds": record.mpc_seconds,
                    }
                )
        return rows

    def train_seconds(self, k: int) -> float:
        """The time iteration k's model update took (0 before it is done); read once from
        its checkpoint, which never changes after it is written."""
        from dlocli.models.checkpoints import read_checkpoint

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

    def write(self, wall: float, final: bool = False) -> dict[str, Any]:
        """Write metrics, summary and plot of the trials finished so far; with ``final``
        also checkpoints/final.pt. The summary, returned."""
        out = self.spec.out
        rows = self.rows()
        offline_rows = self.rows(offline=True) if self.spec.offline else []
        write_csv(out / "metrics.csv", rows)
        if offline_rows:
            write_csv(out / "offline_metrics.csv", offline_rows)
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
            # the same starts and goals, doing nothing, random actions and the held-end servo
            "zero_final_error_mm": last.get("zero_final_error_mm_mean"),
            "random_final_error_mm": last.get("random_final_error_mm_mean"),
            "held_end_final_error_mm": last.get("held-end_final_error_mm_mean"),
            "seconds": round(wall, 1),
            **self.time_shares(rows),
            "reference_seconds": round(table.seconds(), 1),
            "out": str(out),
        }
        if offline_rows:
            summary["offline_curve"] = iteration_curve(offline_rows, transitions_from=curve)
        if final and self.paths.checkpoint(len(curve)).is_file():
            final_ckpt = out / "checkpoints" / "final.pt"
            tmp = final_ckpt.with_suffix(".pt.tmp")
            shutil.copyfile(self.paths.checkpoint(len(curve)), tmp)
            tmp.replace(final_ckpt)
        if curve:
            offline_curve = summary.get("offline_curve")
            plot_learning_curve(curve, offline_curve, out / "plots" / "learning_curve.png")
        write_json_atomic(out / "summary.json", summary)
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


def write_csv(path: Path, rows: list[dict[str, Any]]) -> None:
    if not rows:
        return
    buffer = io.StringIO()
    writer = csv.DictWriter(buffer, fieldnames=list(rows[0]))
    writer.writeheader()
    writer.writerows(rows)
    write_text_atomic(path, buffer.getvalue())
