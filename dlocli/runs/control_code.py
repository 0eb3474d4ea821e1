"""The cable's code while `dlo control` plans (a marker model with cable codes).

``--cable DATA`` plans with the code the model learned for that recorded cable
(:func:`use_cable_code`); ``--adapt-code`` infers it while the cable moves
(:class:`CodeAdapting`, :mod:`dlocli.models.code_follow`): the mean code first, then every
``adapt_every`` steps the trained cable's code, or their mean, that best predicts the last
``adapt_window`` observed frames. A network that serves any marker count plans with the
markers the task observes (:func:`observe_with`), so a model trained on several cables
controls any of them.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import numpy as np

from dlocli.controllers.base import Controller
from dlocli.data import load_dataset
from dlocli.env.observation import held_markers
from dlocli.env.shape_env import DLOShapeEnv
from dlocli.errors import BadInput

if TYPE_CHECKING:
    from dlocli.runs.control import ControlSpec


def use_cable_code(model: Any, spec: ControlSpec) -> None:
    """Plan with the code ``model`` learned for ``spec.cable``; BadInput where it has no
    codes, the file is no marker dataset, or it never trained on that cable."""
    if spec.cable is None:
        return
    if not getattr(model.spec, "cable_code", 0):
        raise BadInput(f"model {spec.checkpoint} learned no cable codes: drop --cable")
    dataset = load_dataset(spec.cable)
    if dataset.form != "markers":
        raise BadInput(f"--cable {spec.cable} is not a marker dataset: pass one from `dlo import`")
    if model.use_recorded_cable(dataset.held, dataset.episodes("train")) is None:
        raise BadInput(
            f"model {spec.checkpoint} never trained on --cable {spec.cable}: give it a code "
            f"with `dlo adapt --checkpoint {spec.checkpoint} --data {spec.cable}`, or drop "
            "--cable to plan with the mean code"
        )


def check_adapt_code(model: Any, spec: ControlSpec) -> None:
    """BadInput where ``spec.adapt_code`` has no codes to pick from: a rod model, or a marker
    model that learned no cable codes."""
    if not spec.adapt_code:
        return
    if getattr(model, "form", "rod") != "markers":
        raise BadInput(
            f"--adapt-code picks a marker model's cable code, but model {spec.checkpoint} is a "
            "rod model: drop --adapt-code"
        )
    if not getattr(model.spec, "cable_code", 0) or not model.cable_keys:
        raise BadInput(
            f"model {spec.checkpoint} learned no cable codes, so there is none to pick: drop "
            "--adapt-code, or train one on several cables with --cable-code D"
        )


def observe_with(model: Any, env: DLOShapeEnv) -> None:
    """A marker model with the codes of several cables whose network serves any marker count
    (``arc-mlp``, ``attention``, ``in-bilstm``) holds its first cable's held mask: it takes
    the mask of the markers ``env`` observes (DLO1 has 13, DLO2-4 12). Any other model is
    checked by its view: trained on one layout, it plans on that one."""
    layout = getattr(env, "marker_layout", None)
    if layout is None or getattr(model, "form", "rod") != "markers":
        return
    several = len(getattr(model, "cable_keys", [])) > 1 and model.network.any_count
    if several and not np.array_equal(model.held.cpu().numpy(), layout.held):
        model.held = model.held.new_tensor(layout.held)


def code_follower(model: Any, spec: ControlSpec) -> Any:
    """The :class:`~dlocli.models.code_follow.CodeFollower` of ``spec``'s adapt fields, its
    candidates named by the datasets ``model`` trained on, where still readable."""
    from dlocli.models.code_follow import CodeFollower
    from dlocli.models.code_pick import cable_names

    assert spec.checkpoint is not None
    names = cable_names(spec.checkpoint, model.cable_keys)
    return CodeFollower(model, names, spec.adapt_every, spec.adapt_window)


class CodeAdapting:
    """``controller``, planning with a marker model whose code ``follower`` re-picks from the
    markers it observes in ``env`` (:mod:`dlocli.models.code_follow`): what the tracker
    reported of each frame, the held markers where the grippers put them then (the robot
    knows its poses; the report is ``latency_steps`` old), a hidden marker where it was last
    seen. Its ``last_stats`` add the code in use (``code``) and a re-pick's time
    (``code_pick_ms``); anything else is the controller's."""

    def __init__(self, controller: Controller, env: DLOShapeEnv, follower: Any) -> None:
        self.controller, self.env, self.follower = controller, env, follower
        self.latency = env.task_spec.observation.latency_steps
        self.reset_feed()

    def __getattr__(self, name: str) -> Any:
        if name == "controller":  # not set yet (a copy under construction)
            raise AttributeError(name)
        return getattr(self.controller, name)

    def reset_feed(self) -> None:
        self.step = 0
        self.poses: list[np.ndarray] = []
        self.frame: np.ndarray | None = None
        self.pick_ms = 0.0

    def reset(self, goal: np.ndarray) -> None:
        self.reset_feed()
        self.follower.reset()
        self.controller.reset(goal)

    def act(self, obs: np.ndarray) -> np.ndarray:
        pick = self.follower.observe(self.step, self.observed(obs))
        self.pick_ms = 0.0 if pick is None else pick.ms
        self.step += 1
        return self.controller.act(obs)

    def observed(self, obs: np.ndarray) -> np.ndarray:
        """The markers (V, 3) of the frame the tracker reported in ``obs``."""
        layout = self.env.marker_layout
        assert layout is not None
        parts = self.env.split_observation(obs)
        self.poses = [*self.poses, parts["grippers"]][-(self.latency + 1) :]
        held = held_markers(layout, self.poses[0])  # the poses of the reported frame
        seen = parts["markers"]
        if self.frame is not None:
            seen = np.where(parts["visible"].reshape(-1, 1) > 0.5, seen, self.frame)
        self.frame = np.where(layout.held[:, None], held, seen)
        return self.frame

    @property
    def last_stats(self) -> dict[str, Any]:
        return {**self.controller.last_stats, "code": self.follower.current,
                "code_pick_ms": round(self.pick_ms, 3)}  # fmt: skip

    @property
    def last_latency_ms(self) -> float:
        return self.controller.last_latency_ms

    def summary(self) -> dict[str, Any]:
        """What the run's summary says of the code: each re-pick, and the last code."""
        return {"code_picks": [p.summary() for p in self.follower.picks],
                "code_final": self.follower.current}  # fmt: skip
