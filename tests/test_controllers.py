"""Controllers: conformance of every registered controller that needs at most a model, the
planners' optimisation and warm start, closed-loop control in MuJoCo, and `dlo control`.

Real simulators and real (tiny, briefly trained) torch models throughout.
"""

from __future__ import annotations

import csv
import json

import numpy as np
import pytest
import torch
from typer.testing import CliRunner

import dlocli
from dlocli.cli import app
from dlocli.controllers.base import LearningAgent, make_controller
from dlocli.controllers.mpc import GradientMPC, MPCSpec
from dlocli.controllers.mppi import MPPI, MPPISpec
from dlocli.controllers.planning import shift_plan
from dlocli.data import load_dataset
from dlocli.errors import BadInput
from dlocli.events import Began
from dlocli.models import build_model, save_checkpoint
from dlocli.models.fit import fit as fit_model
from dlocli.models.spec import FitSpec, model_spec
from dlocli.registry import controllers
from dlocli.runs.control import ControlSpec, run_control
from dlocli.specs import TaskSpec

from tiny import MUJOCO_ROD, run_dlo

TINY = model_spec({"hidden": 32, "edge_layers": 2, "node_layers": 2, "lstm_layers": 1})
SUMMARY_KEYS = {"initial_error_mm", "final_error_mm", "score", "best_error_mm",
                "cumulative_reward", "latency_ms_median", "latency_ms_p95", "steps"}  # fmt: skip


def model_controllers() -> list[str]:
    """Registered controllers that act with at most a dynamics model (no training loop)."""
    names = []
    for name in controllers.names():
        cls = controllers.get(name)
        if not issubclass(cls, LearningAgent) and set(cls.needs) <= {"model"}:
            names.append(name)
    return names


pytestmark = pytest.mark.usefixtures("one_thread")  # conftest.py


@pytest.fixture(scope="module")
def tiny_model(small_dataset_dir):
    """A small in-bilstm trained for a few seconds on the shared random MuJoCo dataset."""
    torch.manual_seed(0)
    model = build_model(TINY, 20)
    fit = FitSpec(epochs=15, lr=1e-2, batch_size=32, device="cpu", seed=0)
    fit_model(model, load_dataset(small_dataset_dir), fit)
    return model.eval()


@pytest.fixture(scope="module")
def checkpoint(tiny_model, tmp_path_factory):
    return save_checkpoint(tiny_model, tmp_path_factory.mktemp("ckpt") / "tiny.pt")


@pytest.fixture(scope="module")
def envs():
    cache = {task: dlocli.make_env(MUJOCO_ROD, task, seed=0, episode_steps=50)
             for task in ("single", "bimanual")}  # fmt: skip
    yield cache
    for env in cache.values():
        env.close()


# ------------------------------------------------------------------------------ conformance
@pytest.mark.parametrize("task", ["single", "bimanual"])
@pytest.mark.parametrize("name", model_controllers())
def test_controller_conformance(envs, tiny_model, name, task):
    """Every controller: in-bounds float32 actions of the task's size, timed; bimanual runs
    on the single-gripper model without retraining."""
    env = envs[task]
    obs, _ = env.reset(seed=1)
    controller = make_controller(name, env, model=tiny_model, seed=0)
    controller.reset(env.goal)
    for _ in range(3):
        action = controller.act(obs)
        assert action.shape == env.action_space.shape and action.dtype == np.float32
        assert np.all(np.isfinite(action)) and np.all(np.abs(action) <= 1.0)
        assert controller.last_latency_ms > 0.0
        obs, *_ = env.step(action)


def test_planner_needs_a_model(envs):
    with pytest.raises(BadInput, match="needs a model"):
        make_controller("mpc", envs["single"])
    with pytest.raises(BadInput, match="iterations"):
        make_controller("mpc", envs["single"], model=object(), options={"iterations": 0})


# ------------------------------------------------------------------------------ planners
def predicted_cost(controller, obs, plan):
    with torch.no_grad():
        return float(controller.predict_cost(controller.state_tensor(obs), plan[None])[0])


