"""The Fetch family: collision geometry against its definition, walls that are physics, draws, experts, collect."""

from __future__ import annotations

import numpy as np
import pytest

from cdrb_cli import artifacts
from cdrb_cli.envs.fetch import TASKS
from cdrb_cli.envs.fetch.geometry import (
    BLOCK_HALF,
    CONTACT_TOLERANCE,
    FINGERS_CLOSED,
    GRIP_ABOVE_TABLE,
    GRIPPER_LINK,
    TABLE_TOP,
    TABLE_XY,
)
from cdrb_cli.envs.fetch.tasks import side
from cdrb_cli.envs.geometry import segment_box_distance
from cdrb_cli.envs.registry import EXPERTS, family_of, make_spec
from cdrb_cli.seeding import STREAM_COLLECT
from cdrb_cli.stages.collect import rollout

SIX = [i for i in TASKS if not i.endswith("-mixed")]
EPS = 0.001


def _state(spec, grip, block=None, opening=0.0):
    s = np.zeros(spec.obs_dim)
    s[:3] = grip
    if block is not None:
        s[3:6] = block
    else:
        s[3:6] = (1.30, 0.45, TABLE_TOP + BLOCK_HALF) if spec.obs_dim > 10 else 0.0
    if spec.obs_dim > 10:
        s[9] = s[10] = opening
    return s


def _free_block(spec):
    return (1.30, 0.45, TABLE_TOP + BLOCK_HALF) if spec.obs_dim > 10 else None


@pytest.mark.parametrize("env_id", ["fetch-reach-obstacle", "fetch-push-obstacle", "fetch-pick-place-obstacle"])
def test_fingers_just_inside_and_outside_each_wall_face(env_id):
    spec = make_spec(env_id)
    fam = family_of(spec)
    (_, _, f_lo), (_, f_hi_y, _) = FINGERS_CLOSED[0], FINGERS_CLOSED[1]
    for w in spec.scene.walls:
        # the fingers' lower part reaches into the wall's top 1 cm; the link (5 cm above the grip site) stays above
        z = w.high[2] - 0.01
        x = w.center[0]
        face = w.low[1] - f_hi_y + CONTACT_TOLERANCE  # grip y at which the fingers touch the near face
        inside = _state(spec, (x, face + EPS, z), _free_block(spec))
        outside = _state(spec, (x, face - EPS, z), _free_block(spec))
        assert fam.in_collision(spec, np.stack([inside, outside])).tolist() == [True, False]
        # and from above: finger tips just into the top / just over it
        top = w.high[2] - f_lo - CONTACT_TOLERANCE
        over, into = (_state(spec, (x, w.center[1], top + d), _free_block(spec)) for d in (EPS, -EPS))
        assert fam.in_collision(spec, np.stack([into, over])).tolist() == [True, False]


def test_the_gripper_link_counts_with_its_extent():
    spec = make_spec("fetch-pick-place-obstacle")
    fam = family_of(spec)
    (w,) = spec.scene.walls
    lo, hi = np.array(GRIPPER_LINK[0]), np.array(GRIPPER_LINK[1])
    # the grip site 10 cm below the top: the link (from +4.9 cm) overlaps the wall in z; beside the wall in y
    z = w.high[2] - 0.10
    face = w.high[1] - lo[1] - CONTACT_TOLERANCE  # grip y where the link's low side touches the far face
    near, far = (_state(spec, (w.center[0], face + d, z), _free_block(spec)) for d in (-EPS, EPS))
    assert fam.in_collision(spec, np.stack([near, far])).tolist() == [True, False]
    assert hi[2] > 0.15  # the link stands well above the grip site


def test_open_fingers_are_wider_than_closed_ones():
    spec = make_spec("fetch-pick-place-obstacle")
    fam = family_of(spec)
    (w,) = spec.scene.walls
    y = w.low[1] - 0.030  # 3 cm from the face: closed fingers (1.6 cm) clear, open ones (6.6 cm) not
    z = w.high[2] - 0.01
    closed = _state(spec, (w.center[0], y, z), _free_block(spec), opening=0.0)
    opened = _state(spec, (w.center[0], y, z), _free_block(spec), opening=0.05)
    assert fam.in_collision(spec, np.stack([closed, opened])).tolist() == [False, True]
    # a step between two closed states does not count the open width, a step toward an open one does
    a = _state(spec, (w.center[0] - 0.05, y, z), _free_block(spec))
    assert not fam.path_in_collision(spec, np.stack([a, closed])[None])[0]
    assert fam.path_in_collision(spec, np.stack([a, opened])[None])[0]


def test_the_block_counts_by_its_inscribed_ball_and_must_stay_on_the_table():
    spec = make_spec("fetch-push-obstacle")
    fam = family_of(spec)
    (w,) = spec.scene.walls
    r = BLOCK_HALF - CONTACT_TOLERANCE
    grip = (1.45, 0.45, 0.6)
    z = TABLE_TOP + BLOCK_HALF
    # beside a face, and diagonally off a vertical edge (a box test would flag the corner point too early)
    face_in, face_out = (_state(spec, grip, (w.center[0], w.low[1] - r + d, z)) for d in (EPS, -EPS))
    corner = np.array([w.high[0], w.low[1]])
    diag = np.array([1.0, -1.0]) / np.sqrt(2)
    c_in, c_out = (_state(spec, grip, (*(corner + diag * (r + d)), z)) for d in (-EPS, EPS))
    box_corner = _state(spec, grip, (*(corner + np.array([r, -r]) * 0.9), z))  # inside the box hull, outside the ball
    off_table = _state(spec, grip, (TABLE_XY[0][0] - 0.01, 0.6, z))
    sunk = _state(spec, grip, (1.3, 0.5, TABLE_TOP - 0.01))
    got = fam.in_collision(spec, np.stack([face_in, face_out, c_in, c_out, box_corner, off_table, sunk]))
    assert got.tolist() == [True, False, True, False, False, True, True]


