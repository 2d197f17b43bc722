"""Planning: start and goal held exactly, bad points refused, iterates, pictures."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from cdrb_cli import artifacts
from cdrb_cli.methods.config import train_config
from tests.test_train import tiny


@pytest.mark.parametrize("method", ["cdrb", "diffuser", "mlp"])
def test_start_and_goal_held_exactly(tiny_models, tmp_path, cdrb, method):
    model = tiny_models[method]
    out = tmp_path / "p.h5"
    r = cdrb(
        "plan",
        model.path,
        "--start",
        "0.3,-0.2",
        "--start",
        "1,1,0.5,-0.5",
        "--goal",
        "6,6",
        "--goal",
        "-6,-6",
        "-n",
        "3",
        "--out",
        out,
        "--set",
        "keep_iterates=2",
    )
    assert r.returncode == 0, r.stderr
    assert r.stdout.strip() == str(out)
    p = artifacts.load(out, "plans")
    plans = p.plans
    assert plans.shape == (6, 16, 4)
    starts = np.array([[0.3, -0.2, 0, 0], [1, 1, 0.5, -0.5]], dtype=np.float32)
    goals = np.array([[6, 6, 0, 0], [-6, -6, 0, 0]], dtype=np.float32)
    np.testing.assert_array_equal(plans[:, 0, :4], starts[p.arrays["pair_index"]])
    np.testing.assert_array_equal(plans[:, -1, :4], goals[p.arrays["pair_index"]])
    if method != "mlp":
        assert p.arrays["iterates"].shape[:2] == (6, 2)


def test_protocol_pairs_and_plot(tiny_models, tmp_path, cdrb):
    out, png = tmp_path / "p.h5", tmp_path / "p.png"
    r = cdrb("plan", tiny_models["cdrb"].path, "--pairs", "5", "--out", out, "--plot", png, "--set", "keep_iterates=3")
    assert r.returncode == 0, r.stderr
    p = artifacts.load(out)
    s = p.manifest.summary
    assert s.pairs == 5 and 0 <= s.in_wall_fraction <= 1 and png.stat().st_size > 5000
    np.testing.assert_array_equal(p.arrays["in_wall"].mean(), np.float64(s.in_wall_fraction))
    # the same seed draws the same pairs
    r = cdrb("plan", tiny_models["diffuser"].path, "--pairs", "5", "--out", tmp_path / "q.h5")
    q = artifacts.load(tmp_path / "q.h5")
    np.testing.assert_array_equal(p.starts, q.starts)


def test_the_batch_size_is_a_recorded_setting_and_the_memo_tells_sizes_apart(tiny_models, tmp_path, cdrb):
    """Plans sampled together share a random stream, so the batch size is part of what the plans are: recorded in
    the artifact, reproduced by the same size, and a file of another size is never "up to date"."""
    model, out = tiny_models["cdrb"].path, tmp_path / "p.h5"
    args = ("plan", model, "--pairs", "3", "-n", "2", "--seed", "5")
    assert cdrb(*args, "--out", out).returncode == 0
    whole = artifacts.load(out)
    assert whole.manifest.config.batch == 256
    r = cdrb(*args, "--out", out, "--batch-size", "1")  # other settings: refused without --force, file kept
    assert r.returncode == 2 and "--force" in r.stderr, r.stderr
    np.testing.assert_array_equal(artifacts.load(out).arrays["plans"], whole.arrays["plans"])
    for name, flags in (("a.h5", ["--batch-size", "1"]), ("b.h5", ["--set", "batch=1"])):
        assert cdrb(*args, "--out", tmp_path / name, *flags).returncode == 0
    one, again = artifacts.load(tmp_path / "a.h5"), artifacts.load(tmp_path / "b.h5")
    assert one.manifest.config.batch == 1
    np.testing.assert_array_equal(one.arrays["plans"], again.arrays["plans"])
    assert not np.array_equal(one.arrays["plans"], whole.arrays["plans"])
    r = cdrb(*args, "--out", tmp_path / "c.h5", "--batch-size", "1", "--set", "batch=2")
    assert r.returncode == 2 and "batch" in r.stderr, r.stderr
    # null marks files from before the size was recorded: not a size to plan with
    r = cdrb(*args, "--out", tmp_path / "c.h5", "--set", "batch=null")
    assert r.returncode == 2 and "--set batch=null: null is not a batch size" in r.stderr, r.stderr
    assert not (tmp_path / "c.h5").exists()
    # an unknown device is refused even where the output is up to date and nothing would be planned
    r = cdrb(*args, "--out", out, "--device", "tpu")
    assert r.returncode == 2 and "--device tpu: unknown device" in r.stderr, r.stderr


def test_settings_and_the_plan_count_are_checked_before_pairs_are_drawn(tiny_models, tmp_path, cdrb, monkeypatch):
    """A typo in --set, or a count of plans no machine holds, is refused before the (slow) drawing of many pairs."""
    from cdrb_cli.stages import plan as plan_stage

    def never(*args):
        raise AssertionError("pairs drawn before the settings were checked")

    monkeypatch.setattr(plan_stage, "plan_points", never)
    model = tiny_models["cdrb"].path
    for extra, needle in ((["--set", "sampler_steps=3"], "unknown setting"), (["-n", "10000"], "plans of")):
        r = cdrb("plan", model, "--pairs", "100000", *extra, "--out", tmp_path / "p.h5")
        assert r.returncode == 2 and needle in r.stderr, (extra, r.stderr)


def test_a_plan_file_for_other_points_is_never_up_to_date(tiny_models, tmp_path, cdrb):
    """The start/goal points are what a plans file answers: the same command with other points, or another number
    of protocol pairs, must not pass off the old file as its own."""
    model, out = tiny_models["cdrb"].path, tmp_path / "p.h5"
    base = ("plan", model, "-n", "2", "--seed", "5", "--out", out)
    assert cdrb(*base, "--start", "0,0", "--goal", "6,6").returncode == 0
    first = artifacts.load(out).arrays["plans"][:]
    r = cdrb(*base, "--start", "0,0", "--goal", "6,6")  # the same points: skipped
    assert r.returncode == 0 and "up to date" in r.stderr, r.stderr
    for other in (["--start", "0,0", "--goal", "4,6"], ["--start", "2,0", "--goal", "6,6"], ["--pairs", "2"]):
        r = cdrb(*base, *other)
        assert r.returncode == 2 and "made for other" in r.stderr and "--force" in r.stderr, (other, r.stderr)
        np.testing.assert_array_equal(artifacts.load(out).arrays["plans"][:], first)  # the file is kept
    assert cdrb(*base, "--start", "0,0", "--goal", "4,6", "--force").returncode == 0
    np.testing.assert_allclose(artifacts.load(out).arrays["goals"][0, :2], [4, 6])
    pairs = ("plan", model, "-n", "2", "--seed", "5", "--out", tmp_path / "q.h5")
    assert cdrb(*pairs, "--pairs", "2").returncode == 0
    r = cdrb(*pairs, "--pairs", "3")
    assert r.returncode == 2 and "made for other starts and goals" in r.stderr, r.stderr


@pytest.mark.parametrize(
    "args, needle",
    [
        (["--start", "-3,3", "--goal", "6,6"], "inside a wall"),
        (["--start", "0,0", "--goal", "9,0"], "outside the map"),
        (["--start", "0,0", "--goal", "0.45,3"], "inside a wall"),
        (["--start", "0,0,1", "--goal", "6,6"], "expected 2 or 4 numbers"),
        (["--start", "0,0,1e30,0", "--goal", "6,6"], "beyond"),
        (["--start", "0,0,9,0", "--goal", "6,6"], "a velocity beyond"),
        (["--start", "1_3,0", "--goal", "6,6"], "not a list of numbers"),  # Python's float() reads 13
        (["--start", "nan,0", "--goal", "6,6"], "not a list of numbers"),
        (["--start", "0x1,0", "--goal", "6,6"], "not a list of numbers"),
        (["--start", "0,0", "--goal", "6,6", "-n", "1e9"], "--num-plans"),
        (["--start", "0,0", "--goal", "6,6", "--num-plans", "2000000"], "--num-plans"),
        # each within its bound, together past what one run plans (it died of memory in numpy)
        (["--pairs", "100", "-n", "10000", "--set", "avoid.best_of=64"], "planned states in one run"),
        (["--start", "a,b", "--goal", "6,6"], "not a list of numbers"),
        (["--start", "0,0"], "no start/goal"),
        (["--start", "0,0", "--goal", "6,6", "--set", "sampler=ddpm"], "--set sampler=ddpm"),
    ],
)
def test_bad_points(tiny_models, tmp_path, cdrb, args, needle):
    r = cdrb("plan", tiny_models["cdrb"].path, *args, "--out", tmp_path / "p.h5")
    assert r.returncode == 2 and needle in r.stderr and r.stderr.count("\n") == 1, r.stderr
    assert not (tmp_path / "p.h5").exists()


def test_plan_refuses_non_model(small_data, tmp_path, cdrb):
    demos, _ = small_data
    r = cdrb("plan", demos.path, "--start", "0,0", "--goal", "6,6", "--out", tmp_path / "p.h5")
    assert r.returncode == 2 and "'model' artifact is needed" in r.stderr


def test_a_pinned_subset_is_held_exactly_and_the_rest_is_planned(small_data):
    """spec.pinned_dims: only those dimensions of the ends are pinned (Fetch pins positions, not velocities); CDRB
    then degrades the end states too, so training sees what sampling does."""
    import torch

    from cdrb_cli.buffer import Normalizer
    from cdrb_cli.methods.base import build_method
    from cdrb_cli.stages.plan import sample_plans

    demos, buffer = small_data
    spec = demos.manifest.env.model_copy(update={"pinned_dims": [0, 1]})
    cfg = train_config(demos, buffer, "cdrb", tiny("cdrb"))
    method = build_method(cfg, spec, Normalizer(low=buffer.low, high=buffer.high), buffer.points)
    assert method.kept == () and method.pinned == [0, 1]
    batch = torch.from_numpy(np.asarray(buffer.points[None, :16], dtype=np.float32)).repeat(4, 1, 1)
    assert torch.isfinite(method.loss(batch, np.random.default_rng(0)))
    starts = np.array([[0.3, -0.2, 0.7, -0.7]])
    goals = np.array([[6.0, 6.0, 0.5, 0.5]])
    plans, *_ = sample_plans(method, starts, goals, 3, seed=0)
    np.testing.assert_array_equal(plans[:, 0, :2], np.repeat(starts[:, :2], 3, 0))
    np.testing.assert_array_equal(plans[:, -1, :2], np.repeat(goals[:, :2], 3, 0))
    assert not np.allclose(plans[:, 0, 2:], starts[0, 2:]) and not np.allclose(plans[:, -1, 2:], goals[0, 2:])


@pytest.mark.parametrize("method_name", ["cdrb", "diffuser", "mlp"])
def test_start_and_goal_pins_can_differ(small_data, method_name):
    """spec.pinned_end_dims: the goal pins fewer dimensions than the start (Fetch: gripper and block at the start,
    the block alone at the goal). Each end holds exactly its own dims, and nothing else of the goal state (made up
    by the family at sampling) reaches the plan."""
    from cdrb_cli.buffer import Normalizer
    from cdrb_cli.methods.base import build_method
    from cdrb_cli.stages.plan import sample_plans

    demos, buffer = small_data
    spec = demos.manifest.env.model_copy(update={"pinned_dims": [0, 1, 2], "pinned_end_dims": [0, 1]})
    cfg = train_config(demos, buffer, method_name, tiny(method_name))
    method = build_method(cfg, spec, Normalizer(low=buffer.low, high=buffer.high), buffer.points)
    assert method.pinned == [0, 1, 2] and method.pinned_end == [0, 1]
    starts = np.array([[0.3, -0.2, 0.7, -0.7]])
    goals = np.array([[6.0, 6.0, 0.5, 0.5]])
    plans, *_ = sample_plans(method, starts, goals, 2, seed=0)
    np.testing.assert_array_equal(plans[:, 0, :3], np.repeat(starts[:, :3], 2, 0))
    np.testing.assert_array_equal(plans[:, -1, :2], np.repeat(goals[:, :2], 2, 0))
    assert not np.allclose(plans[:, -1, 2], goals[0, 2])
    other, *_ = sample_plans(method, starts, goals * [1, 1, -3, 7], 2, seed=0)  # only unpinned goal dims differ
    np.testing.assert_array_equal(plans, other)


def test_plans_that_leave_their_start_or_cross_a_wall_are_warned_about():
    """A plan walking from its start in steps the dynamics allow is fine; one whose first step leaps far from the
    start, or one whose straight step crosses a wall, gets one warning line saying which."""
    from cdrb_cli.envs.pointmaze.maze import MazeGeometry
    from cdrb_cli.envs.registry import family_of, make_spec
    from cdrb_cli.stages.plan_warnings import disconnected_warning

    spec = make_spec("maze-tight")
    allowed = family_of(spec).max_step(spec) * 2
    start = MazeGeometry(spec.scene.maze).cell_to_xy([7, 7])  # the centre cell
    walk = start + np.outer(np.arange(20), [allowed * 0.5, 0.0])  # east along the centre row, half a step each
    plans = np.zeros((1, 20, spec.obs_dim))
    plans[0, :, :2] = walk
    assert disconnected_warning(spec, plans, stride=2) is None
    leap = plans.copy()
    leap[0, 1:, 1] += 0.6  # every state after the start 0.6 m north: the first step is ~4x what is allowed
    text = disconnected_warning(spec, leap, stride=2)
    assert text is not None and "first planned step" in text and "\n" not in text
    through = np.zeros((1, 2, spec.obs_dim))
    through[0, :, :2] = [start, start + [6.0, 6.0]]  # one straight step from the centre to a corner: through walls
    assert "pass through an obstacle" in disconnected_warning(spec, through, stride=2)


def test_video_folders_are_checked_before_the_run_and_reported_truthfully(tiny_models, small_data, tmp_path):
    """--video under a file, or --out inside the --video folder, is one line before any work (the eval, or the
    demos, would otherwise be written and then fail, or be overwritten by a GIF); an up-to-date eval says that it
    wrote no GIFs instead of pointing at an empty folder."""
    from tests.conftest import run_cdrb as cdrb  # fresh processes: MuJoCo picks its renderer once per process

    model = tiny_models["mlp"].path
    (tmp_path / "vfile").write_text("x")
    ev = tmp_path / "e.h5"
    r = cdrb("eval", model, "--seeds", "0", "--episodes", "1", "--video", tmp_path / "vfile" / "sub", "--out", ev)
    assert r.returncode == 2 and "is not a folder" in r.stderr and r.stderr.count("\n") == 1 and not ev.exists()
    if Path("/proc").is_dir():  # no folder can be made there, whatever the permission bits tell (root passes them)
        for cmd in (("eval", model, "--seeds", "0", "--episodes", "1"), ("collect", "maze-tight", "-n", "2")):
            r = cdrb(*cmd, "--video", "/proc/cdrb-gifs", "--out", ev)
            assert r.returncode == 2 and "--video /proc/cdrb-gifs" in r.stderr, r.stderr[-500:]
            assert r.stderr.count("\n") == 1 and not ev.exists()
    gifs = tmp_path / "gifs"
    gifs.mkdir()
    r = cdrb("collect", "maze-tight", "-n", "2", "--out", gifs / "demo_00_success.gif", "--video", gifs)
    assert r.returncode == 2 and "inside the --video folder" in r.stderr and not any(gifs.iterdir())
    r = cdrb("eval", model, "--seeds", "0", "--episodes", "1", "--video", ev, "--out", ev)
    assert r.returncode == 2 and "the same path as --out" in r.stderr and r.stderr.count("\n") == 1 and not ev.exists()
    r = cdrb("eval", model, "--seeds", "0", "--episodes", "1", "--video", gifs, "--videos", "1", "--out", ev)
    assert r.returncode == 0 and "1 GIF(s) in" in r.stderr, r.stderr[-500:]
    r = cdrb("eval", model, "--seeds", "0", "--episodes", "1", "--video", tmp_path / "gifs2", "--out", ev)
    assert r.returncode == 0 and "no GIFs written" in r.stderr and "up to date" in r.stderr, r.stderr[-500:]


@pytest.mark.parametrize("method", ["cdrb", "diffuser"])
def test_sampling_through_the_traced_network_gives_the_same_bits(tiny_models, method):
    """Sampling runs a trace of the U-Net (no Python per module call); it must plan exactly what the module itself
    plans, at batch 1 and at another batch size than the one it was traced at, and follow the module's weights."""
    import torch

    from cdrb_cli.methods.checkpoint import load_method
    from cdrb_cli.stages.plan import sample_plans

    planner = load_method(tiny_models[method])
    planner.TRACE_AFTER = 0  # trace at once (by default only after a few plans, when it pays)
    starts, goals = np.array([[0.0, 0.0, 0.0, 0.0]] * 3), np.array([[6.0, 6.0, 0.0, 0.0]] * 3)

    def plans(trace: bool, n: int):
        planner.trace_sampling = trace
        return sample_plans(planner, starts[:n], goals[:n], 1, seed=3, batch_size=n).plans

    for n in (1, 3):
        np.testing.assert_array_equal(plans(True, n), plans(False, n))
    assert any(t is not None for t in planner.__dict__.get("_traces", {}).values()), "no trace was made and used"
    with torch.no_grad():
        for p in planner.net.parameters():
            p.mul_(0.5)  # new weights, as after loading others: the trace must follow them
    np.testing.assert_array_equal(plans(True, 3), plans(False, 3))