@pytest.mark.parametrize(
    "planner,spec",
    [(GradientMPC, MPCSpec(iterations=10, warm_start=False)),
     (GradientMPC, MPCSpec(iterations=3, exact_gradient=True, warm_start=False)),
     (GradientMPC, MPCSpec(optimizer="adam", iterations=10, warm_start=False)),
     (GradientMPC, MPCSpec(iterations=5, restarts=4, warm_start=False)),
     (GradientMPC, MPCSpec(iterations=10, settle_steps=5, warm_start=False)),
     (GradientMPC, MPCSpec(iterations=10, motion_cost=32.0, warm_start=False)),
     (MPPI, MPPISpec(samples=64, iterations=3, warm_start=False))],
    ids=["mpc", "mpc-exact-gradient", "mpc-adam", "mpc-restarts", "mpc-settle", "mpc-motion",
         "mppi"],
)  # fmt: skip
def test_planner_lowers_predicted_cost(envs, tiny_model, planner, spec):
    """The executed plan's model-predicted shape cost is below the initial guess's (zeros).

    Exact-gradient Gauss-Newton lowers the predicted cost by only 0-5% in its 3 iterations,
    and not on every start: its last evaluated cost over its first was 0.947-1.004 (12 tiny
    models x starts, AMD EPYC, MuJoCo 3.17), where stepping uphill instead gives 1.006-1.029.
    So for it the test holds the mean over three starts of the same run of the returned
    plan's cost over the first."""
    env = envs["single"]
    if getattr(spec, "exact_gradient", False):
        ratios = []
        for start in (2, 3, 4):
            obs, _ = env.reset(seed=start)
            controller = planner(env, tiny_model, spec)
            controller.reset(env.goal)
            controller.act(obs)
            stats = controller.last_stats
            assert stats["replanned"] == 1
            ratios.append(controller.returned_cost() / stats["cost_initial"])
        assert np.mean(ratios) < 1.0, ratios
        return
    obs, _ = env.reset(seed=2)
    controller = planner(env, tiny_model, spec)
    controller.reset(env.goal)
    controller.act(obs)
    zeros = torch.zeros_like(controller.plan)
    executed = predicted_cost(controller, obs, controller.plan)
    assert executed < predicted_cost(controller, obs, zeros)
    stats = controller.last_stats
    assert stats["replanned"] == 1 and controller.returned_cost() < stats["cost_initial"]


@pytest.mark.parametrize("spec", [MPCSpec(), MPCSpec(iterations=4), MPCSpec(motion_cost=32.0)])
def test_reported_final_cost_is_the_returned_plans(envs, tiny_model, spec):
    """A re-plan's reported final cost is the predicted cost of the plan it returns, from the
    state it planned from (with the default one Gauss-Newton step too, where the only cost
    the optimisation evaluated is the warm start's), and `cost_initial` is the start's."""
    env = envs["single"]
    obs, _ = env.reset(seed=2)
    controller = GradientMPC(env, tiny_model, spec)
    controller.reset(env.goal)
    first_plan = torch.zeros(spec.horizon, 6)
    controller.act(obs)
    state = controller.state_tensor(obs)
    with torch.no_grad():
        returned = float(controller.residuals(state, controller.plan[None], None).square().sum())
        started = float(controller.residuals(state, first_plan[None], None).square().sum())
    assert controller.returned_cost() == pytest.approx(returned, rel=1e-6)
    assert controller.last_stats["cost_initial"] == pytest.approx(started, rel=1e-6)
    assert controller.returned_cost() != pytest.approx(started, rel=1e-3)  # the plan moved


def test_gauss_newton_gradient_matches_backprop(envs, tiny_model):
    """Right after a Jacobian refresh, the forward-only gradient 2 J^T r (J by finite
    differences) points where the back-propagated gradient does, and the step descends."""
    env = envs["single"]
    obs, _ = env.reset(seed=2)
    mpc = GradientMPC(env, tiny_model, MPCSpec())
    mpc.reset(env.goal)
    state = mpc.state_tensor(obs)
    plan = torch.linspace(-0.5, 0.5, 30).view(5, 6)
    mpc.rule.refresh(mpc, state, plan)
    cost, lagged = mpc.rule.cost_and_gradient(mpc, state, plan[None])
    plans = plan[None].clone().requires_grad_(True)
    (exact,) = torch.autograd.grad(mpc.predict_cost(state, plans).sum(), plans)
    assert torch.nn.functional.cosine_similarity(lagged.flatten(), exact.flatten(), 0) > 0.95
    with torch.no_grad():
        stepped = plan[None] - mpc.rule.step(lagged, 1)
        assert mpc.predict_cost(state, stepped)[0] < cost[0]