def test_the_gripper_may_not_go_into_the_table():
    spec = make_spec("fetch-reach")
    fam = family_of(spec)
    ok, low = (_state(spec, (1.3, 0.75, TABLE_TOP + GRIP_ABOVE_TABLE + d)) for d in (EPS, -EPS))
    assert fam.in_collision(spec, np.stack([ok, low])).tolist() == [False, True]


@pytest.mark.parametrize("env_id", ["fetch-reach-obstacle", "fetch-push-obstacle", "fetch-pick-place-obstacle"])
def test_a_step_that_jumps_through_a_wall_is_caught(env_id):
    spec = make_spec(env_id)
    fam = family_of(spec)
    w = spec.scene.walls[0]
    z = w.center[2] if spec.scene.task == "reach" else TABLE_TOP + BLOCK_HALF + 0.02
    if spec.scene.task == "reach":
        a, b = _state(spec, (w.center[0], w.low[1] - 0.12, z)), _state(spec, (w.center[0], w.high[1] + 0.12, z))
    else:  # the block jumps across the wall, the gripper stays high and free
        grip = (1.3, 0.75, 0.95)
        zb = TABLE_TOP + BLOCK_HALF
        a = _state(spec, grip, (w.center[0], w.low[1] - 0.08, zb))
        b = _state(spec, grip, (w.center[0], w.high[1] + 0.08, zb))
    path = np.stack([a, b])
    assert not fam.in_collision(spec, path).any()
    assert fam.path_in_collision(spec, path[None]).tolist() == [True]
    # the same two states joined around the wall's end are free
    end = w.high[0] + 0.07
    around = np.stack([a, a.copy(), b.copy(), b])
    dims = slice(0, 3) if spec.scene.task == "reach" else slice(3, 6)
    around[1, dims][0] = end
    around[2, dims][0] = end
    assert fam.path_in_collision(spec, around[None]).tolist() == [False]


@pytest.mark.parametrize("env_id", list(TASKS))
def test_each_env_resets_steps_and_has_real_walls(env_id):
    import mujoco

    spec = make_spec(env_id)
    fam = family_of(spec)
    env = fam.make_env(spec)
    try:
        walls = [
            g
            for g in range(env.env.model.ngeom)
            if (mujoco.mj_id2name(env.env.model, mujoco.mjtObj.mjOBJ_GEOM, g) or "").startswith("cdrb_wall")
        ]
        assert len(walls) == len(spec.scene.walls)
        assert all(env.env.model.geom_contype[g] and env.env.model.geom_conaffinity[g] for g in walls)
        for ep in fam.draw_episodes(spec, 2, 0, STREAM_COLLECT):
            s, goal = env.reset(ep)
            assert s.shape == (spec.obs_dim,) and goal.shape == (3,)
            assert np.allclose(goal, ep.goal)
            assert np.allclose(s[:3], spec.scene.home, atol=0.003)  # every episode starts at home
            if ep.start:
                assert np.allclose(s[3:5], ep.start, atol=1e-6)
            assert not fam.in_collision(spec, s[None])[0]
            rng = np.random.default_rng(0)
            for _ in range(3):
                s = env.step(rng.uniform(-1, 1, 4))
            assert np.all(np.isfinite(s))
    finally:
        env.close()


@pytest.mark.parametrize("env_id", ["fetch-reach-obstacle", "fetch-pick-place-obstacle"])
def test_robot_joints_read_by_address_are_the_stock_observation(env_id):
    """The env reads the robot joints by their addresses, looked up once: the same arrays as gymnasium-robotics'
    own lookup by name, step after step."""
    import gymnasium_robotics.utils.mujoco_utils as stock

    spec = make_spec(env_id)
    fam = family_of(spec)
    env = fam.make_env(spec)
    try:
        u = env.env
        assert u._utils is not stock and u._utils.get_site_xpos is stock.get_site_xpos
        env.reset(fam.draw_episodes(spec, 1, 0, STREAM_COLLECT)[0])
        rng = np.random.default_rng(1)
        for _ in range(20):
            env.step(rng.uniform(-1, 1, 4))
            ours = u._utils.robot_get_obs(u.model, u.data, u._model_names.joint_names)
            theirs = stock.robot_get_obs(u.model, u.data, u._model_names.joint_names)
            for a, b in zip(ours, theirs):
                assert a.shape == b.shape and a.dtype == b.dtype
                np.testing.assert_array_equal(a, b)
    finally:
        env.close()


def test_walls_stop_the_gripper():
    """Driving the gripper into a wall at full speed: the wall holds (a post-hoc check would let it through)."""
    spec = make_spec("fetch-reach-obstacle")
    fam = family_of(spec)
    env = fam.make_env(spec)
    try:
        env.reset(fam.draw_episodes(spec, 1, 0, STREAM_COLLECT)[0])
        far_side = min(w.low[1] for w in spec.scene.walls)
        for _ in range(25):
            s = env.step(np.array([0.0, -1.0, 0.0, 0.0]))
        assert s[1] > far_side  # still inside the corridor
    finally:
        env.close()


