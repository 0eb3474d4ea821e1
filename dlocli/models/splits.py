"""The train/validation split by trajectory, shared by every training loop."""

from __future__ import annotations

import numpy as np

GOLDEN = 0.6180339887498949  # episode e is validation iff frac((e + 1) * GOLDEN) < fraction


def split_episodes(n_episodes: int, val_fraction: float) -> tuple[np.ndarray, ...]:
    """(train, validation) episode indices, stable as episodes are appended.

    Episode e is held out iff frac((e + 1) * golden ratio) < val_fraction: a low-discrepancy
    rule, so about ``val_fraction`` of any prefix is held out, and an episode never changes
    side as the dataset grows (whatever the training seed). With at least two episodes and a
    positive fraction, one is always held out and one always trained on.
    """
    e = np.arange(n_episodes)
    is_val = (((e + 1) * GOLDEN) % 1.0) < val_fraction
    if val_fraction > 0 and n_episodes >= 2:
        if not is_val.any():
            is_val[-1] = True
        if is_val.all():
            is_val[0] = False
    return e[~is_val], e[is_val]
