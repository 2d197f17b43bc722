"""Closed-loop planning: re-planning during an episode and plan repair."""

from __future__ import annotations

import numpy as np
import pytest

from cdrb_cli.envs.registry import CONTROLLERS, family_of
from cdrb_cli.methods.checkpoint import load_method
from cdrb_cli.methods.config import train_config
from cdrb_cli.seeding import STREAM_EVAL
from cdrb_cli.stages.configure import eval_config
from cdrb_cli.stages.evaluate import evaluate
from cdrb_cli.stages.plan import sample_plans
from cdrb_cli.stages.replan import deviation, plan_at, remainder, run_closed_loop
from cdrb_cli.stages.train import train
from tests.factories import RandomActions
from tests.test_train import tiny

PLANNERS = ("cdrb", "diffuser", "mlp")


@pytest.fixture(scope="module")
def models(small_data, tmp_path_factory):
    demos, buffer = small_data
    root = tmp_path_factory.mktemp("replan")
    out = {}
    for method in PLANNERS:
        b = buffer if method == "cdrb" else None
        cfg = train_config(demos, b, method, tiny(method, steps=20, checkpoint_every=20, stride=10))
        out[method] = train(demos, b, cfg, root / f"m-{method}.h5")
    return out


def test_remainder_and_plan_time():
    plan = np.arange(10 * 3, dtype=float).reshape(10, 3)
    state = np.array([-1.0, -2.0])
    rest = remainder(plan, 3.7, state)
    assert rest.shape == plan.shape
    np.testing.assert_array_equal(rest[1:7], plan[4:10])  # the plan from floor(3.7) on, after the current state
    np.testing.assert_array_equal(rest[7:], np.repeat(plan[-1:], 3, axis=0))  # padded with the last state
    np.testing.assert_array_equal(rest[0], [-1.0, -2.0, plan[3, 2]])  # the observation part is the current state
    np.testing.assert_allclose(plan_at(plan, 2.25), 0.75 * plan[2] + 0.25 * plan[3])
    np.testing.assert_array_equal(plan_at(plan, 99.0), plan[-1])
    np.testing.assert_array_equal(remainder(plan, 50.0, state)[1:], np.repeat(plan[-1:], 9, axis=0))


@pytest.mark.parametrize("method", PLANNERS)
def test_a_replanning_interval_beyond_the_episode_is_open_loop_exactly(models, tmp_path, method):
    model = models[method]
    never = evaluate(model, eval_config(model, episodes=3, seeds=[0, 1]), tmp_path / "never.h5")
    # the machinery alone: without the settings chosen for re-planning (the plan clock's look-ahead, best of 8)
    plain = {"avoid": "plain", "controller.look_ahead": 0}
    closed = evaluate(
        model, eval_config(model, episodes=3, seeds=[0, 1], replan="every:100000", **plain), tmp_path / "closed.h5"
    )
    a, b = never.arrays, closed.arrays
    assert (b["episodes/replans"] == 0).all()
    for name in ("success", "steps", "final_distance", "path_length", "executed_collision", "start", "goal"):
        np.testing.assert_array_equal(a[f"episodes/{name}"], b[f"episodes/{name}"], err_msg=name)
    for name in ("plan_in_wall_fraction", "plan_crosses_obstacle", "plan_max_jump"):
        np.testing.assert_array_equal(a[f"episodes/{name}"], b[f"episodes/{name}"], err_msg=name)
    np.testing.assert_array_equal(a["plans"], b["plans"])
    assert closed.manifest.config.replan.mode == "every" and never.manifest.config.replan.mode == "never"


def _closed_loop(model, replan, n=4, seed=0, aims=None):
    """Run ``n`` episodes of eval seed ``seed`` closed loop with the model's PD controller (gated clock), re-plans
    aiming where ``aims`` says (the goals when None)."""
    method = load_method(model)
    spec = model.manifest.env
    family = family_of(spec)
    episodes = family.draw_episodes(spec, n, seed, STREAM_EVAL)
    starts, goals = family.reset_states(spec, episodes)
    plans = sample_plans(method, starts, family.goal_state(spec, goals), 1, seed, batch_size=n)[0]
    entry = CONTROLLERS.get("pd")
    cfg = eval_config(model, episodes=n, seeds=[seed], **replan).replan
    runs = run_closed_loop(
        family,
        spec,
        method,
        episodes,
        plans,
        lambda env: entry.build(spec, env, entry.config(), method.config.stride),
        cfg,
        spec.episode_limit,
        (0, seed, 0),
        aims=aims,
    )
    return spec, family, runs