def test_motion_cost_is_the_predicted_motion_per_step(envs, tiny_model):
    """motion_cost w adds sqrt(w) x the predicted change of every position per step, the first
    from the observed positions, after the shape errors and the effort; w = 0 is the paper's
    cost (those two alone)."""
    env = envs["single"]
    obs, _ = env.reset(seed=2)
    moving = GradientMPC(env, tiny_model, MPCSpec(horizon=5, motion_cost=16.0))
    paper = GradientMPC(env, tiny_model, MPCSpec(horizon=5, motion_cost=0.0))
    for mpc in (moving, paper):
        mpc.reset(env.goal)
    state = moving.state_tensor(obs)
    plan = torch.linspace(-0.6, 0.6, 30).view(1, 5, 6)
    with torch.no_grad():
        ours, theirs = moving.residuals(state, plan, None), paper.residuals(state, plan, None)
        predicted = moving.view.predict(state, moving.task.to_grippers(plan), None)
    path = torch.cat([state[None, :, :, :3], predicted], dim=1)
    motion = 4.0 * (path[:, 1:] - path[:, :-1]).flatten(1)
    assert ours.shape == (1, theirs.shape[1] + 5 * 20 * 3)
    torch.testing.assert_close(ours[:, : theirs.shape[1]], theirs)
    torch.testing.assert_close(ours[:, theirs.shape[1] :], motion)
    assert float(motion.abs().max()) > 0.0


def test_settle_steps_cost_the_swing_after_the_plan(envs, tiny_model):
    """settle_steps S: the cost of an H-step plan is that of the plan followed by S steps
    standing still (zero actions), less nothing but the still steps' zero effort; the
    recorded prediction stays the plan's H steps, and the executed plan its H actions."""
    env = envs["single"]
    obs, _ = env.reset(seed=2)
    settling = GradientMPC(env, tiny_model, MPCSpec(horizon=5, settle_steps=3, motion_cost=0))
    longer = GradientMPC(env, tiny_model, MPCSpec(horizon=8, motion_cost=0))
    for mpc in (settling, longer):
        mpc.reset(env.goal)
    state = settling.state_tensor(obs)
    plan = torch.linspace(-0.6, 0.6, 30).view(1, 5, 6)
    extended = torch.cat([plan, torch.zeros(1, 3, 6)], dim=1)
    with torch.no_grad():
        ours = settling.residuals(state, plan)
        theirs = longer.residuals(state, extended)
    positions = 8 * 20 * 3
    assert ours.shape == (1, positions + 5 * 6)
    torch.testing.assert_close(ours[:, :positions], theirs[:, :positions])
    torch.testing.assert_close(ours[:, positions:], theirs[:, positions : positions + 30])
    plain = GradientMPC(env, tiny_model, MPCSpec(horizon=5, motion_cost=0))
    plain.reset(env.goal)
    with torch.no_grad():
        assert settling.predict_cost(state, plan) > plain.predict_cost(state, plan)
    settling.act(obs)
    commands, predicted = settling.planned_path()
    assert commands.shape == (5, 2, 6) and predicted.shape == (5, 20, 3)


def jacobian_updates(env, model, refresh: str, steps: int = 11) -> tuple[dict, list]:
    """Closed-loop MPC with the Jacobian refreshed every 3 re-plans: {re-plan: the J^T
    installed there}, and the actions."""
    obs, _ = env.reset(seed=4)
    mpc = GradientMPC(env, model, MPCSpec(curvature_every=3, refresh=refresh))
    mpc.reset(env.goal)
    installed, actions, last = {}, [], None
    for replan in range(1, steps + 1):
        actions.append(mpc.act(obs))
        if mpc.rule.jacobian_t is not last:
            installed[replan] = last = mpc.rule.jacobian_t
        obs = env.step(actions[-1])[0]
    return installed, actions


