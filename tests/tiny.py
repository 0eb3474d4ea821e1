"""Tiny settings the tests share, so every agent learns and every bench job runs in seconds
(the defaults are the paper's sizes). Budgets are 60 transitions of 20-step episodes."""

from __future__ import annotations

from typing import Any

#: options of the learning agents: small networks and GP, short horizons
TINY_AGENTS: dict[str, dict[str, Any]] = {
    "sac": {"net_arch": [16, 16], "batch_size": 8, "learning_starts": 20},
    "td3": {"net_arch": [16, 16], "batch_size": 8, "learning_starts": 20},
    "pilco": {
        "action_repeat": 2,
        "horizon": 3,
        "n_basis": 4,
        "gp_iterations": 10,
        "policy_iterations": 2,
        "max_gp_points": 15,
    },
}

#: a bench spec: three evaluation points of one episode each, one seed, one evaluation episode
TINY_BENCH: dict[str, Any] = {
    "task": {"episode_steps": 20, "reset_motion_steps": 10, "reset_settle_steps": 10},
    "model": {"hidden": 16, "lstm_layers": 1, "edge_layers": 2, "node_layers": 2},
    "fit": {"epochs": 2, "batch_size": 32, "device": "cpu"},
    "budget": 60,
    "evals": 3,
    "eval_trials": 1,
    "seeds": 1,
    "workers": 1,
    "options": TINY_AGENTS,
}