@pytest.mark.parametrize("env_id", list(TASKS))
def test_draws_avoid_walls_are_seeded_and_cross_when_asked(env_id):
    spec = make_spec(env_id)
    fam = family_of(spec)
    eps = fam.draw_episodes(spec, 40, 3, STREAM_COLLECT)
    assert eps == fam.draw_episodes(spec, 40, 3, STREAM_COLLECT)
    assert eps != fam.draw_episodes(spec, 40, 4, STREAM_COLLECT)
    goals = fam.goal_state(spec, np.array([e.goal for e in eps]))
    if spec.scene.task == "reach":
        assert not fam.in_collision(spec, goals).any()
    else:
        blocks = np.array([[*e.start, TABLE_TOP + BLOCK_HALF] for e in eps])
        high = _state(spec, (1.3, 0.75, 0.95))
        states = np.repeat(high[None], 2 * len(eps), axis=0)
        states[:, 3:6] = np.concatenate([blocks, np.array([e.goal for e in eps])])
        assert not fam.in_collision(spec, states).any()
        # footprints stay edge_margin inside the table's edge (an overshooting push must not drop the block)
        xy = np.concatenate([blocks[:, :2], np.array([e.goal for e in eps])[:, :2]])
        inset = BLOCK_HALF + spec.scene.edge_margin
        for axis, (lo, hi) in enumerate(TABLE_XY):
            assert np.all((xy[:, axis] >= lo + inset) & (xy[:, axis] <= hi - inset)), axis
    if spec.scene.cross:
        for e in eps:
            start = np.array(spec.scene.home) if spec.scene.task == "reach" else np.array([*e.start, 0.0])
            assert side(spec.scene, np.array(e.goal)) != side(spec.scene, start)


@pytest.mark.parametrize("env_id", ["fetch-reach-obstacle", "fetch-push-obstacle", "fetch-pick-place-obstacle"])
def test_anywhere_starts_the_gripper_elsewhere_clear_of_every_wall(env_id):
    """`--protocol anywhere`: the stock block/goal draws, the gripper started at a seeded point of the workspace,
    reached (within 1 cm) and at rest, the whole arm touching no wall there, clear of the block; the expert still
    gets to the goal from there."""
    spec = make_spec(env_id)
    fam = family_of(spec)
    stock = fam.draw_episodes(spec, 8, 1, STREAM_COLLECT)
    eps = fam.draw_protocol_episodes(spec, 6, 1, STREAM_COLLECT, "anywhere")
    assert eps == fam.draw_protocol_episodes(spec, 6, 1, STREAM_COLLECT, "anywhere")
    n_block = 0 if spec.scene.task == "reach" else 2
    by_seed = {e.seed: e for e in stock}
    assert all(e.seed in by_seed and e.goal == by_seed[e.seed].goal for e in eps)  # kept draws of the stream
    assert all(e.start[:n_block] == by_seed[e.seed].start for e in eps)
    env = fam.make_env(spec)
    entry = EXPERTS.get("fetch-scripted")
    expert = entry.build(spec, entry.configure(None))
    try:
        grips = []
        for ep in eps:
            state, _ = env.reset(ep)
            grip = np.array(ep.start[n_block:])
            assert np.linalg.norm(state[:3] - grip) < 0.01
            assert not env.robot_contacts() and not fam.in_collision(spec, state[None])[0]
            assert np.abs(state[-5:-2]).max() < 1e-3  # the grip site at rest
            if n_block:
                assert np.linalg.norm(state[:3] - state[3:6]) >= 0.09
            grips.append(grip)
        assert np.linalg.norm(np.array(grips) - np.array(spec.scene.home), axis=1).min() > 0.01
        assert np.ptp(np.array(grips), axis=0).min() > 0.05  # spread over the workspace, not one pose
        ok = [rollout(env, expert, spec, ep, spec.episode_limit)[3] for ep in eps[:3]]
        assert sum(ok) >= 2, ok
        env.reset(by_seed[eps[0].seed])  # a stock episode after one from anywhere starts at home again
        assert np.linalg.norm(env.observe()[:3] - np.array(spec.scene.home)) < 0.01
    finally:
        env.close()


def test_routes_around_a_wall_end_turn_where_the_clearance_holds():
    """A goal beside the wall's end: the route turns outside the clearance zone, so its last leg does not run along
    the wall at the end legs' smaller margin (a drifting block would graze it)."""
    spec = make_spec("fetch-push-obstacle")
    entry = EXPERTS.get("fetch-scripted")
    router = entry.build(spec, entry.configure(None)).block_router
    z = TABLE_TOP + BLOCK_HALF
    a, b = np.array([1.25, 0.856, z]), np.array([1.468, 0.697, z])  # b: y- side, past the x+ end, near the face
    centers, halves = router.hard  # where the block touches the wall

    def gap(p, q):  # the least distance of a leg from the wall
        return float(segment_box_distance(p[None], q[None], centers, halves)[0])

    straight = gap(np.array([1.10, b[1], z]), b)  # a leg turning at b's own y runs along the wall's face
    assert straight < 0.015
    for name in ("around x-", "around x+"):
        *_, turn, end = router.options(a, b, ["around"])[name]
        assert np.array_equal(end, b)
        assert turn[1] < b[1]  # turned short of the face, outside the clearance zone
        assert not router.blocked(turn, turn)
        assert gap(turn, b) > straight + 0.005  # the last leg closes in on the wall only near its end
    far = np.array([1.30, 0.62, z])  # an end already outside the zone keeps its own y
    assert router.options(a, far, ["around"])["around x-"][-2][1] == far[1]