@pytest.mark.parametrize("method", PLANNERS)
@pytest.mark.parametrize("repair", [None, 2])
def test_every_n_steps_plans_from_the_current_state_to_the_same_goal(models, method, repair):
    spec, family, runs = _closed_loop(models[method], {"replan": "every:45", "replan.repair_k": repair})
    goal_states = family.goal_state(spec, np.stack([r.goal for r in runs]))
    for run, goal in zip(runs, goal_states):
        hits = np.flatnonzero(family.success(spec, run.states, run.goal))
        until = hits[0] if hits.size else spec.episode_limit
        # a plan at every multiple of 45 before the goal is reached (or the episode ends), none after
        expected = [t for t in range(45, spec.episode_limit, 45) if t <= until]
        assert run.plan_steps == [0, *expected]
        assert run.replans == len(expected)
        for t, plan in zip(run.plan_steps, run.plans):
            assert plan.shape == run.plans[0].shape
            np.testing.assert_array_equal(plan[0, : spec.obs_dim], run.states[t])  # pinned exactly to the state
            np.testing.assert_array_equal(plan[-1, : spec.obs_dim], goal)  # and to the same goal
        assert run.planning_seconds > 0


def test_deviation_replans_only_when_off_the_plan(models):
    model = models["diffuser"]
    _, _, far = _closed_loop(model, dict(replan="deviation:1000"))
    assert all(r.replans == 0 for r in far)  # nothing is 1 km off its plan
    spec, family, near = _closed_loop(model, dict(replan="deviation:0.000001"))
    for run in near:
        # every step is more than a micrometre off a tiny model's plan: a new plan each step until the goal
        gaps = np.diff(run.plan_steps)
        assert run.replans > 0 and (gaps == 1).all()
    # the trigger measures in the obstacle dimensions (positions), against the plan at the controller's clock
    plan = np.zeros((5, 4))
    plan[:, 0] = np.arange(5)
    state = np.array([2.5, 0.4, 9.0, 9.0])  # velocities are not positions
    assert np.isclose(deviation(spec, plan, 2.5, state), 0.4)


def test_cdrb_repair_degrades_the_previous_plan_with_the_ball_sampler(models, monkeypatch):
    """Repair at k: every non-pinned state of the restorer's first input is a buffer point within eps_k of the
    previous plan's state (or that state, when the ball is empty), and restoration runs k, k-1, ..., 1."""
    import torch

    from cdrb_cli.methods.cdrb import CDRB

    method = load_method(models["cdrb"])
    rng = np.random.default_rng(0)
    H, F = method.horizon, method.feature_dim
    previous = torch.as_tensor(method.points[rng.integers(0, len(method.points), (3, H))] + 0.01, dtype=torch.float32)
    start, goal = previous[:, 0, : method.obs_dim].clone(), previous[:, -1, : method.obs_dim].clone()
    seen = {}
    original = CDRB._restore

    def spy(self, x, start_, goal_, ks, rng_, sampler, keep):
        seen["x"], seen["ks"] = x.clone(), [int(k) for k in ks]
        return original(self, x, start_, goal_, ks, rng_, sampler, keep)

    monkeypatch.setattr(CDRB, "_restore", spy)
    for k in (1, 4, method.T - 1):
        res = method.repair(start, goal, previous, k, np.random.default_rng(k))
        assert seen["ks"] == list(range(k, 0, -1))
        x, prev = seen["x"].numpy(), previous.numpy()
        inner = x[:, 1:-1].reshape(-1, F)
        moved = np.linalg.norm(inner - prev[:, 1:-1].reshape(-1, F), axis=1)
        assert (moved < method.eps[k] + 1e-5).all()
        d = np.linalg.norm(inner[:, None] - method.points[None], axis=2).min(axis=1)
        unchanged = moved == 0
        assert (d[~unchanged] < 1e-6).all()  # every moved state is a buffer point
        np.testing.assert_array_equal(res.plans[:, 0, : method.obs_dim], start)  # pinned exactly
        np.testing.assert_array_equal(res.plans[:, -1, : method.obs_dim], goal)
    assert method.repairs and method.repair_steps() == method.T - 1
    res = method.repair(start, goal, previous, 6, np.random.default_rng(0), steps=3)
    assert seen["ks"] == [6, 4, 1]
    with pytest.raises(ValueError):
        method.repair(start, goal, previous, method.T, np.random.default_rng(0))


