"""DLOShapeEnv: the Gymnasium shape-control task on top of any backend.

Observation (flat float32 Box): segment positions (N*3), segment quaternions (N*4), gripper
poses (2*7), goal positions (N*3) and, with ``task.observe_velocity`` (default), segment
velocities (N*7: the change of each segment's position and quaternion over the last control
step, divided by the step; zero right after a reset, when the rod has settled). Use
:meth:`DLOShapeEnv.split_observation` to get the parts back; ``env.observation_slices`` and
``env.observation_shapes`` give each part's place and shape (docs/python.md, "Gymnasium").
Action: Box(-1, 1, (6,)) for ``single`` or (12,) for ``bimanual``, scaled to the task's
maximum gripper velocities. Reward: paper eq. 12. Starts and goals: :mod:`dlocli.env.shapes`.

A diverged simulation does not end the episode early, so that blowing the simulation up never
scores better than trying: every remaining step returns the clip reward -1.5 and the last
finite observation, with ``info["diverged"] = True``, until the episode is truncated after T
steps. Loops that stop at divergence count the steps they skip at -1.5
(:func:`dlocli.env.metrics.diverged_remainder`).
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np

from dlocli.backends import make_backend
from dlocli.backends.rotations import state_change
from dlocli.cancel import CancelToken
from dlocli.cell_spec import CellChoice
from dlocli.env.envelope import Envelope
from dlocli.env.goals import check_goal_reachable, load_goal, save_goal  # noqa: F401 (its API)
from dlocli.env.metrics import REWARD_CLIP, shape_error_mm
from dlocli.env.metrics import reward as shape_reward
from dlocli.env.observation import (
    MarkerLayout,
    Tracker,
    held_markers,
    marker_layout,
    marker_tracker,
    markers_of_shape,
    markers_of_state,
)
from dlocli.env.options import resolve_env_options
from dlocli.env.shapes import (
    apply_task_limits,
    episode_poses,
    load_recorded_poses,
    make_shape,
    max_twist,
    shape_at,
)
from dlocli.env.spaces import (
    observation_layout,
    observation_slices,
    observation_space,
    observed_markers,
)
from dlocli.env.tasks import Task, make_task
from dlocli.errors import BadInput, BadOption, UnworkablePhysics
from dlocli.specs import BackendSpec, EnvSpec, GoalSpec, TaskSpec


class DLOShapeEnv(gym.Env):
    """Drive a rod held by grippers to a goal shape. See the module docstring.

    Args:
        backend: backend name or BackendSpec; None: the MuJoCo rod of the installed MuJoCo.
        task: task name or TaskSpec.
        goal: a goal shape ((N, 3) array or .npy path), or the goal mode "fixed" / "random".
        seed: seed of the goal and of the episodes until ``reset(seed=...)`` is given one.
        render_mode: None (``render()`` returns None) or "rgb_array".
        cell: the address of a cell that steps the rod (``dlo serve``, or a robot speaking
            the dlocli-cell protocol) or a CellChoice; default: a simulator in this process.
        cancel: stops the episode at its next step once cancelled (the commands hand it the
            process's stop signals, so a Ctrl-C swallowed by a destructor still stops them).
        **task_options: TaskSpec fields (``episode_steps=50``, ``shapes="near-rest"``, ...);
            an unknown name raises UnknownOption (a TypeError) listing the valid ones, a bad
            value BadOption (a ValueError).
    """

    @property
    def metadata(self) -> dict[str, Any]:  # type: ignore[override]
        # a property, as on Gymnasium's wrappers: gym.make then hands render_mode="human" to
        # the constructor, which refuses it, instead of wrapping the env in HumanRendering (a
        # pygame window, which fails at the first frame without a display)
        return {"render_modes": ["rgb_array"], "render_fps": 50}

    _closed = False

    def __init__(
        self,
        backend: BackendSpec | str | None = None,
        task: TaskSpec | str = "single",
        goal: np.ndarray | Path | str | None = None,
        seed: int = 0,
        render_mode: str | None = None,
        cell: str | CellChoice | None = None,
        cancel: CancelToken | None = None,
        **task_options: Any,
    ) -> None:
        self._cancel = cancel
        self.backend_spec, self.task_spec, goal = resolve_env_options(
            backend, task, goal, task_options
        )
        if isinstance(cell, str):
            cell = CellChoice(cell=cell)
        if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
            raise BadOption(f"DLOShapeEnv: seed must be an integer >= 0, got {seed!r}")
        if render_mode is not None and render_mode not in self.metadata["render_modes"]:
            modes = ", ".join(["None", *self.metadata["render_modes"]])
            raise BadOption(
                f"DLOShapeEnv: render_mode must be one of {modes}, got {render_mode!r} (it "
                "renders frames, no window: wrap an rgb_array env in HumanRendering to see them)"
            )
        self.task: Task = make_task(self.task_spec.name)
        self.backend = make_backend(self.backend_spec, self.task_spec.control_dt, cell)
        try:  # a cell's session ends with the env that could not be built
            self._set_up(goal, seed, render_mode)
        except BaseException:
            self.backend.close()
            raise

    def _set_up(self, goal: Any, seed: int, render_mode: str | None) -> None:
        apply_task_limits(self.backend, self.task_spec)
        self.envelope = Envelope(
            self.task_spec.envelope, self.backend.limits, self.task.moving,
            self.task_spec.control_dt,
        )  # fmt: skip
        self.n_segments = self.backend.n_segments
        self.render_mode = render_mode
        self.seed_value = int(seed)
        n, velocity = self.n_segments, self.task_spec.observe_velocity
        markers = observed_markers(self.task_spec)
        self.action_space = gym.spaces.Box(-1.0, 1.0, (self.task.action_dim,), np.float32)
        self.observation_space = observation_space(n, velocity, markers)
        #: shape of each part of the flat observation, in order (docs/python.md, "Gymnasium")
        self.observation_shapes = observation_layout(n, velocity, markers)
        #: where each part lies in the flat observation: ``obs[slices["goal"]]``
        self.observation_slices = observation_slices(self.observation_shapes)
        #: the true state's parts, as the full observation holds them (:meth:`state_parts`)
        self.state_shapes = observation_layout(n, velocity)
        self._state_slices = observation_slices(self.state_shapes)
        self._state_space = observation_space(n, velocity)
        #: where the markers sit (None with the full observation) and the tracker's faults
        self.marker_layout: MarkerLayout | None = None
        self.tracker: Tracker | None = None  # or a CloudObserver, alike
        if markers is not None:
            rod = self.backend.rod
            held = (bool(self.backend.moving[0]), bool(self.backend.moving[1]))
            self.marker_layout = marker_layout(self.task_spec.observation, rod.length, n, held)
            self.tracker = marker_tracker(self.task_spec.observation, self.marker_layout,
                                          self.backend, self.task_spec.control_dt)  # fmt: skip
        #: (K, 2, 7) the gripper poses of recorded shapes (None: other shapes)
        self.recorded_poses = None
        if self.task_spec.recorded_poses is not None:
            self.recorded_poses = load_recorded_poses(
                self.task_spec.recorded_poses, self.backend.limits
            )
        self._goal_rng = np.random.default_rng([seed, 1])
        self._goal_given = goal is not None or self.task_spec.goal_file is not None
        #: (2,7) gripper poses that made the goal, when the env made it (None: a given goal)
        self.goal_gripper_poses: np.ndarray | None = None
        #: simulations the last random shape took (more than 1: earlier ones diverged)
        self.shape_attempts = 0
        #: cumulative reward of every episode run to its end on this env, in order
        self.episode_returns: list[float] = []
        self._return = 0.0
        self._seeded = False
        #: the episode generator's state as the last reset began: with ``restore_generator``
        #: that reset can be made again (a learner resumed at an episode boundary)
        self.reset_generator_state: dict[str, Any] | None = None
        self.goal = self._initial_goal(goal)
        self._scale = max_twist(self.task_spec)
        self._t = 0
        self._previous: np.ndarray | None = None  # (N, 7) segment state one step earlier
        self._last_observation: np.ndarray | None = None
        self._last_state: np.ndarray | None = None  # the full observation's vector
        self._reported: np.ndarray | None = None  # (M, 3) the tracker's previous report

    # ------------------------------------------------------------------ setup
    def _initial_goal(self, goal: np.ndarray | Path | str | None) -> np.ndarray | None:
        if goal is None and self.task_spec.goal_file is not None:
            goal = self.task_spec.goal_file
        name = "goal"
        if isinstance(goal, (str, Path)):
            name = f"goal {goal}"
            goal = load_goal(Path(goal), self.n_segments)
        if goal is not None:
            goal = np.asarray(goal, dtype=np.float64)
            if goal.shape != (self.n_segments, 3) or not np.all(np.isfinite(goal)):
                raise BadInput(
                    f"goal must be a finite ({self.n_segments}, 3) array, got {goal.shape}"
                )
            check_goal_reachable(goal, self.backend, name=name)
            return goal
        if self.task_spec.goal == "fixed":
            return self.sample_goal(self._goal_rng)
        return None

    # ------------------------------------------------------------------ random shapes
    def _random_shape(self, rng: np.random.Generator, motion_steps: int) -> bool:
        """Reset the backend and make a random shape (:mod:`dlocli.env.shapes`); False if the
        simulation diverged 10 times."""
        for attempt in range(1, 11):
            self.backend.reset(int(rng.integers(2**31)))
            shaped = make_shape(self.backend, self.task_spec, self.task.moving, rng,
                                motion_steps, self.recorded_poses)  # fmt: skip
            if shaped:
                self.shape_attempts = attempt
                return True
        self.shape_attempts = 10
        return False

    def sample_goal(self, rng: np.random.Generator) -> np.ndarray:
        """A reachable goal: a random shape (:mod:`dlocli.env.shapes`) the rod settled in."""
        if not self._random_shape(rng, 2 * self.task_spec.reset_motion_steps):
            raise UnworkablePhysics(
                "could not generate a goal: the simulation diverged 10 times; lower the task's "
                "velocities or backend.physics_dt, or bring the rod closer to the defaults"
            )
        self.goal_gripper_poses = self.backend.gripper_poses()
        return self.backend.segment_positions().copy()

    def _shape_at(self, poses: np.ndarray, what: str) -> np.ndarray:
        """Settle the rod with its grippers at ``poses`` (2, 7); its segment centres."""
        self.backend.reset(0)
        if not shape_at(self.backend, self.task_spec, poses):
            raise UnworkablePhysics(
                f"the simulation diverged making the episode's {what} at the given gripper "
                "poses; give poses the rod can reach (slack, inside the workspace)"
            )
        return self.backend.segment_positions().copy()

    # ------------------------------------------------------------------ gym API
    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[np.ndarray, dict[str, Any]]:
        self._check_open("reset")
        if seed is None and not self._seeded:
            seed = self.seed_value  # make_env(seed=...) alone makes episodes reproducible
        self._seeded = True
        super().reset(seed=seed)
        self.reset_generator_state = self.np_random.bit_generator.state
        start_poses, goal_poses = episode_poses(options, self.backend.limits)
        if goal_poses is not None:
            self.goal = self._shape_at(goal_poses, "goal")
            self.goal_gripper_poses = self.backend.gripper_poses()
        elif self.task_spec.goal == "random" and not self._goal_given:
            self.goal = self.sample_goal(self.np_random)
        if start_poses is not None:
            self._shape_at(start_poses, "start")
        else:
            self._random_shape(self.np_random, self.task_spec.reset_motion_steps)
        self.envelope.reset()
        self.envelope.check_start(self.backend.gripper_poses())
        self._t = 0
        self._previous = None  # settled: counted at rest
        self._last_observation = self._last_state = self._reported = None
        self._return = 0.0
        return self._observation(), self._info(diverged=False)

    def step(self, action: np.ndarray) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        if self._cancel is not None:
            self._cancel.raise_if_cancelled()
        self._check_open("step")
        commands = self.task.to_grippers(np.clip(self._checked(action), -1.0, 1.0))
        self._previous = self.segment_state()
        velocities = commands * self._scale
        poses = self.backend.gripper_poses()
        sent = self.envelope.apply(velocities, poses, self.tracked)
        if sent is not velocities:  # clipped: what the grippers did is what is recorded
            commands = sent / self._scale
        ok = self.backend.step(sent)
        self._t += 1
        reward = -REWARD_CLIP if not ok else float(shape_reward(self._positions(), self.goal))
        truncated = self._t >= self.task_spec.episode_steps
        self._return += reward
        if truncated:
            self.episode_returns.append(self._return)
        info = self._info(diverged=not ok)
        info["commands"] = commands
        return self._observation(), reward, False, truncated, info

    def generator_state(self) -> dict[str, Any]:
        """The episode generator's state now: what the next ``reset()`` draws from."""
        return self.np_random.bit_generator.state

    def restore_generator(self, state: dict[str, Any], episode_returns: list[float]) -> None:
        """Continue a saved env: the next ``reset()`` (no seed) draws from ``state`` and
        ``episode_returns`` holds the returns of the episodes run before."""
        self._seeded = True
        self.np_random.bit_generator.state = state
        self.episode_returns = list(episode_returns)

    def _positions(self) -> np.ndarray:
        if self.backend.diverged and self._last_state is not None:
            return self.state_parts()["positions"]
        return self.backend.segment_positions()

    def _info(self, diverged: bool) -> dict[str, Any]:
        error = float(shape_error_mm(self._positions(), self.goal))
        return {
            "shape_error_mm": error, "diverged": diverged, "t": self._t,
            "tracked": self.tracked,
        }  # fmt: skip

    @property
    def tracked(self) -> bool:
        """Whether the latest observation saw the cable (a cell's tracker, a lost frame)."""
        return self.backend.tracked and not (self.tracker is not None and self.tracker.lost)

    def segment_state(self) -> np.ndarray:
        """(N, 7) segment positions and quaternions."""
        backend = self.backend
        return np.concatenate([backend.segment_positions(), backend.segment_quaternions()], 1)

    def _observation(self) -> np.ndarray:
        if self.backend.diverged and self._last_observation is not None:
            return self._last_observation  # frozen at the last finite state
        state = self.segment_state()
        parts = {
            "positions": state[:, :3],
            "quaternions": state[:, 3:],
            "grippers": self.backend.gripper_poses(),
            "goal": np.asarray(self.goal),
        }
        if self.task_spec.observe_velocity:
            change = 0.0 * state if self._previous is None else state_change(self._previous, state)
            parts["velocities"] = change / self.task_spec.control_dt
        self._last_state = self._flat(parts, self.state_shapes, self._state_space)
        if self.tracker is None:
            self._last_observation = self._last_state
        else:
            marker_parts = self._marker_parts(state, parts["grippers"])
            self._last_observation = self._flat(
                marker_parts, self.observation_shapes, self.observation_space
            )
        return self._last_observation

    @staticmethod
    def _flat(
        parts: dict[str, np.ndarray], shapes: dict[str, tuple[int, ...]], space: gym.spaces.Box
    ) -> np.ndarray:
        flat = np.concatenate([parts[name].ravel() for name in shapes])
        flat = np.nan_to_num(flat, posinf=np.inf, neginf=-np.inf)
        return np.clip(flat, space.low, space.high).astype(np.float32)

    def _marker_parts(self, state: np.ndarray, grippers: np.ndarray) -> dict[str, np.ndarray]:
        """The markers observation's parts: the tracker's report of the true markers."""
        assert self.tracker is not None and self.marker_layout is not None
        true = markers_of_state(self.marker_layout, state[:, :3], state[:, 3:], grippers)
        if self._reported is None:  # a reset: the tracker's stream follows the episode's
            seen, visible = self.tracker.reset(self._tracker_rng(), true)
        else:
            seen, visible = self.tracker.report(true)
        parts = {
            "markers": seen,
            "visible": visible[:, None].astype(np.float64),
            "grippers": grippers,
            "goal": self.goal_markers(),
        }
        if self.task_spec.observe_velocity:
            before = seen if self._reported is None else self._reported
            parts["velocities"] = (seen - before) / self.task_spec.control_dt
        self._reported = seen.copy()
        return parts

    def goal_markers(self) -> np.ndarray:
        """(M, 3) the goal's markers: on the polyline of its centres, the held ones at the
        goal's gripper poses when the env made the goal (a goal file has none)."""
        assert self.marker_layout is not None
        markers = markers_of_shape(self.marker_layout, np.asarray(self.goal))
        if self.goal_gripper_poses is None:
            return markers
        held = self.marker_layout.held[:, None]
        return np.where(held, held_markers(self.marker_layout, self.goal_gripper_poses), markers)

    def _tracker_rng(self) -> np.random.Generator:
        """The tracker's generator of this episode, from the episode's start state, so the
        tracker draws nothing from the env's own stream (starts and goals stay the same)."""
        state = json.dumps(self.reset_generator_state, sort_keys=True, default=str)
        digest = hashlib.sha256(state.encode()).digest()
        return np.random.default_rng(int.from_bytes(digest[:16], "little"))

    def state_parts(self) -> dict[str, np.ndarray]:
        """The true state at the latest observation, as the full observation would hold it
        (float32): positions, quaternions, grippers, goal and, if observed, velocities;
        whatever the controller observes."""
        if self._last_state is None:
            raise RuntimeError("call reset() before state_parts()")
        return {
            name: self._last_state[self._state_slices[name]].reshape(shape)
            for name, shape in self.state_shapes.items()
        }

    def split_observation(self, obs: np.ndarray) -> dict[str, np.ndarray]:
        """Inverse of the flat observation: positions, quaternions, grippers, goal and, if
        observed, velocities (N, 7); leading batch axes are kept."""
        obs = np.asarray(obs)
        lead = obs.shape[:-1]
        return {
            name: obs[..., self.observation_slices[name]].reshape(*lead, *shape)
            for name, shape in self.observation_shapes.items()
        }

    def render(self) -> np.ndarray | None:
        """An RGB frame (H, W, 3) of the rod and the goal with ``render_mode="rgb_array"``;
        None without a render mode (Gymnasium's convention)."""
        if self.render_mode is None:
            return None
        return self.backend.render(goal=self.goal)

    def close(self) -> None:
        if not self._closed:
            self.backend.close()
            self._closed = True

    def _check_open(self, call: str) -> None:
        if self._closed:
            raise BadOption(f"DLOShapeEnv.{call}() after close(): make a new env")

    def _checked(self, action: Any) -> np.ndarray:
        """``action`` as float64 of the action space's shape; BadOption (a ValueError) for
        anything else: complex, objects, text, the wrong size, NaN."""
        array = np.asarray(action)
        shape = self.action_space.shape
        if array.dtype.kind not in "biuf":
            raise BadOption(f"DLOShapeEnv.step: the action must be real numbers, not {array.dtype}")
        if array.shape != shape:
            raise BadOption(
                f"DLOShapeEnv.step: the action must have shape {shape}, not {array.shape}"
            )
        array = array.astype(np.float64)
        if not np.all(np.isfinite(array)):
            raise BadOption("DLOShapeEnv.step: the action holds NaN or inf")
        return array

    # ------------------------------------------------------------------ state for planners
    def get_state(self) -> np.ndarray:
        return np.concatenate([self.backend.get_state(), [self._t]])

    def set_state(self, state: np.ndarray) -> None:
        self.backend.set_state(state[:-1])
        self._t = int(state[-1])


def make_env(
    backend: str | BackendSpec | None = None,
    task: str | TaskSpec = "single",
    goal: np.ndarray | Path | str | None = None,
    seed: int = 0,
    render_mode: str | None = "rgb_array",
    cell: str | CellChoice | None = None,
    cancel: CancelToken | None = None,
    **task_overrides: Any,
) -> DLOShapeEnv:
    """Build a shape-control environment; ``task_overrides`` set TaskSpec fields. ``goal`` is
    a goal shape (array or .npy path) or the goal mode, "fixed" or "random"; ``cell`` the
    address of a cell that steps the rod (default: a simulator in this process). Unlike
    DLOShapeEnv and ``gym.make``, it renders frames by default (``dlo control --video``)."""
    return DLOShapeEnv(backend, task, goal, seed, render_mode, cell, cancel, **task_overrides)


def make_env_from_spec(
    spec: EnvSpec, goal: np.ndarray | Path | str | None = None, cancel: CancelToken | None = None
) -> DLOShapeEnv:
    return make_env(spec.backend, spec.task, goal=goal, seed=spec.seed, cancel=cancel)


# ----------------------------------------------------------------------------- goal files
def make_goal(spec: GoalSpec) -> np.ndarray:
    """The (N,3) goal the env would use as its fixed goal for ``spec.seed``."""
    env = make_env_from_spec(
        spec.model_copy(
            update={"task": spec.task.model_copy(update={"goal": "fixed", "goal_file": None})}
        )
    )
    try:
        return np.asarray(env.goal, dtype=np.float64)
    finally:
        env.close()
