"""The options of the built-in controllers (torch-free: `dlo control --help` lists them
without importing torch). Each controller class names its spec as ``spec_cls``; the
registry names it too, so --help need not import the controller.

A run spec that plans through its model (`dlo online`, `dlo bench`) names its planner in a
``planner`` field and holds that planner's options in its ``mpc`` field
(:func:`planner_name_field`, :func:`planner_options_field`).
"""

from __future__ import annotations

import difflib
from typing import Annotated, Any, Literal

from pydantic import BeforeValidator, Field, SerializeAsAny, ValidationInfo

from dlocli.backends.facts import BACKEND_DEFAULT, SERVO_COST
from dlocli.controllers.base import is_planner, with_backend_defaults
from dlocli.errors import BadInput, UnknownName
from dlocli.limits import MAX_COUNT
from dlocli.registry import controllers
from dlocli.specs import Spec


class PlannerSpec(Spec):
    """Options every model-based planner shares."""

    horizon: int = Field(
        5, ge=1, le=100, description="Planning horizon H in control steps (paper: 5)."
    )
    replan_every: int = Field(
        1,
        ge=1,
        le=100,
        description="Re-optimise every k control steps; in between, execute the plan's next "
        "actions.",
    )
    action_cost: float = Field(
        1e-4,
        ge=0,
        description="Weight lambda of a control-effort term lambda * sum_k ||a_k||^2 added to "
        "the shape cost (m^2 per unit action^2); 0 = the paper's objective exactly.",
    )
    warm_start: bool = Field(
        True,
        description="Start each re-plan from the previous plan shifted by the executed steps "
        "(else from zeros).",
    )
    settle_steps: int = Field(
        0,
        ge=0,
        le=100,
        description="Control steps the cost also looks past the horizon with the grippers "
        "standing still: a plan that leaves the cable swinging away from the goal costs what "
        "the swing will cost (0 = the paper's objective; on MuJoCo 4's lightly damped flex "
        "rod, 20 once the model is well trained: docs, the flex rod's control gap).",
    )
    motion_cost: float = Field(
        0.0,
        ge=0,
        le=1e4,
        json_schema_extra=BACKEND_DEFAULT,
        description="Weight of the rod's predicted motion: the cost adds motion_cost * sum_k "
        "||p_k - p_(k-1)||^2 over the plan's steps (the first from the observed positions), so "
        "a plan that reaches the goal with the cable still swinging pays for the swing, and "
        "the planner damps it. 0 = the paper's objective; unset, the backend's planner default "
        "(`dlo list` names them; docs: a planner that damps the swing).",
    )
    servo_cost: float = Field(
        0.0,
        ge=0,
        le=1e2,
        json_schema_extra=BACKEND_DEFAULT,
        description="Weight of each planned action's distance from the held-end servo's action "
        "(the reference `held-end`: each moving gripper driven to where the goal holds its "
        "end), per unit action^2 like action_cost, all but the grippers' roll (which the goal "
        "barely shows: the model's shape cost finds it). 0 = the paper's objective; unset, "
        "the backend's planner default (`dlo list` names them; docs: the held ends decide "
        "the shape).",
    )
    roll_search: int = Field(
        0,
        ge=0,
        le=100,
        description="With servo_cost: control steps a search over each moving gripper's roll "
        "looks past the horizon with the grippers still. At every step the servo's action "
        "with the roll turned at -1, 0 and +1 of the largest rate, held over the horizon, "
        "goes through the model; the one whose predicted final positions lie nearest the goal "
        "becomes the pull's target, roll included (the goal barely shows the roll; the model "
        "may). 0 = off (docs: the held ends decide the shape).",
    )
    servo_above_mm: float = Field(
        0.0,
        ge=0,
        le=1e3,
        description="The held-end servo's action (the reference `held-end`) is executed "
        "instead of the plan's while the model's recent one-step prediction error (the mean "
        "distance of its predicted positions from the observed, averaged with weight "
        "disturbance_gain) is above this many mm; the plan is still made every step. A model "
        "that mispredicts the rod hands the grippers to the servo; one that predicts it plans. "
        "0 = off (docs: the held ends decide the shape).",
    )
    rest_roll: bool = Field(
        False,
        json_schema_extra=BACKEND_DEFAULT,
        description="With servo_cost: turn each moving gripper's roll about the rod's axis "
        "(which the goal barely shows and the servo keeps) to where the rod's earlier rest "
        "states say it rests nearest the goal: a locally weighted linear map from the "
        "grippers' poses to the rest positions, fitted around the current poses to the rest "
        "states the model's checkpoint carries (an online run's: each trial's start and its "
        "end where the grippers stood still). Where few rest states lie near, the roll is "
        "kept. false = off; unset, the backend's planner default (`dlo list` names them; "
        "docs: the roll the rod rests best at).",
    )
    disturbance: Literal["none", "offset", "drift"] = Field(
        "none",
        description="Correct the model's predictions by what it got wrong at the last steps "
        "(offset-free MPC): each step's one-step prediction error of the positions, averaged "
        "with weight disturbance_gain, is added to every predicted step ('offset') or once per "
        "predicted step, so k steps ahead carry k of it ('drift': the model's own drift at "
        "rest cancels). 'none' = the paper's predictions.",
    )
    disturbance_gain: float = Field(
        0.2,
        gt=0,
        le=1,
        description="Weight of the latest one-step prediction error in the running averages "
        "the disturbance and servo_above_mm options read (1 = the latest error alone).",
    )
    tracking: Literal["estimate", "raw"] = Field(
        "estimate",
        description="With the markers observation: 'estimate' blends each report with the "
        "model's prediction, predicts missing markers and bridges the latency; 'raw' plans "
        "from the report as it is (missing markers at their last seen place).",
    )

    def check_resolved(self) -> None:
        if self.roll_search and self.servo_cost == 0.0:
            raise BadInput(
                f"roll_search {self.roll_search} searches the roll of the servo's pull, and "
                "servo_cost is 0 (no pull): set servo_cost > 0 (--servo-cost; the MuJoCo "
                f"rods' default is {SERVO_COST:g}) or roll_search 0"
            )


