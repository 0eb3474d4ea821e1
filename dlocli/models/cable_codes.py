"""Cable codes: what a model learns per cable that the cable's shape does not tell.

Trained on several cables, one network must tell them apart, and the motion it is shown
(positions, velocities, the held markers' next step) does not tell a stiff heavy cable
from a soft light one of the same length: both hang and swing alike for a frame or two. So
a model with ``cable_code`` > 0 learns, beside its weights, one code vector per training
cable (an auto-decoder's latent: no encoder, the code is what gradient descent on that
cable's rollouts makes it). The code is given to the network as more per-marker inputs, the
same for every marker. Which code a cable gets is decided by its recordings (their content
key, :func:`cable_key`), never by a name: a cable the model trained on gets its own, a new
one the mean of them all until ``--init-from`` on its recordings learns one.

An ensemble's members train apart (:mod:`dlocli.models.member_fits`), so each learns its
own codes: an ensemble's codes are (cables, members, D), member i reads column i.

For a network of fully connected layers over the flattened inputs (``flat_layers``), a
constant input is a bias: :func:`fold_code` moves the code into the first layer's bias, so
the fused rollout trains and runs a coded model unchanged.
"""

from __future__ import annotations

import hashlib

import numpy as np
import torch
from torch import Tensor


def cable_key(held: np.ndarray, episodes: list[np.ndarray]) -> str:
    """A cable's key: a hash of its held mask and training recordings (16 hex digits)."""
    digest = hashlib.sha256(np.asarray(held, dtype=bool).tobytes())
    for episode in episodes:
        digest.update(np.ascontiguousarray(episode, dtype=np.float32).tobytes())
    return digest.hexdigest()[:16]


def no_codes(width: int, members: int = 1) -> Tensor:
    """The codes of a model that has trained on no cable yet: (0, D), an ensemble's
    (0, members, D)."""
    return torch.zeros(0, width) if members == 1 else torch.zeros(0, members, width)


def grown(codes: Tensor, rows: int) -> Tensor:
    """``codes`` (N, ...) with rows added up to ``rows``, each new one the mean of the old
    (zero where there are none): a new cable starts where an unseen one would."""
    if rows <= codes.shape[0]:
        return codes
    start = chosen_code(codes, None)
    extra = start.expand(rows - codes.shape[0], *start.shape)
    return torch.cat([codes.detach(), extra.detach()], 0)


def chosen_code(codes: Tensor, index: int | None) -> Tensor:
    """Row ``index`` of ``codes``, or their mean for None (a cable not trained on); zeros
    when there are none yet."""
    if index is not None:
        return codes[index]
    return codes.mean(0) if codes.shape[0] else codes.new_zeros(codes.shape[1:])


def with_code(features: Tensor, code: Tensor) -> Tensor:
    """Per-marker features (B, V, F) with the code (D,) appended to every marker's; with an
    ensemble's codes (M, D), the (M, B, V, F + D) inputs of each member."""
    if code.dim() == 1:
        return torch.cat([features, code.expand(*features.shape[:2], -1)], -1)
    per_member = code[:, None, None].expand(-1, *features.shape[:2], -1)
    return torch.cat([features.expand(code.shape[0], *features.shape), per_member], -1)


def fold_code(
    layers: list[tuple[Tensor, Tensor]], count: int, features: int, code: Tensor
) -> list[tuple[Tensor, Tensor]]:
    """Fully connected ``layers`` over ``count`` markers of ``features`` + code inputs each
    (flattened marker by marker) as layers over the ``features`` alone: the code's columns
    times the code, summed over the markers, join the first bias (gradients reach both)."""
    weight, bias = layers[0]
    per_marker = weight.view(weight.shape[0], count, features + code.shape[0])
    bias = bias + per_marker[:, :, features:].sum(1) @ code
    weight = per_marker[:, :, :features].reshape(weight.shape[0], count * features)
    return [(weight, bias), *layers[1:]]