def test_background_jacobian_refresh_is_deterministic_and_lagged(envs, tiny_model):
    """refresh="background": the Jacobian due at re-plan k (from k's state and plan) is
    computed in a second thread and installed at k + curvature_every - 1, whatever the
    thread's timing: two runs act alike. Inline, it is installed at k itself."""
    env = envs["single"]
    inline, _ = jacobian_updates(env, tiny_model, "inline")
    background, first = jacobian_updates(env, tiny_model, "background")
    again, second = jacobian_updates(env, tiny_model, "background")
    assert list(inline) == [1, 4, 7, 10]
    assert list(background) == list(again) == [1, 6, 9], "launched at 4, 7, 10; installed 2 later"
    # both runs are alike up to re-plan 4's refresh: the same state and plan went in
    torch.testing.assert_close(background[6], inline[4], atol=0, rtol=0)
    for a, b in zip(first, second, strict=True):
        np.testing.assert_array_equal(a, b)


def test_planner_feeds_the_model_the_previous_observation(envs, tiny_model):
    """The velocity input: at the second step the planner rolls out from (s_1, s_0); a state
    it did not observe (and the first step of an episode) counts as at rest."""
    assert tiny_model.spec.velocity_input
    env = envs["single"]
    obs0, _ = env.reset(seed=3)
    mpc = GradientMPC(env, tiny_model, MPCSpec())
    mpc.reset(env.goal)
    mpc.act(obs0)
    assert mpc.previous_of(mpc._observed) is None, "first step: no previous state"
    obs1 = env.step(np.ones(6, np.float32))[0]
    mpc.act(obs1)
    observed = mpc._observed
    assert torch.equal(mpc.previous_of(observed), mpc.state_tensor(obs0))
    plan = torch.zeros(1, 5, 6)
    with torch.no_grad():
        moving = mpc.predict_cost(observed, plan)
        at_rest = mpc.predict_cost(mpc.state_tensor(obs1), plan)
    assert not torch.equal(moving, at_rest), "the rod's motion changes the prediction"
    mpc.reset(env.goal)
    assert mpc._observed is None and mpc._previous is None, "a new episode forgets it"


def test_shift_plan():
    plan = torch.arange(10.0).view(5, 2)
    np.testing.assert_array_equal(shift_plan(plan, 1), [[2, 3], [4, 5], [6, 7], [8, 9], [8, 9]])
    np.testing.assert_array_equal(shift_plan(plan, 3), [[6, 7], [8, 9], [8, 9], [8, 9], [8, 9]])


def test_warm_start_and_replan_every(envs, tiny_model):
    """Between re-plans the plan's next actions run unchanged; a re-plan starts from the plan
    shifted by the executed steps; without warm start it starts from zeros."""
    env = envs["single"]
    obs, _ = env.reset(seed=4)
    mpc = GradientMPC(env, tiny_model, MPCSpec(iterations=2, replan_every=3))
    mpc.reset(env.goal)
    first = mpc.act(obs)
    plan = mpc.plan.clone()
    np.testing.assert_allclose(first, plan[0].numpy())
    for k in (1, 2):
        np.testing.assert_allclose(mpc.act(obs), plan[k].numpy())
        assert mpc.last_stats == {"replanned": 0.0}
    torch.testing.assert_close(mpc._initial_plan(), shift_plan(plan, 3))
    mpc.act(obs)
    assert mpc.last_stats["replanned"] == 1
    cold = GradientMPC(env, tiny_model, MPCSpec(warm_start=False))
    cold.reset(env.goal)
    cold.act(obs)
    assert not cold._initial_plan().any()


# ------------------------------------------------------------------------------ closed loop
def easy_goal(tmp_path, seed: int) -> str:
    """The shape 20 steps of one constant right-gripper motion away from the seeded start."""
    env = dlocli.make_env(MUJOCO_ROD, "single", seed=seed)
    env.reset(seed=seed)
    for _ in range(20):
        env.step(np.array([0.8, 0.0, 0.6, 0.0, 0.0, 0.0], np.float32))
    path = tmp_path / f"easy-{seed}.npy"
    np.save(path, env.backend.segment_positions())
    env.close()
    return str(path)