class MPCSpec(PlannerSpec):
    """Gradient MPC options (paper-like: optimizer adam, iterations 50, warm_start false)."""

    iterations: int = Field(1, ge=1, le=1000, description="Gradient steps per re-plan.")
    step_size: float = Field(
        0.2,
        gt=0,
        description="Optimiser step size: Adam's learning rate in action units "
        "(SGD: per unit gradient).",
    )
    optimizer: Literal["gauss-newton", "adam", "sgd"] = Field(
        "gauss-newton",
        description="Update rule on the actions: gauss-newton (the cost is a sum of squares: "
        "Gauss-Newton steps with the Jacobian refreshed every `curvature_every` re-plans, "
        "clipped to max_step), adam, or sgd (step_size x gradient).",
    )
    max_step: float = Field(
        0.7,
        gt=0,
        le=2,
        description="gauss-newton: largest change of one action coordinate per iteration "
        "(a trust region; the solution is clipped to it).",
    )
    damping: float = Field(
        1e-2, gt=0, le=1e3, json_schema_extra=BACKEND_DEFAULT,
        description="gauss-newton: Levenberg damping added to J^T J, relative to its mean "
        "diagonal: larger moves less far along the directions the model barely sees; unset, "
        "the backend's planner default (`dlo list` names them).",
    )  # fmt: skip
    exact_gradient: bool = Field(
        False,
        description="gauss-newton: back-propagate the exact gradient every iteration (a "
        "backward pass per iteration) instead of J^T r with the residuals r of a forward "
        "rollout and the Jacobian J of the latest refresh.",
    )
    curvature_every: int = Field(
        25,
        ge=1,
        description="gauss-newton: re-plans between refreshes of the Gauss-Newton matrix "
        "(one batched forward rollout of H*A+1 plans by finite differences).",
    )
    jacobian: Literal["full", "shifted"] = Field(
        "full",
        description="gauss-newton: how the Jacobian is refreshed. full: every action of the "
        "plan nudged (H*A+1 plans). shifted: the first action's coordinates only (A+1 plans), "
        "each later action's effect taken as the first's delayed by its steps (the rod's "
        "response to a nudge depends on how long ago it was, not when), about H times "
        "cheaper, so it can be refreshed that much more often.",
    )
    refresh: Literal["inline", "background"] = Field(
        "inline",
        description="gauss-newton: where the Jacobian refresh runs. inline: in the control "
        "step that is due (one batched rollout of H*A+1 plans, every `curvature_every`-th "
        "step). background: in a second "
        "thread from the due step's state and plan, installed curvature_every-1 re-plans "
        "later (it waits there if unfinished), so the steps keep their median latency where "
        "a second core is free. Deterministic either way; background's Jacobian is that "
        "many re-plans older.",
    )
    restarts: int = Field(
        1,
        ge=1,
        le=256,
        description="Plans optimised together in one batch: the warm start plus restarts-1 "
        "uniform random ones; the one with the lowest predicted cost is executed.",
    )
    tolerance: float = Field(
        0.0,
        ge=0,
        lt=1,
        description="Stop early once an iteration lowers the predicted cost by less than this "
        "fraction (0 = always run every iteration).",
    )