@pytest.mark.parametrize("env_id", SIX)
def test_the_scripted_expert_succeeds_without_touching_anything(env_id):
    spec = make_spec(env_id)
    fam = family_of(spec)
    entry = EXPERTS.get("fetch-scripted")
    expert = entry.build(spec, entry.configure(None))
    env = fam.make_env(spec)
    try:
        for ep in fam.draw_episodes(spec, 4, 0, STREAM_COLLECT):
            states, actions, goal, ok = rollout(env, expert, spec, ep, spec.episode_limit)
            assert ok, f"{env_id}: episode {ep.seed} failed"
            assert len(states) == spec.episode_limit + 1  # fixed-length episodes
            assert not fam.path_in_collision(spec, states[None])[0]
            assert fam.distance(spec, states[-1], goal) <= spec.success_radius  # still at the goal at the end
            assert np.all(np.abs(actions) <= 1.0)
    finally:
        env.close()


def test_collect_fetch_end_to_end_with_routes_and_pictures(tmp_path):
    from tests.conftest import run_cdrb as cdrb  # a fresh process: MuJoCo picks its renderer once per process

    out, pic = tmp_path / "demos.h5", tmp_path / "demos.png"
    gifs = tmp_path / "gifs"
    r = cdrb(
        "collect", "fetch-pick-place-obstacle", "-n", "12", "--seed", "2", "--out", out, "--plot", pic,
        "--video", gifs, "--videos", "1",
    )  # fmt: skip
    assert r.returncode == 0, r.stderr
    assert len(list(gifs.glob("demo_00_*.gif"))) == 1
    assert "GIF(s) drawn with MuJoCo" in r.stderr or "GIF(s) drawn with matplotlib" in r.stderr
    assert r.stdout.strip() == str(out)
    demos = artifacts.load(out, "demos")
    s = demos.manifest.summary
    assert s.states_in_walls == 0 and s.success_rate >= 0.9
    assert demos.observations.shape[1] == 25 and demos.manifest.env.scene.family == "fetch"
    routes = {label for group in s.routes.values() for label in group}
    assert len(routes) >= 2  # over and around both occur
    assert pic.stat().st_size > 10_000


def test_collect_set_expert_routes_keeps_one_route_kind(tmp_path, cdrb):
    """`cdrb collect --set expert.routes=...` changes the demonstrations as asked and is recorded: with "over"
    only, every Reach Obstacle demo that leaves the corridor does so above the walls' top, never past their ends."""
    out = tmp_path / "demos.h5"
    r = cdrb(
        "collect", "fetch-reach-obstacle", "-n", "8", "--seed", "1", "--workers", "1",
        "--set", 'expert.routes=["over"]', "--out", out,
    )  # fmt: skip
    assert r.returncode == 0, r.stderr
    demos = artifacts.load(out, "demos")
    assert demos.manifest.config.expert.routes == ["over"]
    s = demos.manifest.summary
    assert s.success_rate == 1.0 and s.states_in_walls == 0
    assert {label for group in s.routes.values() for label in group} == {"over"}
    walls = demos.manifest.env.scene.walls
    y_lo, y_hi = min(w.center[1] for w in walls), max(w.center[1] for w in walls)
    top = max(float(w.high[2]) for w in walls)
    x_lo, x_hi = min(float(w.low[0]) for w in walls), max(float(w.high[0]) for w in walls)
    st, ln = demos.arrays["episodes/start"], demos.arrays["episodes/length"]
    for s0, n in zip(st, ln):
        grip = demos.observations[s0 : s0 + n, :3]
        inside = (grip[:, 1] > y_lo) & (grip[:, 1] < y_hi)
        assert inside[0] and not inside[-1]  # a cross variant: every demo leaves the corridor
        i = int(np.argmax(~inside))  # the first state past a wall's plane
        assert max(grip[i - 1, 2], grip[i, 2]) > top  # above the top, not around an end
        assert x_lo < grip[i, 0] < x_hi
    # bad settings: one line, exit 2, nothing written
    cases = [
        ("expert.routes=over", "valid list"),
        ('expert.routes=["sideways"]', "'over' or 'around'"),
        ("expert.routes=[]", "at least 1 item"),
        ('expert.routes=["over","over"]', "each route kind once"),
        ("expert.nope=1", "unknown setting 'expert.nope'"),
        ("episodes=3", "sets expert.<field>"),
        ("expert.kind=sac", "sets expert.<field>"),
        ("expert.clearance=-1", "greater than or equal to 0"),
    ]
    for item, needle in cases:
        bad = tmp_path / "bad.h5"
        r = cdrb("collect", "fetch-reach-obstacle", "-n", "2", "--set", item, "--out", bad)
        assert r.returncode == 2, (item, r.stderr)
        assert needle in r.stderr and "Traceback" not in r.stderr, r.stderr
        assert len(r.stderr.strip().splitlines()) == 1 and not bad.exists()
    # a field that --policy sets (the file and its hash) is not a --set field
    policy = tmp_path / "policy.zip"
    policy.write_bytes(b"not read: refused before loading")
    r = cdrb(
        "collect", "fetch-reach", "--expert", "sac", "--policy", policy, "-n", "2",
        "--set", "expert.policy_sha256=0", "--out", tmp_path / "bad.h5",
    )  # fmt: skip
    assert r.returncode == 2 and "comes from --policy" in r.stderr and not (tmp_path / "bad.h5").exists(), r.stderr
    listed = cdrb("config", "collect")
    assert listed.returncode == 0 and "expert.routes" in listed.stdout and "expert.clearance" in listed.stdout