def test_mpc_reduces_true_error_in_mujoco(tmp_path, checkpoint):
    """Gradient MPC through the tiny learned model brings the simulated rod closer to easy
    goals than doing nothing from the same starts; the run directory holds the summary,
    metrics, plot, resolved spec and a GIF."""
    mpc, nothing = [], []
    for seed in (0, 1, 2):
        task = TaskSpec(goal_file=easy_goal(tmp_path, seed), episode_steps=30)
        spec = ControlSpec(task=task, checkpoint=checkpoint, seed=seed,
                           out=tmp_path / f"run-{seed}")  # fmt: skip
        if seed == 0:
            spec = spec.model_copy(update={"video": tmp_path / "run.gif", "video_every": 10})
        records = []
        mpc.append(run_control(spec, records.append))
        stepped = [e for e in records if not isinstance(e, Began)]
        assert mpc[-1].keys() >= SUMMARY_KEYS and mpc[-1]["steps"] == len(stepped) == 30
        # the reference from the same start in the same run: doing nothing
        nothing.append(run_control(
            spec.model_copy(update={"controller": "zero", "checkpoint": None, "video": None,
                                    "out": tmp_path / f"zero-{seed}"})
        ))  # fmt: skip
        assert nothing[-1]["initial_error_mm"] == mpc[-1]["initial_error_mm"]

    def ratio(key: str) -> float:  # MPC's error over doing nothing's, mean over the starts
        return float(np.mean([m[key] / z[key] for m, z in zip(mpc, nothing, strict=True)]))

    # The tiny model differs between CPUs (float rounding in its training), so the margins
    # come from the spread over 8 tiny models (training seeds 0-7, AMD EPYC), with the default
    # rod's planner defaults (on the flex rod the cost also pays for the motion, which slows
    # the approach within 30 steps): the 3-start mean of final/nothing ranged 0.36-0.82 (mean
    # 0.55, sd 0.15; one start alone up to 0.91), of best/nothing 0.33-0.78 (mean 0.46, sd
    # 0.14); with the paper's planner 0.35-0.93 and 0.23-0.67. Bounds: about 3 sd above the
    # mean.
    assert ratio("final_error_mm") < 1.0
    assert ratio("best_error_mm") < 0.9
    out = tmp_path / "run-0"
    assert (
        json.loads((out / "summary.json").read_text())["final_error_mm"] == mpc[0]["final_error_mm"]
    )
    assert json.loads((out / "spec.json").read_text())["controller_options"]["horizon"] == 5
    assert (out / "metrics.csv").read_text().startswith("step,shape_error_mm,reward,latency_ms")
    assert (out / "plots" / "error.png").stat().st_size > 0
    assert (tmp_path / "run.gif").stat().st_size > 0


# ------------------------------------------------------------------------------ CLI
runner = CliRunner()


def control(*args: str):
    return runner.invoke(app, ["control", *args])


def test_cli_bimanual_with_single_model(tmp_path, checkpoint):
    """`dlo control --task bimanual` with a model trained on the single task, JSON summary."""
    goal = tmp_path / "goal.npy"
    assert runner.invoke(app, ["goal", "--out", str(goal), "--task", "bimanual"]).exit_code == 0
    res = control("--goal", str(goal), "--checkpoint", str(checkpoint), "--task", "bimanual",
                  "--steps", "4", "-o", "iterations=1", "--out", str(tmp_path / "r"),
                  "--json")  # fmt: skip
    assert res.exit_code == 0, res.output
    summary = json.loads(res.stdout.strip().splitlines()[-1])
    assert summary.keys() >= SUMMARY_KEYS and summary["steps"] == 4
    # each re-plan's row: the cost it started from and the cost of the plan it returned
    with open(tmp_path / "r" / "metrics.csv", newline="") as rows:
        costs = [(float(r["cost_initial"]), float(r["cost_final"])) for r in csv.DictReader(rows)]
    assert len(costs) == 4 and all(final != initial for initial, final in costs), costs