class MPPISpec(PlannerSpec):
    """MPPI options."""

    samples: int = Field(
        32,
        ge=2,
        le=4096,
        description="Sampled action sequences per iteration (K), one batch of model rollouts "
        "(at most 4096: each holds every segment's hidden features).",
    )
    iterations: int = Field(
        1, ge=1, le=100, description="Sample-and-average iterations per re-plan."
    )
    noise: float = Field(
        0.3, gt=0, description="Standard deviation of the action perturbations (action units)."
    )
    temperature: float = Field(
        0.1,
        gt=0,
        description="Softmax temperature, as a fraction of the sampled costs' spread (max - min).",
    )


class PilcoSpec(Spec):
    """PILCO hyperparameters (reduced state, GP data, policy, cost, optimisers)."""

    n_keypoints: int = Field(
        3, ge=1, le=200, description="Segments whose positions form the GP state."
    )
    action_repeat: int = Field(
        10, ge=1, le=MAX_COUNT, description="Env steps each PILCO action is held for."
    )
    horizon: int | None = Field(
        None, ge=1, le=MAX_COUNT, description="Planning horizon in PILCO steps; None = one episode."
    )
    initial_random_episodes: int = Field(
        1,
        ge=1,
        le=MAX_COUNT,
        description="Episodes of random actions before the first policy update.",
    )
    max_gp_points: int = Field(
        100,
        ge=2,
        le=10_000,
        description="GP training points (at most 10000: the GP holds their square), "
        "subsampled at random from all data.",
    )
    gp_iterations: int = Field(
        50, ge=1, le=MAX_COUNT, description="L-BFGS iterations of the GP evidence."
    )
    n_basis: int = Field(20, ge=1, le=10_000, description="RBF policy basis functions.")
    policy_scale_floor: float = Field(
        0.1,
        gt=0,
        description="Least input scale (m) of the RBF policy, per dimension: its initial "
        "lengthscale. The scale is the spread of the states seen before the first update; "
        "where episode starts lie many such spreads away, the basis functions vanish there, "
        "the policy outputs zero and its gradient too. The default is the cost width.",
    )
    policy_iterations: int = Field(
        30, ge=1, le=MAX_COUNT, description="Adam steps per policy update."
    )
    policy_lr: float = Field(0.05, gt=0, description="Adam learning rate of the policy.")
    cost_width: float = Field(
        0.1, gt=0, description="Width (m) of the saturating cost on the keypoint distance."
    )


# ----------------------------------------------------------------------------- run specs
#: the planner of a run spec unless it names another (paper Algorithm 1's)
DEFAULT_PLANNER = "mpc"


def planner_options(name: str, options: Any) -> PlannerSpec:
    """``options`` (a dict or spec) as the spec of the registered planner ``name``;
    UnknownName if ``name`` is no planner, ValidationError for wrong options."""
    planners = [n for n in controllers.names() if is_planner(n)]
    if name not in planners:
        if name in controllers:
            why = f"controller '{name}' does not plan through a model"
        else:
            close = difflib.get_close_matches(name, planners, n=1)
            why = f"unknown planner '{name}'" + (f" (did you mean '{close[0]}'?)" if close else "")
        raise UnknownName(f"{why}; planners: {', '.join(planners)}")
    spec_cls = controllers.spec_cls(name)
    if type(options) is spec_cls:
        return options
    if isinstance(options, Spec):  # another planner's: the options it was given
        options = options.model_dump(exclude_unset=True)
    return spec_cls.model_validate(options or {})


def _as_planner_options(value: Any, info: ValidationInfo) -> Any:
    planner = info.data.get("planner")
    # a planner name that failed validation has its own error; these options wait for it
    if planner is None:
        return value
    options = planner_options(planner, value)
    backend = info.data.get("backend")  # None: it failed validation, with its own error
    return options if backend is None else with_backend_defaults(options, planner, backend.name)


def _registered_planner(name: Any) -> Any:
    if isinstance(name, str):
        planner_options(name, None)  # UnknownName if it is no planner
    return name


def planner_name_field() -> Any:
    """The ``planner`` field of a run spec (declare it before :func:`planner_options_field`)."""
    return Field(
        DEFAULT_PLANNER,
        description="The planner through the model: a registered controller that plans "
        "(mpc, mppi, or a plugin's); its options are the mpc fields.",
    )


def planner_options_field(description: str) -> Any:
    """The ``mpc`` field of a run spec: the options of its ``planner``, saved whole."""
    return Field(default_factory=MPCSpec, validate_default=True, description=description)


#: a planner's name, checked against the registry
PlannerName = Annotated[str, BeforeValidator(_registered_planner)]
#: the options of the run's planner: validated as that planner's spec
PlannerOptions = Annotated[SerializeAsAny[PlannerSpec], BeforeValidator(_as_planner_options)]