def test_diffuser_repair_noises_to_timestep_k_and_denoises_from_there(models, monkeypatch):
    import torch

    from cdrb_cli.methods.diffuser import Diffuser

    method = load_method(models["diffuser"])
    previous = torch.zeros((200, method.horizon, method.feature_dim)) + 0.3
    start, goal = previous[:, 0, : method.obs_dim].clone(), previous[:, -1, : method.obs_dim].clone()
    seen = {}
    original = Diffuser._denoise

    def spy(self, x, start_, goal_, sched, gen, sampler, keep):
        seen["x"], seen["t"] = x.clone(), [int(t) for t in sched.timesteps]
        return original(self, x, start_, goal_, sched, gen, sampler, keep)

    monkeypatch.setattr(Diffuser, "_denoise", spy)
    abar = method.train_sched.alphas_cumprod
    for k in (1, 5, method.T - 1):
        res = method.repair(start, goal, previous, k, np.random.default_rng(k))
        assert seen["t"] == list(range(k, -1, -1))
        inner = seen["x"][:, 1:-1].numpy()
        # q(x_k | x_0): mean sqrt(abar_k) x_0, std sqrt(1 - abar_k)
        assert abs(inner.mean() - 0.3 * float(abar[k]) ** 0.5) < 0.02
        assert abs(inner.std() - float(1 - abar[k]) ** 0.5) < 0.02
        np.testing.assert_array_equal(res.plans[:, 0, : method.obs_dim], start)
        np.testing.assert_array_equal(res.plans[:, -1, : method.obs_dim], goal)
    method.repair(start[:2], goal[:2], previous[:2], 6, np.random.default_rng(0), steps=3)
    assert seen["t"] == [6, 3, 0]


def test_mlp_repair_re_predicts(models):
    import torch

    method = load_method(models["mlp"])
    start = torch.zeros((2, method.obs_dim))
    goal = torch.ones((2, method.obs_dim)) * 0.5
    previous = torch.rand((2, method.horizon, method.feature_dim))
    a = method.repair(start, goal, previous, 3, np.random.default_rng(0)).plans
    b = method.sample(start, goal, np.random.default_rng(1)).plans
    np.testing.assert_array_equal(a.numpy(), b.numpy())
    assert not method.repairs


def test_eval_cli_closed_loop(models, tmp_path, cdrb):
    model = models["cdrb"].path
    out, pic = tmp_path / "e.h5", tmp_path / "replans.png"
    r = cdrb(
        "eval", model, "-n", "2", "--seeds", "0", "--replan", "every:60", "--set", "replan.repair_k=2",
        "--replan-plot", pic,
        "--out", out,
    )  # fmt: skip
    assert r.returncode == 0, r.stderr
    assert out.exists() and pic.exists() and pic.stat().st_size > 1000
    assert "re-plans" in r.stderr and "repair k=2" in r.stderr
    from cdrb_cli import artifacts

    ev = artifacts.load(out, "eval")
    assert ev.manifest.config.replan.repair_k == 2 and (ev.arrays["episodes/replans"] > 0).any()
    s = ev.manifest.summary
    assert np.isclose(s.replans_mean, ev.arrays["episodes/replans"].mean())
    assert np.isclose(s.planning_seconds_mean, ev.arrays["episodes/planning_seconds"].mean())
    rep = cdrb("report", out)
    assert rep.returncode == 0 and "re-plans" in rep.stdout, rep.stdout + rep.stderr