def test_fetch_bad_inputs_get_one_line_errors(tmp_path, cdrb):
    cases = [
        (["collect", "fetch-pushh", "-n", "2"], "unknown environment"),
        (["collect", "fetch-push", "--maze-map", tmp_path / "m.txt", "-n", "2"], "--maze-map"),
        (["collect", "fetch-push", "--expert", "planner", "-n", "2"], "not an expert of the fetch"),
        (["collect", "maze", "--expert", "fetch-scripted", "-n", "2"], "not an expert of the pointmaze"),
    ]
    (tmp_path / "m.txt").write_text("###\n#S#\n#G#\n###\n")
    for args, needle in cases:
        r = cdrb(*args, "--out", tmp_path / "x.h5")
        assert r.returncode == 2, (args, r.stderr)
        assert needle in r.stderr and "Traceback" not in r.stderr
        assert len(r.stderr.strip().splitlines()) <= 2
        assert not (tmp_path / "x.h5").exists()


def test_fetch_gym_env_for_rl_experts():
    spec = make_spec("fetch-push-obstacle")
    env = family_of(spec).make_gym_env(spec, 0)
    try:
        obs, _ = env.reset(seed=5)
        assert obs["observation"].shape == (25,) and obs["desired_goal"].shape == (3,)
        assert not family_of(spec).in_collision(spec, obs["observation"][None])[0]
        obs, reward, terminated, truncated, info = env.step(env.action_space.sample())
        assert reward in (0.0, -1.0)
    finally:
        env.close()


def test_sac_her_expert_for_fetch_tiny_budget(tmp_path, cdrb):
    """`cdrb expert train` on a Fetch task (tiny budget: the real cost is in docs/environments.md), then collect."""
    policy = tmp_path / "push.zip"
    r = cdrb("expert", "train", "fetch-push-obstacle", "--steps", "150", "--out", policy, "--seed", "0")
    assert r.returncode == 0, r.stderr
    out = tmp_path / "sac.h5"
    r = cdrb("collect", "fetch-push-obstacle", "--expert", "sac", "--policy", policy, "-n", "2", "--out", out)
    assert r.returncode == 0, r.stderr
    demos = artifacts.load(out, "demos")
    assert demos.manifest.config.expert.kind == "sac" and demos.observations.shape[1] == 25


@pytest.mark.parametrize(
    ("env_id", "controller"),
    [
        ("fetch-push", "fetch-track"),
        ("fetch-push", "fetch-push-path"),
        ("fetch-pick-place", "fetch-track"),
        ("fetch-reach", "fetch-track"),
    ],
)
def test_controllers_execute_the_experts_own_plans(env_id, controller):
    """A controller's ceiling: the expert's states, cut to the plan a model would make, executed from the same
    reset, reach the goal (docs/results/controller_ceiling.csv measures it on 100 episodes per task)."""
    from cdrb_cli.data import first_window
    from cdrb_cli.envs.registry import CONTROLLERS
    from cdrb_cli.stages.evaluate import run_episode

    spec = make_spec(env_id)
    fam = family_of(spec)
    entry = EXPERTS.get("fetch-scripted")
    expert = entry.build(spec, entry.configure(None))
    c = CONTROLLERS.get(controller)
    env = fam.make_env(spec)
    try:
        ctl = c.build(spec, env, c.config(), spec.plan_stride)
        for ep in fam.draw_episodes(spec, 3, 0, STREAM_COLLECT):
            obs, goal = env.reset(ep)
            expert.reset(obs, goal, np.random.default_rng(ep.seed))
            demo = run_episode(env, spec, ep, lambda o, t: expert.act(o), spec.episode_limit)
            ctl.reset(first_window(demo.states, spec.horizon, spec.plan_stride))
            run = run_episode(env, spec, ep, ctl.act, spec.episode_limit)
            assert run.success, (env_id, controller, ep.seed)
            if controller == "fetch-push-path" or spec.scene.task != "push":
                assert not run.collision  # (tracking the pusher's grip alone may later shove the block off the table)
            if fam.success(spec, demo.states[:1], goal).any():
                continue  # the block starts at its goal
            # a plan that goes nowhere is not executed as a success (the controller follows the plan, not the goal)
            ctl.reset(np.repeat(demo.states[:1], spec.horizon, axis=0))
            assert not run_episode(env, spec, ep, ctl.act, spec.episode_limit).success
    finally:
        env.close()


def test_push_path_controller_is_for_push_only(tmp_path):
    from cdrb_cli.envs.registry import CONTROLLERS
    from cdrb_cli.errors import BadInput

    spec = make_spec("fetch-pick-place")
    c = CONTROLLERS.get("fetch-push-path")
    with pytest.raises(BadInput, match="not a Push task"):
        c.build(spec, None, c.config(), 1)


