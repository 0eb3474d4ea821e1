"""The learned dynamics as the tracker's prior: one step of a marker model
(:mod:`dlocli.models.marker_model`), the held nodes' next positions as its input.

Kept thin and apart so that it can follow the model to its marker view: only
:meth:`MarkerModelPrior.predict` knows how the model is called.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from dlocli.errors import BadInput
from dlocli.models.checkpoints import load_marker_model
from dlocli.models.marker_model import MarkerModel, neighbour_distances
from dlocli.tracking.priors import check_history


class MarkerModelPrior:
    """A trained marker model's next frame; ``held`` (M,) must be the model's held mask.

    Without the held nodes' next positions the model is given them at constant velocity.
    The neighbour distances of the latest frame are the ones the model keeps (its length
    projection, where its options ask for one)."""

    def __init__(self, model: MarkerModel, held: np.ndarray) -> None:
        held = np.asarray(held, dtype=bool)
        own = model.held.cpu().numpy()
        if own.shape != held.shape or not (own == held).all():
            raise BadInput(
                f"the marker model was trained on {len(own)} markers held as "
                f"{own.astype(int).tolist()}; the tracked nodes are held as "
                f"{held.astype(int).tolist()}: track the model's markers or retrain it"
            )
        self.model = model.eval()
        self.held = held

    @classmethod
    def load(cls, path: Path | str, held: np.ndarray) -> MarkerModelPrior:
        return cls(load_marker_model(path), held)

    @torch.no_grad()
    def predict(self, history: np.ndarray, held_next: np.ndarray | None) -> np.ndarray:
        history = check_history(history, len(self.held))
        last = history[-1]
        before = history[-2] if len(history) > 1 else last
        nxt = 2.0 * last - before  # the held rows when the robot does not say
        if held_next is not None:
            nxt[self.held] = np.asarray(held_next, dtype=np.float64).reshape(-1, 3)
        x, x_prev, held = (
            torch.as_tensor(a[None], dtype=torch.float32, device=self.model.device)
            for a in (last, before, nxt)
        )
        out = self.model(x, x_prev, held, neighbour_distances(x))
        return out[0].double().cpu().numpy()