@pytest.mark.parametrize(
    "args, needle",
    [
        (["--replan", "sometimes:3"], "--replan sometimes:3: expected never, every:N or deviation:D"),
        (["--replan", "every:0"], "--replan every:0"),
        (["--replan", "every:x"], "--replan every:x: expected never"),
        (["--replan", "every:1_0"], "--replan every:1_0: expected never"),  # Python's int would read 10
        (["--replan", "every:\u0665"], "expected never"),  # an Arabic-Indic 5
        (["--replan", "deviation:nan"], "expected never"),
        (["--replan", "deviation:-1"], "--replan deviation:-1"),
        (["--set", "replan.repair_k=2"], "set a replan mode too"),
        (["--replan", "every:10", "--set", "replan.repair_k=999"], "--set replan.repair_k=999: the model has T = "),
        (["--replan", "every:10", "--set", "replan.repair_steps=3"], "repair_steps needs repair_k"),
        (["--replan-plot", "x.png"], "--replan-plot"),
        (["--set", "replan.every=5"], "replan"),
        (
            ["--replan", "every:10", "--set", "replan.repair_k=2", "--set", "replan.repair_steps=50"],
            "repair_steps 50 > repair_k 2",
        ),
        # a check across two settings names both, not only the last one given
        (
            ["--replan", "deviation:0.05", "--set", "replan.every=3"],
            "--replan deviation:0.05 with --set replan.every=3",
        ),
        # and only the settings its message names, not others of the same record
        (
            ["--set", "avoid.best_of=2", "--set", "avoid.route_clearance=0.1"],
            "error: --set avoid.route_clearance=0.1: route_clearance keeps routes",
        ),
    ],
)
def test_eval_cli_closed_loop_bad_inputs(models, tmp_path, cdrb, args, needle):
    r = cdrb("eval", models["cdrb"].path, "-n", "2", "--seeds", "0", "--out", tmp_path / "e.h5", *args)
    assert r.returncode == 2, r.stderr
    lines = [line for line in r.stderr.strip().splitlines() if line.strip()]
    assert needle in lines[0] and "Traceback" not in r.stderr, r.stderr
    assert not (tmp_path / "e.h5").exists()


def test_an_eval_from_before_closed_loop_reads_as_one_plan_per_episode(models, tmp_path):
    from cdrb_cli import artifacts
    from cdrb_cli.stages.results import episode_results

    model = models["mlp"]
    config = eval_config(model, episodes=2, seeds=[0])
    ev = evaluate(model, config, tmp_path / "e.h5")
    from cdrb_cli.artifacts.migrations import backfill_arrays

    old = {k: v for k, v in ev.arrays.items() if k not in ("episodes/replans", "episodes/planning_seconds")}
    read = backfill_arrays("eval", old)  # what reading a 2.3 file gives
    for r in episode_results(read):
        assert r.replans == 0 and r.planning_seconds == r.plan_seconds
    full = backfill_arrays("eval", ev.arrays)  # nothing replaced in a file that has every dataset
    assert full.keys() == ev.arrays.keys() and all(full[k] is ev.arrays[k] for k in full)
    # an open-loop eval config from before the replan field is the same config: the file stays up to date
    data = config.model_dump()
    del data["replan"]
    assert type(config).model_validate(data) == config
    assert artifacts.existing(tmp_path / "e.h5", "eval", config, [model]).up_to_date


@pytest.mark.parametrize("graph", ["transitions", "free-steps"])
def test_waypoints_lead_plans_toward_a_far_goal_one_reach_at_a_time(models, tmp_path, graph):
    """``replan.waypoint_reach``: the first plan aims at the point that far along the buffer route to the goal (the
    goal once it is that close), and so does every re-plan, from where the robot is then; the route goes along the
    model's transition graph (the default: no map read) or through buffer states joined by free steps."""
    from cdrb_cli.configs import ReplanConfig
    from cdrb_cli.stages.avoid import buffer_graph
    from cdrb_cli.stages.routes import TransitionRoutes, waypoint_aims

    model = models["cdrb"]
    reach = 1.5
    settings = {"replan.waypoint_reach": reach, "replan.waypoint_graph": graph}
    config = eval_config(model, episodes=4, seeds=[0], replan="every:45", **settings)
    ev = evaluate(model, config, tmp_path / "wp.h5")
    assert ev.manifest.config.replan.waypoint_reach == reach
    assert "waypoints 1.5 ahead" in ev.manifest.config.replan.label()
    method = load_method(model)
    spec = model.manifest.env
    family = family_of(spec)
    assert "buffer/graph/edges" in model.arrays  # a CDRB model carries its buffer's transition graph
    if graph == "transitions":
        routes = TransitionRoutes(spec, method.normalizer.unnormalize(method.points), method.buffer_graph[0])
    else:
        routes = buffer_graph(method, spec, config.avoid)
    aims = waypoint_aims(routes, spec, reach, method.feature_dim)
    starts, goals = ev.arrays["episodes/start"], ev.arrays["episodes/goal"]
    expected = aims(starts, family.goal_state(spec, goals))
    plans = ev.arrays["plans"]
    np.testing.assert_allclose(plans[:, -1, : spec.obs_dim], expected, atol=1e-5)  # the first plans end there
    far = np.linalg.norm(goals - starts[:, :2], axis=1) > reach
    assert far.any() and (np.linalg.norm(expected[far, :2] - starts[far, :2], axis=1) <= reach + 1e-6).all()
    with pytest.raises(ValueError, match="waypoint_reach"):
        ReplanConfig(waypoint_reach=1.0)