def test_the_graphable_loop_degrades_through_buffer_states_with_the_ends_pinned(tiny_models, monkeypatch):
    """The loop a CUDA graph holds, run on the CPU with a network that restores nothing: each plan is then its
    degradations' own, so every state between the pinned ends is a replay-buffer state."""
    import torch

    from cdrb_cli.methods.checkpoint import load_method

    method = load_method(tiny_models["cdrb"])
    monkeypatch.setattr(method, "sample_net", lambda x, k: x)
    gen = torch.Generator().manual_seed(0)
    points = torch.as_tensor(method.ball.points, dtype=torch.float32)
    P, H, obs = 4, method.horizon, method.obs_dim
    start, goal = points[:P, :obs] + 0.01, points[P : 2 * P, :obs] - 0.01  # not buffer states themselves
    x = method.pin(points[torch.randint(0, len(points), (P, H), generator=gen)], start, goal)
    ks = method._schedule(method.T - 1, None)
    u = torch.rand((len(ks), P, H - 2), generator=gen, dtype=torch.float64)
    out = method.graph_loop(x, start, goal, u, ks)
    torch.testing.assert_close(out[:, 0, :obs], start, rtol=0, atol=0)
    torch.testing.assert_close(out[:, -1, :obs], goal, rtol=0, atol=0)
    inner = out[:, 1:-1].reshape(-1, points.shape[1])
    assert (torch.cdist(inner.double(), points.double()).min(dim=1).values < 1e-6).all()