def test_plan_and_eval_on_fetch_from_the_cli(tmp_path, cdrb):
    """Collect -> cluster -> train (tiny) -> plan (top and side views) -> eval on Push Obstacle, with start and goal
    pinned on their own dims, and one-line errors for a start on a Push task and a goal inside the wall."""
    from tests.test_train import TINY_FLAGS

    demos, buffer, model = tmp_path / "d.h5", tmp_path / "b.h5", tmp_path / "m.h5"
    assert cdrb("collect", "fetch-push-obstacle", "-n", "8", "--seed", "1", "--out", demos).returncode == 0
    assert cdrb("cluster", demos, "--k", "30", "--seed", "0", "--out", buffer).returncode == 0
    r = cdrb("train", demos, "--buffer", buffer, "--method", "cdrb", *TINY_FLAGS, "--steps", "20", "--out", model)
    assert r.returncode == 0, r.stderr
    plans, pic = tmp_path / "p.h5", tmp_path / "p.png"
    r = cdrb("plan", model, "--pairs", "2", "-n", "2", "--seed", "3", "--out", plans, "--plot", pic)
    assert r.returncode == 0, r.stderr
    a = artifacts.load(plans, "plans").arrays
    spec = make_spec("fetch-push-obstacle")
    starts, goals = np.repeat(a["starts"], 2, axis=0), np.repeat(a["goals"], 2, axis=0)  # 2 plans per pair
    np.testing.assert_array_equal(a["plans"][:, 0, :6], starts[:, :6])  # gripper and block at the start
    np.testing.assert_array_equal(a["plans"][:, -1, 3:6], goals[:, 3:6])  # the block at the goal
    assert a["plans"].shape[1] == 16 and spec.plan_stride == 2
    assert pic.stat().st_size > 10_000
    one = tmp_path / "one.h5"  # a start the family understands: the block's x,y, the gripper at home
    r = cdrb("plan", model, "--start", "1.30,0.62", "--goal", "1.30,0.88,0.425", "--out", one)
    assert r.returncode == 0, r.stderr
    p = artifacts.load(one, "plans").arrays["plans"][0]
    np.testing.assert_allclose(p[0, :3], spec.scene.home, atol=0.01)
    np.testing.assert_allclose(p[0, 3:5], [1.30, 0.62], atol=0.002)
    np.testing.assert_array_equal(p[-1, 3:6], np.float32([1.30, 0.88, 0.425]))
    for args, needle in [
        (["--start", "1.3,0.6,0.42", "--goal", "1.3,0.9,0.425"], "expected the block's x,y"),
        (["--start", "1.3,0.75", "--goal", "1.3,0.9,0.425"], "would overlap a wall or leave the table"),
        (["--start", "1.3,0.6", "--goal", "1.3,0.75,0.425"], "would overlap a wall or leave the table"),
        (["--start", "1.7,0.6", "--goal", "1.3,0.9,0.425"], "would overlap a wall or leave the table"),
        (["--start", ",".join(["nan"] * 25), "--goal", "1.3,0.9,0.425"], "not a list of numbers"),
        (["--start", "1.3,x", "--goal", "1.3,0.9,0.425"], "not a list of numbers"),
    ]:
        r = cdrb("plan", model, *args, "--out", tmp_path / "bad.h5")
        assert r.returncode == 2 and needle in r.stderr and r.stderr.count("\n") == 1, r.stderr
        assert not (tmp_path / "bad.h5").exists()
    ev = tmp_path / "e.h5"
    r = cdrb("eval", model, "--episodes", "2", "--seeds", "0", "--set", "controller=fetch-push-path", "--out", ev)
    assert r.returncode == 0, r.stderr
    e = artifacts.load(ev, "eval")
    assert e.manifest.config.controller.name == "fetch-push-path" and len(e.arrays["episodes/success"]) == 2
    # a box put down after training: plan and eval run among it, the model unchanged, and record the scene
    box = tmp_path / "box.toml"
    box.write_text("name = 'post'\n[[boxes]]\ncenter = [1.15, 0.95, 0.45]\nhalf = [0.03, 0.03, 0.05]\n")
    r = cdrb(
        "plan",
        model,
        "--pairs",
        "2",
        "--scene",
        box,
        "--set",
        "avoid.mask_buffer=true",
        "--out",
        tmp_path / "pb.h5",
        "--plot",
        tmp_path / "pb.png",
    )
    assert r.returncode == 0, r.stderr
    p = artifacts.load(tmp_path / "pb.h5", "plans")
    assert p.manifest.env.id == "fetch-push-obstacle+post" and p.manifest.config.scene == "box.toml"
    r = cdrb(
        "eval",
        model,
        "--episodes",
        "2",
        "--seeds",
        "0",
        "--scene",
        box,
        "--set",
        "avoid.best_of=2",
        "--out",
        ev,
        "--force",
    )
    assert r.returncode == 0, r.stderr
    e = artifacts.load(ev, "eval")
    assert e.manifest.env.scene.extra_boxes[0].center == (1.15, 0.95, 0.45) and e.manifest.config.avoid.best_of == 2
    r = cdrb("eval", model, "--episodes", "2", "--scene", tmp_path / "none.toml", "--out", tmp_path / "bad.h5")
    assert r.returncode == 2 and "--scene" in r.stderr and r.stderr.count("\n") == 1, r.stderr
    r = cdrb("eval", model, "--episodes", "2", "--set", "scene.extra_boxes=[]", "--out", tmp_path / "bad.h5")
    assert r.returncode == 2 and "pass --scene FILE" in r.stderr and r.stderr.count("\n") == 1, r.stderr


def test_failure_causes_follow_their_definition():
    """A failed Push episode is "grasp" when the block never moved 2 cm, then "collision" when the executed path
    touched a wall, else "tracking"; a plan through a wall ("plan") comes first; a success has no cause."""
    from cdrb_cli.envs.fetch import MOVED
    from cdrb_cli.stages.metrics import FAILURE_CODES, failure_code, failure_counts

    spec, family = make_spec("fetch-push-obstacle"), family_of(make_spec("fetch-push-obstacle"))
    still = np.stack([_state(spec, (1.2, 0.5, 0.6))] * 10)
    still[:, 0] += np.linspace(0, 0.2, 10)  # the gripper moves, the block does not
    nudged = still.copy()
    nudged[-1, 3] += 0.99 * MOVED  # moved, but less than MOVED
    moved = still.copy()
    moved[5:, 3] += 1.01 * MOVED
    assert family.execution_failure(spec, still, collided=False) == "grasp"
    assert family.execution_failure(spec, nudged, collided=True) == "grasp"  # never moved: grasp comes first
    assert family.execution_failure(spec, moved, collided=True) == "collision"
    assert family.execution_failure(spec, moved, collided=False) == "tracking"
    reach = make_spec("fetch-reach-obstacle")  # no block: never "grasp"
    r = np.stack([_state(reach, (1.2, 0.5, 0.6))] * 10)
    assert family_of(reach).execution_failure(reach, r, collided=False) == "tracking"
    assert failure_code(True, True, "grasp") == 0
    assert failure_code(False, True, "grasp") == FAILURE_CODES["plan"]
    assert failure_code(False, False, "collision") == FAILURE_CODES["collision"]
    assert failure_counts([0, 1, 4, 4, 3]) == {"plan": 1, "grasp": 0, "collision": 1, "tracking": 2}
    assert failure_counts([0, -1]) is None  # an episode not classified: no counts