def test_re_plans_aim_where_the_aims_say(models):
    """run_closed_loop's ``aims``: each re-plan ends at the aim computed from the state it starts at."""
    model = models["cdrb"]
    spec = model.manifest.env
    shift = np.zeros(spec.obs_dim)
    shift[spec.goal_dims[0]] = 0.25
    spec, family, runs = _closed_loop(model, {"replan": "every:30"}, n=3, aims=lambda states, goals: goals + shift)
    goal_states = family.goal_state(spec, np.stack([r.goal for r in runs]))
    assert sum(r.replans for r in runs) > 0
    for run, goal in zip(runs, goal_states):
        for plan in run.plans[1:]:
            np.testing.assert_allclose(plan[-1, : spec.obs_dim], goal + shift)


def test_a_planner_without_a_buffer_takes_waypoints_through_a_route_buffer(models, small_data, tmp_path):
    """Diffuser carries no buffer: its waypoints route through ``avoid.route_buffer`` (the buffer of its demos,
    along that buffer's transition graph); without one the eval is refused in one line. A route buffer with nothing
    routing through it stays a mistake for `cdrb plan`."""
    from cdrb_cli.configs import AvoidConfig, PlanConfig
    from cdrb_cli.errors import BadInput
    from cdrb_cli.stages.avoid import route_states
    from cdrb_cli.stages.routes import TransitionRoutes, waypoint_aims

    _, buffer = small_data
    model = models["diffuser"]
    settings = {"replan.waypoint_reach": 1.5, "avoid.route_buffer": str(buffer.path)}
    config = eval_config(model, episodes=3, seeds=[0], replan="every:45", **settings)
    ev = evaluate(model, config, tmp_path / "wp.h5", route_buffer=buffer)
    method = load_method(model)
    spec = model.manifest.env
    routes = TransitionRoutes(spec, route_states(method, spec, buffer), buffer.graph()[0])
    aims = waypoint_aims(routes, spec, 1.5, method.feature_dim)
    starts, goals = ev.arrays["episodes/start"], ev.arrays["episodes/goal"]
    expected = aims(starts, family_of(spec).goal_state(spec, goals))
    np.testing.assert_allclose(ev.arrays["plans"][:, -1, : spec.obs_dim], expected, atol=1e-5)
    bare = eval_config(model, episodes=3, seeds=[0], replan="every:45", **{"replan.waypoint_reach": 1.5})
    with pytest.raises(BadInput, match="route_buffer"):
        evaluate(model, bare, tmp_path / "bare.h5")
    assert not (tmp_path / "bare.h5").exists()
    with pytest.raises(ValueError, match="avoid.route_buffer is what routes go through"):
        PlanConfig(sampler="ddpm", n=1, seed=0, avoid=AvoidConfig(route_buffer="b.h5"))


class _Recorder:
    """A policy that records the goals it is asked to act toward and stands still."""

    def __init__(self, act_dim: int):
        self.act_dim, self.seen = act_dim, []

    def reset(self, n, rng):
        self.seen = []

    def act(self, states, goals, rng):
        self.seen.append((np.array(states), np.array(goals)))
        return np.zeros((len(states), self.act_dim))