def bad_goal(tmp_path, kind: str) -> str:
    good = dlocli.make_env(MUJOCO_ROD, "single", seed=0)
    shape = good.goal
    good.close()
    arrays = {
        "text": np.full((20, 3), "a"), "shape": shape[:10], "inf": shape * np.inf,
        "nan": np.where(shape > 0.5, np.nan, shape), "far": shape + np.array([5.0, 0.0, 0.0]),
    }  # fmt: skip
    path = tmp_path / f"{kind}.npy"
    if kind in arrays:
        np.save(path, arrays[kind])
    elif kind == "suffix":
        path = tmp_path / "goal.txt"
        path.write_text("1 2 3")
    elif kind == "garbage":
        path.write_bytes(b"not an npy file")
    return str(path)


@pytest.mark.parametrize(
    "kind,needle",
    [("missing", "does not exist"), ("suffix", "not a .npy"), ("garbage", "could not be read"),
     ("text", "dtype"), ("shape", "shape (10, 3)"), ("nan", "NaN"), ("inf", "NaN or inf"),
     ("far", "reach")],
)  # fmt: skip
def test_cli_bad_goal_exit_2(tmp_path, checkpoint, kind, needle):
    res = control("--goal", bad_goal(tmp_path, kind), "--checkpoint", str(checkpoint),
                  "--out", str(tmp_path / "r"))  # fmt: skip
    assert res.exit_code == 2, res.output
    assert needle in res.output
    assert kind == "far" or "(20, 3)" in res.output, "names the expected format"
    assert "Traceback" not in res.output and len(res.output.strip().splitlines()) == 1
    assert not (tmp_path / "r").exists(), "bad input writes no run directory"


def test_cli_bad_model_exit_2(tmp_path):
    goal = tmp_path / "goal.npy"
    env = dlocli.make_env(MUJOCO_ROD, "single", seed=0)
    np.save(goal, env.goal)
    env.close()
    other = save_checkpoint(build_model(TINY, 10), tmp_path / "ten.pt")
    res = control("--goal", str(goal), "--checkpoint", str(other), "--out", str(tmp_path / "r"))
    assert res.exit_code == 2 and "10 segments" in res.output and "20" in res.output
    assert len(res.output.strip().splitlines()) == 1
    for args, needle in [
        (["--checkpoint", str(goal)], "checkpoint"),  # not a checkpoint
        (["--checkpoint", str(tmp_path / "none.pt")], "does not exist"),
        ([], "needs a model"),
        (["--checkpoint", str(other), "--controller", "mcp"], "Did you mean 'mpc'"),
        (["--checkpoint", str(other), "-o", "iterations=0"], "iterations"),
        (["--checkpoint", str(other), "--video", str(tmp_path / "v.avi")], ".gif or .mp4"),
    ]:
        res = control("--goal", str(goal), *args, "--out", str(tmp_path / "r"))
        assert res.exit_code == 2 and needle in res.output, (args, res.output)
        assert "Traceback" not in res.output


@pytest.mark.parametrize(
    "value,needle",
    [("-1", "greater than or equal to 0"), ("1000", "less than or equal to 100"),
     ("nan", "valid integer"), ("2.5", "valid integer")],
)  # fmt: skip
def test_cli_bad_settle_steps_exit_2_and_write_nothing(tmp_path, capsys, value, needle):
    """`dlo online --settle-steps` takes 0..100 whole steps: anything else is one line from
    the `dlo` entry point, exit 2, before any run directory exists."""
    out = tmp_path / "run"
    assert run_dlo(["online", "--settle-steps", value, "--out", str(out)]) == 2
    said = capsys.readouterr().err.strip()
    assert needle in said and len(said.splitlines()) == 1
    assert not out.exists()