def _push_wall():
    """Push Obstacle, its family, and where to cross its first wall: the wall's x, a y just before and just after
    it, and the block's resting height."""
    spec = make_spec("fetch-push-obstacle")
    wall = spec.scene.walls[0]
    wy = float(wall.center[1])
    crossing = (float(wall.center[0]), wy - wall.half[1] - 0.08, wy + wall.half[1] + 0.08, TABLE_TOP + BLOCK_HALF)
    return spec, family_of(spec), crossing


def test_a_plan_fails_by_its_block_path_on_block_tasks():
    """The cause "plan" on Push/Pick is the planned block path through a wall (or off the table); a gripper dipping
    into the wall is not a plan failure there (it is one on Reach, where the gripper is what the plan moves)."""
    spec, family, (wx, before, after, z) = _push_wall()
    # the gripper goes through the wall's middle while the block stays put, away from it
    grip_through = np.stack([_state(spec, (wx, y, z), (1.10, 0.55, z)) for y in np.linspace(before, after, 8)])
    assert family.path_in_collision(spec, grip_through[None])[0]
    assert not family.goal_path_in_collision(spec, grip_through[None])[0]
    # the block jumps through the wall between two free planned states
    block_jump = np.stack([_state(spec, (1.05, 0.4, 0.6), (wx, y, z)) for y in (before, after)])
    assert not family.in_collision(spec, block_jump).any()
    assert family.goal_path_in_collision(spec, block_jump[None])[0]
    off_table = np.stack([_state(spec, (1.05, 0.4, 0.6), (x, 0.6, z)) for x in (1.30, TABLE_XY[0][1] + 0.05)])
    assert family.goal_path_in_collision(spec, off_table[None])[0]
    reach = make_spec("fetch-reach-obstacle")  # the gripper through the first tall wall: a plan failure on Reach
    r = np.stack([_state(reach, (1.30, y, 0.5)) for y in (0.55, 0.75)])
    assert family_of(reach).goal_path_in_collision(reach, r[None])[0]


def test_crossings_by_body_split_the_gripper_from_the_block():
    """Each body's crossings apart (the gripper through a wall while the block waits; the block jumping a wall under
    a gripper that stays clear); their union is the family's plan-through-an-obstacle test, and `cdrb report` shows
    them in the crossing column. Reach moves one body: no split."""
    from types import SimpleNamespace

    from cdrb_cli.stages.plan_metrics import body_crossing_rates, body_state_rates, body_text, plan_measures

    spec, family, (wx, before, after, z) = _push_wall()
    grip = np.stack([_state(spec, (wx, y, z), (1.10, 0.55, z)) for y in np.linspace(before, after, 8)])
    block = np.stack([_state(spec, (1.05, 0.4, 0.6), (wx, y, z)) for y in np.linspace(before, after, 8)[[0, -1]]])
    block = np.concatenate([block[:1].repeat(4, 0), block[1:].repeat(4, 0)])  # the jump in the middle
    clear = np.stack([_state(spec, (1.05, 0.4, 0.6), (1.10, 0.55, z))] * 8)
    paths = np.stack([grip, block, clear])
    bodies = family.crossings_by_body(spec, paths)
    assert {k: v.tolist() for k, v in bodies.items()} == {
        "gripper": [True, False, False],
        "block": [False, True, False],
    }
    np.testing.assert_array_equal(bodies["gripper"] | bodies["block"], family.path_in_collision(spec, paths))
    reach = make_spec("fetch-reach-obstacle")
    assert family_of(reach).crossings_by_body(reach, paths[..., : reach.obs_dim]) is None

    ev = SimpleNamespace(
        arrays={"plans": np.concatenate([paths, paths[2:]]), "episodes/seed": np.array([0, 1, 1, 0])},
        manifest=SimpleNamespace(env=spec),
    )
    rates = body_crossing_rates(ev)
    assert rates == {"gripper": [0.5, 0.0], "block": [0.0, 0.5]}
    assert body_text([rates]) == "gripper 25.0; block 25.0"
    assert body_text([rates], seed=1) == "gripper 0.0; block 50.0"
    assert body_text([rates, None]) is None
    # states in an obstacle by body: the gripper's 8-state path has its middle states in the wall, the block's none
    states = family.collisions_by_body(spec, paths)
    np.testing.assert_array_equal(states["gripper"] | states["block"], family.in_collision(spec, paths))
    assert states["gripper"][0].any() and not states["block"].any()
    share = body_state_rates(ev)
    assert share["block"] == [0.0, 0.0] and share["gripper"][0] == pytest.approx(states["gripper"][0].mean() / 2)
    # as an eval stores them per episode (and keeps them without its plans), read back in the file's name order:
    # the same rates to the bit, the bodies in the family's order
    stored = dict(sorted(plan_measures(spec, ev.arrays["plans"]).items()))
    kept = SimpleNamespace(arrays={"episodes/seed": ev.arrays["episodes/seed"], **stored}, manifest=ev.manifest)
    assert list(body_crossing_rates(kept)) == ["gripper", "block"] and list(body_state_rates(kept))[0] == "gripper"
    assert body_crossing_rates(kept) == rates and body_state_rates(kept) == share