def test_a_policy_acts_toward_waypoints_given_anew_on_a_clock(small_data, tmp_path):
    """A closed-loop policy toward far goals: ``run_policy``'s aims give it the waypoint of the state it is in every
    ``every`` env steps and keep it in between; the waypoint as a goal is the one a planner's plans end at."""
    from cdrb_cli.stages.avoid import buffer_states
    from cdrb_cli.stages.evaluate import run_policy
    from cdrb_cli.stages.routes import TransitionRoutes, waypoint_aims, waypoint_goals

    _, buffer = small_data
    spec = buffer.manifest.env
    family = family_of(spec)
    routes = TransitionRoutes(spec, buffer_states(buffer, spec, spec.id), buffer.graph()[0])
    goals_of = waypoint_goals(routes, spec, 1.5)
    episodes = family.draw_episodes(spec, 3, 0, STREAM_EVAL)
    policy = _Recorder(spec.action_dim)
    run_policy(family, spec, episodes, policy, 12, np.random.default_rng(0), (goals_of, 5))
    _, goals = family.reset_states(spec, episodes)
    assert len(policy.seen) == 12
    for t, (_, given) in enumerate(policy.seen):
        aimed_at = t - t % 5
        np.testing.assert_allclose(given, goals_of(policy.seen[aimed_at][0], goals))
    first = policy.seen[0]
    np.testing.assert_allclose(
        family.goal_state(spec, first[1]),
        waypoint_aims(routes, spec, 1.5, spec.obs_dim)(first[0], family.goal_state(spec, goals)),
    )
    far = np.linalg.norm(goals - first[0][:, spec.goal_dims], axis=1) > 1.5
    assert far.any() and not np.allclose(first[1][far], goals[far])  # far goals get a waypoint, not the goal


def test_a_policy_eval_toward_waypoints_reads_its_route_buffer(small_data, tmp_path):
    """`cdrb eval` of Diffusion BC with ``replan.waypoint_reach``: the route buffer is a parent of the eval; without
    one, or with a re-planning mode that is not a clock, it is refused in one line and writes nothing."""
    from cdrb_cli.errors import BadInput
    from tests.test_policies import TINY_BC

    demos, buffer = small_data
    cfg = train_config(demos, None, "diffusion-bc", {**TINY_BC, "steps": 10, "checkpoint_every": 10})
    model = train(demos, None, cfg, tmp_path / "bc.h5")
    settings = {"replan.waypoint_reach": 1.5, "avoid.route_buffer": str(buffer.path)}
    config = eval_config(model, episodes=2, seeds=[0], replan="every:20", **settings)
    ev = evaluate(model, config, tmp_path / "wp.h5", route_buffer=buffer)
    assert buffer.sha256 in [p.sha256 for p in ev.manifest.parents]
    assert ev.manifest.config.replan.waypoint_reach == 1.5
    bare = eval_config(model, episodes=2, seeds=[0], replan="every:20", **{"replan.waypoint_reach": 1.5})
    with pytest.raises(BadInput, match="route_buffer"):
        evaluate(model, bare, tmp_path / "bare.h5")
    drift = eval_config(model, episodes=2, seeds=[0], replan="deviation:0.5", **settings)
    with pytest.raises(BadInput, match="replan.mode"):
        evaluate(model, drift, tmp_path / "drift.h5", route_buffer=buffer)
    assert not (tmp_path / "bare.h5").exists() and not (tmp_path / "drift.h5").exists()


@pytest.mark.parametrize("env_id", ["maze-tight", "fetch-pick-place-obstacle"])
def test_envs_reused_batch_after_batch_run_as_fresh_ones(env_id):
    """An eval reuses its lockstep envs from batch to batch: episodes run in envs that ran other episodes before
    (and one env more than they need) give exactly what fresh envs give."""
    from cdrb_cli.envs.registry import make_spec
    from cdrb_cli.stages.evaluate import run_policy

    spec = make_spec(env_id)
    family = family_of(spec)
    first, then = family.draw_episodes(spec, 4, 0, STREAM_EVAL), family.draw_episodes(spec, 3, 1, STREAM_EVAL)
    policy = RandomActions(spec.action_dim)

    def states(episodes, envs=None):
        runs, _, _ = run_policy(family, spec, episodes, policy, 30, np.random.default_rng(5), envs=envs)
        return np.stack([r.states for r in runs])

    pool = [family.make_env(spec) for _ in range(4)]
    try:
        states(first, pool)
        reused = states(then, pool)
    finally:
        for env in pool:
            env.close()
    fresh = states(then)
    assert np.ptp(fresh[:, -1, :2], axis=0).max() > 0  # the episodes went somewhere
    np.testing.assert_array_equal(reused, fresh)