# ------------------------------------------------------------- shifted Jacobian, disturbance
def test_shifted_jacobian_delays_the_first_actions_response(envs, tiny_model):
    """The shifted Jacobian nudges the first action only: its columns for the first action are
    the full Jacobian's, the effort terms are exact for every action, and action j's response
    of the predicted positions is the first action's delayed by j steps."""
    from dlocli.controllers.mpc import full_jacobian, shifted_jacobian

    env = envs["bimanual"]
    obs, _ = env.reset(seed=2)
    mpc = GradientMPC(env, tiny_model, MPCSpec(horizon=5, motion_cost=16.0, settle_steps=2))
    mpc.reset(env.goal)
    state = mpc.state_tensor(obs)
    plan = torch.linspace(-0.5, 0.5, 60).view(5, 12)
    full, _ = full_jacobian(mpc, state, plan, None)
    shifted, _ = shifted_jacobian(mpc, state, plan, None)
    assert shifted.shape == full.shape == (60, 7 * 20 * 3 + 60 + 7 * 20 * 3)
    torch.testing.assert_close(shifted[:12], full[:12], atol=1e-5, rtol=1e-4)
    positions = 7 * 20 * 3
    torch.testing.assert_close(
        shifted[:, positions : positions + 60], full[:, positions : positions + 60]
    )
    first = shifted[:12, :positions].view(12, 7, 60)
    later = shifted[24:36, :positions].view(12, 7, 60)  # action 2: two steps later
    assert float(later[:, :2].abs().max()) == 0.0
    torch.testing.assert_close(later[:, 2:], first[:, :5])


def test_shifted_jacobian_plans_lower_the_predicted_cost(envs, tiny_model):
    """Gauss-Newton with the shifted Jacobian refreshed at every re-plan lowers the predicted
    cost of the plan it executes below the start's."""
    env = envs["bimanual"]
    obs, _ = env.reset(seed=2)
    spec = MPCSpec(iterations=10, jacobian="shifted", curvature_every=1, warm_start=False)
    controller = GradientMPC(env, tiny_model, spec)
    controller.reset(env.goal)
    controller.act(obs)
    assert controller.returned_cost() < controller.last_stats["cost_initial"]


@pytest.mark.parametrize("mode", ["offset", "drift"])
def test_disturbance_adds_the_one_step_prediction_error(envs, tiny_model, mode):
    """With a disturbance option the planner predicts the next observation under each action it
    executes; the error it then sees (gain 1: the latest alone) is added to every predicted
    step ('offset') or k times to the k-th ('drift'); without one, nothing is added."""
    env = envs["single"]
    obs, _ = env.reset(seed=2)
    corrected = GradientMPC(env, tiny_model, MPCSpec(disturbance=mode, disturbance_gain=1.0))
    plain = GradientMPC(env, tiny_model, MPCSpec())
    for mpc in (corrected, plain):
        mpc.reset(env.goal)
    action = corrected.act(obs)
    with torch.no_grad():
        commands = corrected.task.to_grippers(torch.as_tensor(action)[None, None])
        expected = corrected.view.predict(corrected.state_tensor(obs), commands, None)[0, 0]
    obs, *_ = env.step(action)
    corrected.act(obs)
    plain.act(obs)
    state = corrected._observed
    error = state[0, :, :3] - expected
    assert float(error.abs().max()) > 0.0
    torch.testing.assert_close(corrected._disturbance, error)
    plan = torch.linspace(-0.6, 0.6, 30).view(1, 5, 6)
    with torch.no_grad():
        ours = corrected.predicted(state, plan)
        theirs = plain.predicted(state, plan, corrected._previous)
    steps = torch.ones(5) if mode == "offset" else torch.arange(1.0, 6.0)
    torch.testing.assert_close(ours - theirs, steps[None, :, None, None] * error, atol=1e-6, rtol=0)


@pytest.mark.parametrize(
    "option,needle",
    [("disturbance_gain: .nan", "disturbance_gain"), ("disturbance_gain: 0", "disturbance_gain"),
     ("disturbance_gain: 1.5", "disturbance_gain"), ("disturbance: always", "disturbance"),
     ("jacobian: half", "jacobian")],
)  # fmt: skip
def test_bad_jacobian_or_disturbance_exit_2_and_write_nothing(tmp_path, capsys, option, needle):
    """The planner's jacobian and disturbance options take their named values and a gain in
    (0, 1]: anything else in a run's spec is one line, exit 2, no run directory."""
    spec, out = tmp_path / "spec.yaml", tmp_path / "run"
    spec.write_text(f"mpc:\n  {option}\n")
    assert run_dlo(["online", "--spec", str(spec), "--out", str(out)]) == 2
    said = capsys.readouterr().err.strip()
    assert needle in said and len(said.splitlines()) == 1, said
    assert not out.exists()