def test_plans_through_a_wall_leave_out_a_gripper_under_the_table_top():
    """The crossing test counts a body leaving its workspace too: a Push plan that skims the table 5 mm lower than
    the grip site may go (the finger tips in the table top) crosses no wall, and the wall measure says so, where a
    plan through the wall counts in both. Stored per episode as evals keep it and read back as recomputed; the
    mazes, whose walls are the whole test, have no second measure."""
    from types import SimpleNamespace

    from cdrb_cli.envs.fetch.geometry import GRIP_WORKSPACE
    from cdrb_cli.stages.plan_metrics import WALL_CROSSING, plan_measures, wall_crossing_rates

    spec, family, (wx, before, after, z) = _push_wall()
    floor = GRIP_WORKSPACE[0][2]
    through = np.stack([_state(spec, (wx, y, z + 0.01), (1.10, 0.55, z)) for y in np.linspace(before, after, 8)])
    low = np.stack([_state(spec, (1.55, 0.45 + 0.05 * i, floor - 0.005), (1.10, 0.55, z)) for i in range(8)])
    skim = low.copy()
    skim[:, 2] = floor + 0.002  # as low as the workspace allows, in no wall: neither test
    paths = np.stack([through, low, skim])
    assert family.path_in_collision(spec, paths).tolist() == [True, True, False]
    assert family.wall_crossings(spec, paths).tolist() == [True, False, False]
    seeds = np.array([0, 0, 1])
    ev = SimpleNamespace(arrays={"plans": paths, "episodes/seed": seeds}, manifest=SimpleNamespace(env=spec))
    assert wall_crossing_rates(ev) == [0.5, 0.0]
    stored = plan_measures(spec, paths)
    assert stored[WALL_CROSSING].tolist() == [True, False, False]
    kept = SimpleNamespace(arrays={"episodes/seed": ev.arrays["episodes/seed"], **stored}, manifest=ev.manifest)
    assert wall_crossing_rates(kept) == wall_crossing_rates(ev)
    maze = make_spec("maze-tight")  # its walls are the whole test: no second measure
    assert family_of(maze).wall_crossings(maze, np.zeros((1, 4, maze.obs_dim))) is None


def test_unsticking_frees_a_block_the_wall_end_stalls():
    """Tuning-stream episodes where the pusher, on the expert's own plan, is left with no room behind the block at
    the wall's end and waits (a failure): with ``unstick`` the controller pushes the block out the free way closest
    to the wanted one (a pre-push point with room for the gripper, a free way for the block) and then succeeds."""
    from cdrb_cli.data import first_window
    from cdrb_cli.envs.fetch.controllers import FetchPushPathController
    from cdrb_cli.envs.registry import CONTROLLERS
    from cdrb_cli.seeding import STREAM_TUNE
    from cdrb_cli.stages.evaluate import run_episode

    spec = make_spec("fetch-push-obstacle")
    fam = family_of(spec)
    entry = EXPERTS.get("fetch-scripted")
    expert = entry.build(spec, entry.configure(None))
    c = CONTROLLERS.get("fetch-push-path")
    env = fam.make_env(spec)
    try:
        eps = fam.draw_episodes(spec, 20, 0, STREAM_TUNE)
        for ep in (eps[3], eps[19]):  # stalled at the wall's end (benchmarks: controller ceiling)
            obs, goal = env.reset(ep)
            expert.reset(obs, goal, np.random.default_rng(ep.seed))
            plan = first_window(
                run_episode(env, spec, ep, lambda o, t: expert.act(o), spec.episode_limit).states,
                spec.horizon,
                spec.plan_stride,
            )
            outcomes = []
            for unstick in (0, 3):
                ctl = c.build(spec, env, c.config(unstick=unstick), spec.plan_stride)
                assert isinstance(ctl, FetchPushPathController)
                ctl.reset(plan)
                waited, detours = [], []

                def act(o, t, ctl=ctl, waited=waited, detours=detours):
                    n = ctl.unstuck
                    a = ctl.act(o, t)
                    waited.append(ctl.pusher.stuck)
                    if ctl.unstuck > n:  # a detour was just chosen: check it against its definition
                        target, block = ctl.pusher.targets[0], o[3:6]
                        d = (target[:2] - block[:2]) / np.linalg.norm(target[:2] - block[:2])
                        pre = np.array([*(block[:2] - ctl.pusher.BEHIND * d), block[2] - 0.005])
                        assert np.isclose(np.linalg.norm(target[:2] - block[:2]), ctl.DETOUR)
                        assert not ctl.pusher.grip_router.blocked(pre, pre, end_legs=True)
                        assert not ctl.pusher.block_router.blocked(block, target, end_legs=True)
                        detours.append(t)
                    return a

                run = run_episode(env, spec, ep, act, spec.episode_limit)
                outcomes.append((run.success, any(waited), len(detours)))
            (ok0, waited0, n0), (ok3, _, n3) = outcomes
            assert not ok0 and waited0 and n0 == 0, outcomes  # the scripted pusher waits: a failure
            assert ok3 and 1 <= n3 <= 3, outcomes
    finally:
        env.close()