def test_the_network_is_traced_only_once_sampling_has_called_it_enough(tiny_models):
    """A one-off plan runs the module itself (tracing would cost more than it saves); the trace comes once the
    network has been called TRACE_AFTER times."""
    from cdrb_cli.methods.checkpoint import load_method
    from cdrb_cli.stages.plan import sample_plans

    planner = load_method(tiny_models["cdrb"])
    planner.TRACE_AFTER = 2 * (planner.T - 1)  # two plans' worth of calls
    start, goal = np.array([[0.0, 0.0, 0.0, 0.0]]), np.array([[6.0, 6.0, 0.0, 0.0]])
    for plans in range(1, 4):
        sample_plans(planner, start, goal, 1, seed=plans, batch_size=1)
        assert any(t is not None for t in planner.__dict__.get("_traces", {}).values()) == (plans == 3)


def test_the_summary_judges_the_plans_as_the_file_stores_them(tiny_models, tmp_path, monkeypatch):
    """A state a hair outside a wall in float64 that float32 rounds into it: the summary, the stored ``in_wall``
    and a later look at the stored plans must all read it the same way."""
    from cdrb_cli.configs import PlanConfig
    from cdrb_cli.envs.registry import family_of
    from cdrb_cli.stages import plan as plan_stage

    model = tiny_models["cdrb"]
    spec = model.manifest.env
    family = family_of(spec)
    H = 16

    def walled(x: float, y: float) -> bool:
        return bool(family.in_collision(spec, np.array([[[x, y, 0.0, 0.0]]]))[0, 0])

    # bisect along a row from free space into a wall until the edge falls between two float32 neighbours
    y, free = 0.0, 0.0
    assert not walled(free, y)
    inside = next(x for x in np.arange(0.0, 12.0, 0.05) if walled(x, y))
    for _ in range(200):
        mid = 0.5 * (free + inside)
        free, inside = (mid, inside) if not walled(mid, y) else (free, mid)
    edge = free
    while walled(float(np.float32(edge)), y) == walled(edge, y):  # a float64 point float32 carries across the edge
        edge = np.nextafter(edge, inside)
    assert walled(edge, y) != walled(float(np.float32(edge)), y)

    plan = np.zeros((1, H, 4))
    plan[:, :, 0] = free - 0.05  # in free space, but for the one state on the edge
    assert not family.in_collision(spec, plan[..., :2]).any()
    plan[0, H // 2, 0] = edge
    starts, goals = plan[:, 0].copy(), plan[:, -1].copy()

    def fake(method, s, g, n, *a, **k):
        return plan.copy(), np.zeros(1, dtype=np.int64), None, [], 0.01

    monkeypatch.setattr(plan_stage, "sample_plans", fake)
    out = plan_stage.make_plans(model, starts, goals, PlanConfig(sampler="paper", n=1, seed=0), tmp_path / "p.h5")
    stored = out.arrays["plans"].astype(np.float64)[..., :2]
    judged = family.in_collision(spec, stored)
    np.testing.assert_array_equal(out.arrays["in_wall"], judged)
    assert out.manifest.summary.plans_with_wall_states == int(judged.any(axis=1).sum())
    assert out.manifest.summary.plans_crossing == int(np.asarray(family.path_in_collision(spec, stored)).sum())
