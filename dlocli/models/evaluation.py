"""How good is a learned model: one-step and open-loop errors next to "nothing moves".

Errors are in millimetres: the mean over segments of the Euclidean distance between the
predicted and the true segment centre (the shape error of docs/concepts.md). The H-step error is
the error of the state predicted H steps ahead from a true start state, feeding the model its
own predictions and the recorded actions (open loop). The persistence baseline predicts that
nothing moves (s_{t+k} = s_t); a useful model beats it by far.
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from typing import Any

import numpy as np
import torch

from dlocli.data import Dataset
from dlocli.models.base import DynamicsModel

HORIZONS = (5, 50)
ROLL_BATCH = 256


def position_error_mm(pred: np.ndarray, true: np.ndarray) -> np.ndarray:
    """(..., N, >=3) states -> (...) mean over segments of the position error, millimetres."""
    return 1000.0 * np.linalg.norm(pred[..., :3] - true[..., :3], axis=-1).mean(-1)


@torch.no_grad()
def predict(
    model: DynamicsModel, state: np.ndarray, actions: np.ndarray, previous: np.ndarray
) -> np.ndarray:
    """Open-loop rollout in batches: (S, N, 7), (S, H, 2, 6), previous states (S, N, 7) ->
    (S, H, N, 7) numpy."""
    out = []

    def tensor(array: np.ndarray, i: int) -> torch.Tensor:
        return torch.as_tensor(array[i : i + ROLL_BATCH], dtype=torch.float32, device=model.device)

    for i in range(0, len(state), ROLL_BATCH):
        rolled = model.rollout(tensor(state, i), tensor(actions, i), tensor(previous, i))
        out.append(rolled.cpu().numpy())
    n, h = actions.shape[:2]
    return np.concatenate(out) if out else np.zeros((0, h, model.n_segments, 7), np.float32)


def rollout_starts(dataset: Dataset, episodes: np.ndarray, horizon: int, max_starts: int) -> list:
    """(episode, t) start pairs with 1 <= t and t + horizon <= T_e (every start has a recorded
    previous state), evenly thinned to ``max_starts``."""
    lengths = dataset.episode_lengths
    pairs = [(int(e), t) for e in episodes for t in range(1, int(lengths[e]) - horizon + 1)]
    if len(pairs) > max_starts:
        keep = np.linspace(0, len(pairs) - 1, max_starts).round().astype(int)
        pairs = [pairs[k] for k in keep]
    return pairs


def windows(dataset: Dataset, starts: list, horizon: int) -> tuple[np.ndarray, ...]:
    """States (S, N, 7), actions (S, H, 2, 6), true future states (S, H, N, 7) and previous
    states (S, N, 7; the start state itself where t = 0)."""
    states = dataset.states()
    s_off, a_off = dataset.state_offsets(), dataset.action_offsets()
    s_idx = np.array([s_off[e] + t for e, t in starts], dtype=np.int64).reshape(-1, 1)
    a_idx = np.array([a_off[e] + t for e, t in starts], dtype=np.int64).reshape(-1, 1)
    prev_idx = np.array([s_off[e] + max(t - 1, 0) for e, t in starts], dtype=np.int64)
    steps = np.arange(horizon)
    start = states[s_idx[:, 0]]
    return start, dataset.actions[a_idx + steps], states[s_idx + 1 + steps], states[prev_idx]


def evaluate_model(
    model: DynamicsModel,
    dataset: Dataset,
    episodes: np.ndarray | None = None,
    horizons: tuple[int, ...] = HORIZONS,
    max_starts: int = 512,
) -> dict[str, Any]:
    """One-step and H-step errors (mm) of ``model`` and of persistence on ``episodes``.

    Keys: ``one_step_mm``, ``rollout{H}_mm``, ``persistence_one_step_mm``,
    ``persistence_rollout{H}_mm`` (None where no episode is long enough), plus the counts
    ``eval_episodes``, ``eval_transitions``. At most ``max_starts`` evenly spread start
    states per horizon (all transitions for the one-step error).
    """
    result: dict[str, Any] = {}
    for _, measured in evaluation_parts(model, dataset, episodes, horizons, max_starts):
        result.update(measured)
    return result


def evaluation_parts(
    model: DynamicsModel,
    dataset: Dataset,
    episodes: np.ndarray | None = None,
    horizons: tuple[int, ...] = HORIZONS,
    max_starts: int = 512,
) -> Iterator[tuple[str, dict[str, Any]]]:
    """:func:`evaluate_model` one measurement at a time: ("one step", the counts and the
    one-step errors), then ("H steps", the H-step errors) per horizon; a caller may stop
    between them (``dlo eval``'s cancel) and keep what was measured."""
    episodes = np.arange(dataset.n_episodes) if episodes is None else np.asarray(episodes)
    model.eval()
    tr = dataset.transitions(episodes, skip_first=True)
    result: dict[str, Any] = {
        "eval_episodes": len(episodes),
        "eval_transitions": len(tr["state"]),
    }
    pred = predict(model, tr["state"], tr["action"][:, None], tr["previous_state"])[:, 0]
    result["one_step_mm"] = _mean(position_error_mm(pred, tr["next_state"]))
    result["persistence_one_step_mm"] = _mean(position_error_mm(tr["state"], tr["next_state"]))
    yield "one step", result
    for h in horizons:
        starts = rollout_starts(dataset, episodes, h, max_starts)
        state, actions, truth, previous = windows(dataset, starts, h)
        final = predict(model, state, actions, previous)[:, -1] if starts else state
        errors = {
            f"rollout{h}_mm": _mean(position_error_mm(final, truth[:, -1])) if starts else None,
            f"persistence_rollout{h}_mm": (
                _mean(position_error_mm(state, truth[:, -1])) if starts else None
            ),
        }
        yield f"{h} steps", errors


def _mean(values: np.ndarray) -> float | None:
    return float(np.mean(values)) if len(values) and not math.isnan(np.mean(values)) else None
