"""Evaluation, controllers, report and the miniature quickstart."""

from __future__ import annotations

import csv
import io
import json
import shutil

import numpy as np
import pytest

from cdrb_cli import artifacts
from cdrb_cli.envs.family import Episode
from cdrb_cli.envs.pointmaze.controllers import DEFAULT_MAX_LAG, PDController
from cdrb_cli.envs.pointmaze.env import PointMaze
from cdrb_cli.envs.pointmaze.expert import MazeExpert
from cdrb_cli.envs.registry import CONTROLLERS, family_of, make_spec
from cdrb_cli.errors import BadInput
from cdrb_cli.methods.config import train_config
from cdrb_cli.seeding import STREAM_EVAL
from cdrb_cli.stages.collect import rollout
from cdrb_cli.stages.configure import eval_config
from cdrb_cli.stages.evaluate import evaluate, run_episode
from cdrb_cli.stages.train import train
from tests.test_train import tiny


def draw_pairs(spec, n, seed):
    return family_of(spec).draw_episodes(spec, n, seed, STREAM_EVAL)


def make_controller(name, stride, env, max_lag=None):
    """A maze controller through the registry, with its default gains and the given plan clock."""
    entry = CONTROLLERS.get(name)
    return entry.build(env.spec, env, entry.config(max_lag=max_lag), stride)


@pytest.mark.parametrize("controller", ["pd", "inverse-dynamics"])
def test_controllers_track_expert_plans(controller):
    """Replaying an expert episode as a stride-2 plan reaches the goal and tracks it closely."""
    spec = make_spec("maze-tight")
    env = PointMaze(spec)
    ctrl = make_controller(controller, spec.plan_stride, env)
    for ep in draw_pairs(spec, 8, seed=3):
        S, _, goal, ok = rollout(env, MazeExpert(spec), spec, ep, spec.episode_limit)
        plan = S[:: spec.plan_stride]
        ctrl.reset(plan)
        res = run_episode(env, spec, ep, ctrl.act, spec.episode_limit)
        assert res.success and not res.collision
        executed = res.states[: spec.plan_stride * (len(plan) - 1) + 1 : spec.plan_stride, :2]
        err = np.linalg.norm(executed - plan[: len(executed), :2], axis=1)
        # inverse dynamics is exact wherever the interpolated target needs no more than the maximum force
        assert err.max() < (0.1 if controller == "inverse-dynamics" else 0.25), err.max()


def test_plan_clock_pauses_while_the_ball_lags():
    spec = make_spec("maze")
    env = PointMaze(spec)
    plan = np.zeros((10, 4))
    plan[:, 0] = np.arange(10.0)  # 1 m between planned states
    timed = make_controller("pd", 2, env)
    gated = make_controller("pd", 2, env, max_lag=0.6)
    for c in (timed, gated):
        c.reset(plan)
    at_start = np.zeros(4)
    assert [timed.plan_time(at_start, t) for t in range(5)] == [0, 1, 2, 3, 4]
    # the ball stays at x = 0, 1 m from the next planned state: the gated clock never starts
    assert [gated.plan_time(at_start, t) for t in range(5)] == [0, 0, 0, 0, 0]
    # on the target it advances one step per environment step, and reset() restarts it
    on_target = np.array([1.0, 0, 0, 0])
    assert [gated.plan_time(on_target, t) for t in range(2)] == [1, 2]
    gated.reset(plan)
    assert gated.clock == 0
    with pytest.raises(ValueError):
        make_controller("pd", 2, env, max_lag=0.0)  # the config refuses it
    with pytest.raises(ValueError):
        PDController(2, kp=10.0, kd=1.0, max_lag=0.0)  # and so does the controller


def test_gated_clock_follows_plans_too_fast_to_track_on_time():
    """Expert plans replayed at 3x speed: on the environment's clock the ball falls behind and cuts corners into
    walls; with the clock gated it follows the same states to the goal."""
    spec = make_spec("maze-tight")
    env = PointMaze(spec)
    results = {}
    for lag in (None, 0.6):
        ctrl = make_controller("pd", spec.plan_stride, env, max_lag=lag)
        ok = collisions = 0
        for ep in draw_pairs(spec, 8, seed=3):
            S, _, _, _ = rollout(env, MazeExpert(spec), spec, ep, spec.episode_limit)
            ctrl.reset(S[:: 3 * spec.plan_stride])
            res = run_episode(env, spec, ep, ctrl.act, spec.episode_limit)
            ok += res.success
            collisions += res.collision
        results[lag] = (ok, collisions)
    assert results[0.6][0] == 8 and results[0.6][1] <= 1, results
    assert results[None][1] >= 4, results  # the failure mode the gate exists for


def test_inverse_dynamics_is_exact_on_reachable_targets():
    spec = make_spec("maze")
    env = PointMaze(spec)
    ctrl = make_controller("inverse-dynamics", 1, env)
    obs, _ = env.reset(Episode(0, (7, 7), (1, 1)))
    t = np.arange(30)[:, None] * env.dynamics["dt"]
    # constant acceleration of 5 m/s^2 (the ball can do about 24): every target is reachable in one step
    plan = np.concatenate([obs[None, :2] + 0.5 * 5.0 * t**2 * np.array([[0.8, 0.6]]), np.zeros((30, 2))], axis=1)
    ctrl.reset(plan)
    for step in range(29):
        obs = env.step(ctrl.act(obs, step))
        np.testing.assert_allclose(obs[:2], plan[step + 1, :2], atol=1e-9)


def test_protocol_pairs_are_central_starts_and_corner_goals():
    spec = make_spec("maze-tight")
    pairs = draw_pairs(spec, 50, seed=0)
    starts = np.array([p.start for p in pairs])
    goals = {p.goal for p in pairs}
    assert starts.min() >= 5 and starts.max() <= 9
    assert goals <= {(1, 1), (1, 13), (13, 1), (13, 13)} and len(goals) == 4
    family = family_of(spec)
    s1, g1 = family.reset_states(spec, pairs)
    s2, g2 = family.reset_states(spec, draw_pairs(spec, 50, seed=0), PointMaze(spec))
    np.testing.assert_array_equal(s1, s2)
    np.testing.assert_array_equal(g1, g2)
    assert np.all(np.abs(s1[:, 2:]) == 0)


@pytest.fixture(scope="module")
def evals(small_data, tmp_path_factory):
    demos, buffer = small_data
    root = tmp_path_factory.mktemp("evals")
    out = {}
    for method in ("cdrb", "diffuser", "mlp"):
        b = buffer if method == "cdrb" else None
        # horizon 16 at stride 10 covers 160 env steps: enough structure for a smoke test
        model = train(
            demos,
            b,
            train_config(demos, b, method, tiny(method, steps=20, checkpoint_every=20, stride=10)),
            root / f"m-{method}.h5",
        )
        cfg = eval_config(model, episodes=4, seeds=[0, 1])
        assert cfg.sampler == model.manifest.config.method.sampler and cfg.controller.max_lag == DEFAULT_MAX_LAG
        out[method] = evaluate(model, cfg, root / f"e-{method}.h5")
    return out


def test_eval_artifact_contents(evals):
    ev = evals["cdrb"]
    a = ev.arrays
    assert a["episodes/success"].shape == (8,) and set(a["episodes/seed"].tolist()) == {0, 1}
    assert a["plans"].shape[0] == 8
    s = ev.manifest.summary
    assert len(s.per_seed) == 2 and np.isclose(s.success_mean, a["episodes/success"].mean())
    assert np.isclose(s.in_wall_mean, a["episodes/plan_in_wall_fraction"].mean())
    assert np.all(a["episodes/expert_path_length"] > 0)
    # the same seeds give the same start/goal pairs for every method
    for other in ("diffuser", "mlp"):
        np.testing.assert_array_equal(evals[other].arrays["episodes/start"], a["episodes/start"])
        np.testing.assert_array_equal(evals[other].arrays["episodes/goal"], a["episodes/goal"])
    # plan metrics measured from the stored plans: crossings (states or segments) and the largest jump
    from cdrb_cli.envs.geometry import largest_jump

    spec = ev.manifest.env
    states = a["plans"][..., : spec.obs_dim]
    np.testing.assert_array_equal(a["episodes/plan_crosses_obstacle"], family_of(spec).path_in_collision(spec, states))
    np.testing.assert_allclose(a["episodes/plan_max_jump"], largest_jump(states, [0, 1]), rtol=1e-5)
    assert np.allclose(a["episodes/plan_step_limit"], family_of(spec).max_step(spec) * 10)  # stride 10 here
    assert (a["episodes/plan_in_wall_fraction"] > 0)[~a["episodes/plan_crosses_obstacle"]].sum() == 0
    # the summary's std is the sample std over seeds
    per = [p.success_rate for p in s.per_seed]
    assert np.isclose(s.success_std, np.std(per, ddof=1))
    # every failed episode has one cause, a success none; a plan through a wall is the cause whenever it happened
    from cdrb_cli.stages.metrics import FAILURE_CODES

    code = a["episodes/failure"]
    assert ((code == 0) == a["episodes/success"]).all()
    failed_crossing = ~a["episodes/success"] & a["episodes/plan_crosses_obstacle"]  # a maze: the ball's own path
    assert (code[failed_crossing] == FAILURE_CODES["plan"]).all()
    assert (code[~a["episodes/success"] & ~a["episodes/plan_crosses_obstacle"]] != FAILURE_CODES["plan"]).all()
    assert sum(s.failures.values()) == (~a["episodes/success"]).sum()
    assert s.failures == {c: sum(p.failures[c] for p in s.per_seed) for c in s.failures}


def test_tuning_pairs_and_the_official_protocol(evals, tmp_path, cdrb):
    """`--stream tune` draws other pairs; `--protocol official-code` evaluates with cell-centre goals, r = 0.55 and
    the official executor; the report refuses to mix either with the default."""
    model = evals["cdrb"].manifest.parents[0].path
    r = cdrb("eval", model, "--seeds", "0,1", "--episodes", "4", "--stream", "tune", "--out", tmp_path / "t.h5")
    assert r.returncode == 0, r.stderr
    tune = artifacts.load(tmp_path / "t.h5", "eval")
    assert tune.manifest.config.stream == "tune"
    assert not np.isin(tune.arrays["episodes/episode_seed"], evals["cdrb"].arrays["episodes/episode_seed"]).any()
    r = cdrb("report", evals["cdrb"].path, tmp_path / "t.h5")
    assert r.returncode == 2 and "different protocols" in r.stderr and "tune pairs" in r.stderr
    r = cdrb("eval", model, "--seeds", "0", "-n", "4", "--protocol", "official-code", "--out", tmp_path / "o.h5")
    assert r.returncode == 0, r.stderr
    off = artifacts.load(tmp_path / "o.h5", "eval")
    assert off.manifest.config.protocol == "official-code" and off.manifest.config.controller.name == "waypoint"
    assert off.manifest.env.success_radius == 0.55 and not off.manifest.env.scene.goal_noise
    r = cdrb("eval", model, "--protocol", "official-code", "--set", "controller=pd", "--out", tmp_path / "x.h5")
    assert r.returncode == 2 and "waypoint controller" in r.stderr
    r = cdrb("eval", model, "--protocol", "nope", "--out", tmp_path / "x.h5")
    assert r.returncode == 2 and "--protocol nope: not a protocol" in r.stderr and "official-code" in r.stderr
    r = cdrb("eval", model, "--stream", "train", "--out", tmp_path / "x.h5")
    assert r.returncode == 2 and "--stream" in r.stderr


def test_an_eval_without_plans(evals, tmp_path, cdrb):
    """`--no-plans` keeps every episode measure but not the plans, and what the report measures on plans is kept
    per episode (the first-step column is there as with the plans); `--plans-plot` says which flag left them out."""
    model = evals["cdrb"].manifest.parents[0].path
    r = cdrb("eval", model, "--seeds", "0", "-n", "4", "--no-plans", "--out", tmp_path / "bare.h5")
    assert r.returncode == 0, r.stderr
    bare = artifacts.load(tmp_path / "bare.h5", "eval")
    assert "plans" not in bare.arrays and len(bare.arrays["episodes/success"]) == 4
    assert bare.arrays["episodes/plan_crosses_obstacle"].shape == (4,)
    rows = json.loads(cdrb("report", tmp_path / "bare.h5", "--format", "json").stdout)
    assert len(rows) == 1 and rows[0]["method"] == "cdrb" and rows[0]["first_step_ratio"] > 0
    r = cdrb("report", tmp_path / "bare.h5", "--plans-plot", tmp_path / "p.png")
    assert r.returncode == 2 and "--no-plans" in r.stderr and not (tmp_path / "p.png").exists()
    assert "export --compact" in r.stderr  # a compact copy holds no plans either: its original does
    # the plans are checked before any picture is drawn: the bar chart is not left behind either
    r = cdrb("report", tmp_path / "bare.h5", "--plot", tmp_path / "bars.png", "--plans-plot", tmp_path / "p.png")
    assert r.returncode == 2 and not (tmp_path / "bars.png").exists() and not (tmp_path / "p.png").exists()


def test_report_checks_every_output_before_writing_one(evals, tmp_path, cdrb):
    """A --docs file without its block, --docs naming the --out file, or --paper-figures without --paper: one line,
    exit 2, and no picture or file written or changed."""
    path = evals["cdrb"].path
    doc = tmp_path / "doc.md"
    doc.write_text("hello\n")
    r = cdrb("report", path, "--docs", doc, "--block", "t", "--plot", tmp_path / "b.png")
    assert r.returncode == 2 and "<!-- t:begin -->" in r.stderr and not (tmp_path / "b.png").exists()
    doc.write_text("a\n<!-- t:begin -->\n<!-- t:end -->\nb\n")
    r = cdrb("report", path, "--docs", doc, "--block", "t", "--out", doc, "--force")
    assert r.returncode == 2 and "the same file as --docs" in r.stderr
    assert doc.read_text() == "a\n<!-- t:begin -->\n<!-- t:end -->\nb\n"
    r = cdrb("report", path, "--paper-figures", tmp_path / "figures.toml")
    assert r.returncode == 2 and "--paper-figures goes with --paper" in r.stderr


def test_report_outputs_land_together_or_not_at_all(evals, tmp_path, cdrb, monkeypatch):
    """The last output failing to fit (a full disk) leaves none of the earlier ones: the picture, the --docs page
    and the report are written to temp files and renamed only once all are written."""
    import errno
    import pathlib

    doc = tmp_path / "doc.md"
    page = "a\n<!-- t:begin -->\n<!-- t:end -->\nb\n"
    doc.write_text(page)
    write_text = pathlib.Path.write_text

    def full_for_the_report(self, *args, **kwargs):
        if self.name.startswith(".r.md.tmp-"):
            raise OSError(errno.ENOSPC, "No space left on device")
        return write_text(self, *args, **kwargs)

    monkeypatch.setattr(pathlib.Path, "write_text", full_for_the_report)
    flags = ["--docs", doc, "--block", "t", "--plot", tmp_path / "b.png", "--out", tmp_path / "r.md"]
    r = cdrb("report", evals["cdrb"].path, *flags)
    assert r.returncode == 2 and "no space left on device while writing it" in r.stderr, r.stderr
    assert doc.read_text() == page and sorted(p.name for p in tmp_path.iterdir()) == ["doc.md"]
    monkeypatch.undo()
    r = cdrb("report", evals["cdrb"].path, *flags)
    assert r.returncode == 0 and r.stdout.strip() == str(tmp_path / "r.md")
    assert (tmp_path / "b.png").stat().st_size > 0 and "| cdrb" in doc.read_text()


def test_report_formats_and_pictures(evals, tmp_path, cdrb):
    paths = [evals[m].path for m in ("cdrb", "diffuser", "mlp")]
    r = cdrb(
        "report",
        *paths,
        "--format",
        "markdown",
        "--paper",
        "--plot",
        tmp_path / "bars.png",
        "--plans-plot",
        tmp_path / "plans.png",
    )
    assert r.returncode == 0, r.stderr
    assert "| Maze Tight |" in r.stdout and "Maze Tight (paper)" in r.stdout and "98.00 ± 0.00" in r.stdout
    for name in ("bars.png", "plans.png"):
        assert (tmp_path / name).stat().st_size > 5000
    rows = json.loads(cdrb("report", *paths, "--format", "json").stdout)
    assert {row["method"] for row in rows} == {"cdrb", "diffuser", "mlp"}
    csv_text = cdrb("report", *paths, "--format", "csv").stdout
    assert csv_text.splitlines()[0].startswith("env,method")
    r = cdrb("report", *paths, "--out", tmp_path / "r.md")
    assert r.returncode == 0 and r.stdout.strip() == str(tmp_path / "r.md")
    r = cdrb("report", *paths, "--format", "summary", "--paper")
    assert r.returncode == 0 and "| Maze Tight | 2 x 4 | no floor measured |" in r.stdout and "38.29 / " in r.stdout
    r = cdrb("report", *paths, "--format", "summary", "--per-seed")
    assert r.returncode == 2 and "--per-seed has no summary format" in r.stderr


def test_report_refuses_mixed_protocols(evals, tmp_path, cdrb):
    ev = evals["cdrb"]
    # another method evaluated with other episodes per seed
    cfg = ev.manifest.config.model_copy(update={"episodes": 3})
    other = ev.manifest.model_copy(update={"config": cfg, "summary": evals["diffuser"].manifest.summary})
    seeds = ev.arrays["episodes/seed"]
    keep = np.zeros(len(seeds), bool)
    for s in np.unique(seeds):
        keep[np.flatnonzero(seeds == s)[:3]] = True
    arrays = {k: (v[keep] if k.startswith("episodes/") or k == "plans" else v) for k, v in ev.arrays.items()}
    artifacts.save(tmp_path / "other.h5", "eval", other, arrays)
    r = cdrb("report", ev.path, tmp_path / "other.h5")
    assert r.returncode == 2 and "different protocols" in r.stderr
    # another method evaluated on other seeds
    other = evals["diffuser"]
    arrays = {**other.arrays, "episodes/seed": np.where(other.arrays["episodes/seed"] == 1, 9, 0)}
    cfg = other.manifest.config.model_copy(update={"seeds": [0, 9]})
    artifacts.save(tmp_path / "seeds.h5", "eval", other.manifest.model_copy(update={"config": cfg}), arrays)
    r = cdrb("report", ev.path, tmp_path / "seeds.h5")
    assert r.returncode == 2 and "different evaluation seeds ([0, 1] for cdrb vs [0, 9] for diffuser)" in r.stderr
    # the error names the method whose seeds differ, not merely the first two methods (which agree here)
    r = cdrb("report", ev.path, evals["mlp"].path, tmp_path / "seeds.h5")
    assert r.returncode == 2 and "for cdrb vs [0, 9] for diffuser" in r.stderr and "for mlp" not in r.stderr
    # the same seeds twice for one method
    r = cdrb("report", ev.path, ev.path)
    assert r.returncode == 2 and "more than one eval file" in r.stderr
    # two files of one name in two folders are told apart by their paths
    (tmp_path / "again").mkdir()
    shutil.copy(ev.path, tmp_path / "again" / ev.path.name)
    r = cdrb("report", ev.path, tmp_path / "again" / ev.path.name)
    assert r.returncode == 2 and f"again/{ev.path.name}" in r.stderr and r.stderr.count("\n") == 1, r.stderr
    # --paper's rows are the grouped report's: refused beside --per-seed, not silently dropped
    r = cdrb("report", ev.path, "--per-seed", "--paper")
    assert r.returncode == 2 and "--per-seed" in r.stderr and "--paper" in r.stderr, r.stderr


def test_report_pools_one_eval_per_training_seed(evals, tmp_path, cdrb):
    """Table-1 style: one model per training seed, each evaluated on its own seed, pooled as seeds."""
    paths = []
    for method in ("cdrb", "diffuser"):
        ev = evals[method]
        for seed in (0, 1):
            summ = ev.manifest.summary
            per = [p for p in summ.per_seed if p.seed == seed]
            cfg = ev.manifest.config.model_copy(update={"seeds": [seed]})
            m = ev.manifest.model_copy(update={"config": cfg, "summary": summ.model_copy(update={"per_seed": per})})
            keep = ev.arrays["episodes/seed"] == seed
            arrays = {k: (v[keep] if k.startswith("episodes/") or k == "plans" else v) for k, v in ev.arrays.items()}
            path = tmp_path / f"{method}-{seed}.h5"
            artifacts.save(path, "eval", m, arrays)
            paths.append(path)
    rows = json.loads(cdrb("report", *paths, "--format", "json").stdout)
    by = {r["method"]: r for r in rows}
    for method in ("cdrb", "diffuser"):
        per = evals[method].manifest.summary.per_seed
        assert by[method]["seeds"] == 2
        assert np.isclose(by[method]["success_mean"], 100 * np.mean([p.success_rate for p in per]))


def _one_seed(ev, seed: int, path, config=None, summary=None, env=None):
    """``ev``'s episodes of evaluation ``seed`` as an eval file of their own, with manifest fields changed."""
    summ = ev.manifest.summary
    summ = summ.model_copy(update={"per_seed": [p for p in summ.per_seed if p.seed == seed], **(summary or {})})
    cfg = ev.manifest.config.model_copy(update={"seeds": [seed], **(config or {})})
    update = {"config": cfg, "summary": summ, **({"env": env} if env is not None else {})}
    keep = ev.arrays["episodes/seed"] == seed
    arrays = {k: (v[keep] if k.startswith("episodes/") or k == "plans" else v) for k, v in ev.arrays.items()}
    artifacts.save(path, "eval", ev.manifest.model_copy(update=update), arrays)
    return artifacts.load(path, "eval")


def test_report_pools_only_evals_that_ran_alike_and_says_what_its_spread_is_over(evals, tmp_path, cdrb):
    """Seeds pooled into one row must have run alike: any setting (re-planning's minimum gap, a route buffer...),
    the training length of the model evaluated, and the scene an environment's name stands for (a map is named
    after its file). Two evaluation seeds of one model are pooled, but the summary says its spread is over
    evaluation seeds; a one-seed row has no spread in CSV/JSON (null, not 0); the same eval twice is refused in
    the per-seed table too."""
    from cdrb_cli.stages.report import collect_rows
    from cdrb_cli.stages.report_summary import render_summary

    ev = evals["cdrb"]
    a, b = _one_seed(ev, 0, tmp_path / "a.h5"), _one_seed(ev, 1, tmp_path / "b.h5")
    (row,) = collect_rows([a, b])
    assert row["seeds"] == 2 and row["models"] == 1
    assert "std over seeds (a model's evaluation seeds" in render_summary([row])
    replan = ev.manifest.config.replan.model_copy(update={"min_gap": ev.manifest.config.replan.min_gap + 7})
    c = _one_seed(ev, 1, tmp_path / "c.h5", config={"replan": replan})
    d = _one_seed(ev, 1, tmp_path / "d.h5", summary={"model_steps": 10})
    maze = ev.manifest.env.scene.maze
    rows = list(maze.rows)
    col = rows[1].index(".")
    rows[1] = rows[1][:col] + "#" + rows[1][col + 1 :]  # one more wall cell, the same name
    scene = ev.manifest.env.scene.model_copy(update={"maze": maze.model_copy(update={"rows": rows})})
    e = _one_seed(ev, 1, tmp_path / "e.h5", env=ev.manifest.env.model_copy(update={"scene": scene}))
    f = _one_seed(ev, 1, tmp_path / "f.h5", summary={"model_training": "0" * 64})
    assert a.manifest.summary.model_training not in (None, "0" * 64)
    for other, needle in [(c, "a.h5 and c.h5 differ in replan.min_gap"), (d, "a.h5 and d.h5 differ in model_steps"),
                          (e, "a.h5 and e.h5: both name the environment"),
                          (f, "a.h5 and f.h5 evaluate models trained with other settings")]:  # fmt: skip
        with pytest.raises(BadInput, match=needle):
            collect_rows([a, other])
    (tmp_path / "other").mkdir()  # one name in two folders: the error gives the paths
    twin = _one_seed(ev, 1, tmp_path / "other" / "a.h5", config={"replan": replan})
    with pytest.raises(BadInput, match=f"{tmp_path / 'a.h5'} and {tmp_path / 'other' / 'a.h5'} differ"):
        collect_rows([a, twin])
    older = _one_seed(ev, 1, tmp_path / "g.h5", summary={"model_training": None})  # unknown: not compared
    assert collect_rows([a, older])[0]["seeds"] == 2
    r = cdrb("report", tmp_path / "a.h5", "--format", "csv")
    (cells,) = list(csv.DictReader(io.StringIO(r.stdout)))
    assert cells["success_std"] == "" and cells["success_ci95"] == "" and cells["success_mean"] != ""
    (tmp_path / "copy.h5").write_bytes((tmp_path / "a.h5").read_bytes())
    r = cdrb("report", tmp_path / "a.h5", tmp_path / "copy.h5", "--per-seed")
    assert r.returncode == 2 and "a.h5 and copy.h5: the same eval twice" in r.stderr, r.stderr


def test_eval_cli_bad_inputs(evals, small_data, tmp_path, cdrb):
    demos, _ = small_data
    model = evals["cdrb"].manifest.parents[0].path
    for args, needle in [
        (["--seeds", "a,b"], "--seeds"),
        (["--seeds", "1,1"], "repeated"),
        (["--set", "controller=magic"], "--set controller=magic: not a controller"),
        (["--set", "sampler=ddpm"], "--set sampler=ddpm: cdrb models use paper, cold-improved"),
        (["--set", "sampler.kind=magic"], "--set sampler.kind=magic"),
        (["--set", "controller=inverse-dynamics", "--set", "controller.kp=3"], "unknown setting 'controller.kp'"),
        (["--episodes", "0"], "--episodes"),
        (["--set", "sample_steps=999"], "--set sample_steps=999: the model has T = 8 diffusion steps, so at most 8"),
    ]:
        r = cdrb("eval", model, *args, "--out", tmp_path / "e.h5")
        assert r.returncode == 2 and needle in r.stderr and r.stderr.count("\n") == 1, (args, r.stderr)
    r = cdrb("eval", demos.path, "--out", tmp_path / "e.h5")
    assert r.returncode == 2 and "'model' artifact" in r.stderr and r.stderr.count("\n") == 1
    assert not (tmp_path / "e.h5").exists()


@pytest.mark.slow
def test_miniature_quickstart_end_to_end_and_rerun(tmp_path, cdrb):
    out = tmp_path / "qs"
    args = [
        "quickstart",
        "--out",
        out,
        "--episodes",
        "30",
        "--k",
        "50",
        "--steps",
        "20",
        "--seeds",
        "0",
        "--eval-episodes",
        "3",
        "--methods",
        "cdrb,diffuser,mlp",
    ]
    r = cdrb(*args, env={"OMP_NUM_THREADS": "2", "CDRB_PROGRESS_SECONDS": "0"})  # two workers, a thread each
    assert r.returncode == 0, r.stderr
    assert "| Maze Tight |" in r.stdout
    assert (
        "train cdrb, diffuser, mlp (quick preset), then evaluate each: 1 seed x 3 episodes, 2 at a time, 1 thread each"
        in r.stderr
    )
    for method in ("cdrb", "diffuser", "mlp"):  # each worker's progress is drawn by the command itself
        assert f"train {method}: 20/20 (100%)" in r.stderr and f"eval {method}: 3/3 (100%)" in r.stderr
    for name in (
        "demos.h5",
        "buffer.h5",
        "model-cdrb.h5",
        "model-diffuser.h5",
        "eval-cdrb.h5",
        "report.md",
        "results.png",
        "plans.png",
        "demos.png",
    ):
        assert (out / name).exists(), name
    # demonstrations from the protocol's starts and from anywhere; the planners weigh the states after the start
    assert artifacts.load(out / "demos.h5", "demos").manifest.config.starts == "protocol+anywhere"
    for method in ("cdrb", "diffuser"):
        assert artifacts.load(out / f"model-{method}.h5", "model").manifest.config.method.start_weight == 10
    before = {p.name: p.stat().st_mtime_ns for p in out.glob("*.h5")}
    again = cdrb(*args)
    assert again.returncode == 0 and again.stderr.count("up to date") == 3  # collect, cluster, train + evaluate
    assert {p.name: p.stat().st_mtime_ns for p in out.glob("*.h5")} == before
    # an eval lost: only it is made again, from the model on disk
    (out / "eval-mlp.h5").unlink()
    again = cdrb(*args)
    assert again.returncode == 0 and "  mlp: model up to date" in again.stderr and "train mlp:" not in again.stderr
    before.pop("eval-mlp.h5")
    assert {p.name: p.stat().st_mtime_ns for p in out.glob("*.h5") if p.name != "eval-mlp.h5"} == before
    assert artifacts.load(out / "eval-mlp.h5", "eval").manifest.summary.model_steps == 20


def test_report_recomputes_from_the_episodes_and_prints_plain_text(evals, tmp_path, cdrb):
    """A file claiming 100% in its summary with every episode failed reports what its episodes say; ids with
    terminal escapes or rich markup are printed as plain text."""
    ev = evals["mlp"]
    summ = ev.manifest.summary
    boast = summ.model_copy(
        update={"success_mean": 1.0, "per_seed": [p.model_copy(update={"success_rate": 1.0}) for p in summ.per_seed]}
    )
    env = ev.manifest.env.model_copy(update={"id": "maze\x1b[2J[/bold]"})
    arrays = {**ev.arrays, "episodes/success": np.zeros_like(ev.arrays["episodes/success"])}
    artifacts.save(tmp_path / "boast.h5", "eval", ev.manifest.model_copy(update={"summary": boast, "env": env}), arrays)
    r = cdrb("report", tmp_path / "boast.h5", "--format", "json")
    assert r.returncode == 0, r.stderr
    (row,) = json.loads(r.stdout)
    assert row["success_mean"] == 0.0 and "\x1b" not in row["env"]
    r = cdrb("report", tmp_path / "boast.h5")
    assert r.returncode == 0 and "\x1b" not in r.stdout and "[/bold]" in r.stdout


def test_each_method_keeps_its_own_controller_but_only_one(evals, tmp_path, cdrb):
    """Methods tuned separately may use different controller settings (shown in the report); one method's seeds
    may not."""
    from cdrb_cli.envs.pointmaze.controllers import InverseDynamicsConfig

    ev = evals["diffuser"]
    cfg = ev.manifest.config.model_copy(update={"controller": InverseDynamicsConfig(max_lag=0.6, max_wait=5)})
    artifacts.save(tmp_path / "d.h5", "eval", ev.manifest.model_copy(update={"config": cfg}), ev.arrays)
    r = cdrb("report", evals["cdrb"].path, tmp_path / "d.h5", "--format", "json")
    assert r.returncode == 0, r.stderr
    rows = {row["method"]: row for row in json.loads(r.stdout)}
    assert (
        rows["diffuser"]["controller"].startswith("inverse-dynamics") and "max_wait 5" in rows["diffuser"]["controller"]
    )
    assert rows["cdrb"]["controller"].startswith("pd")
    # one method whose two seeds were run with different controllers
    paths = []
    for seed, controller in ((0, ev.manifest.config.controller), (1, cfg.controller)):
        keep = ev.arrays["episodes/seed"] == seed
        arrays = {k: (v[keep] if k.startswith("episodes/") or k == "plans" else v) for k, v in ev.arrays.items()}
        c = ev.manifest.config.model_copy(update={"seeds": [seed], "controller": controller})
        paths.append(
            artifacts.save(tmp_path / f"s{seed}.h5", "eval", ev.manifest.model_copy(update={"config": c}), arrays)
        )
    r = cdrb("report", *paths)
    assert r.returncode == 2 and "different controllers" in r.stderr
    # or with different sampler settings
    c = ev.manifest.config.model_copy(update={"seeds": [1], "sample_steps": 4})
    artifacts.save(paths[1], "eval", ev.manifest.model_copy(update={"config": c}), artifacts.load(paths[1]).arrays)
    r = cdrb("report", *paths)
    assert r.returncode == 2 and "different sampler settings" in r.stderr


def test_weighted_success_and_success_without_collision_follow_their_definitions():
    """Weighted success (the official code's): success with no planned state in an obstacle; success without
    collision: success with no executed collision. Checked on every combination of the three flags."""
    import itertools

    from cdrb_cli.stages.results import EpisodeResult, seed_result

    results = []
    for i, (ok, wall, hit) in enumerate(itertools.product([True, False], [0.0, 0.25], [False, True])):
        results.append(
            EpisodeResult(
                seed=0, episode_seed=i, success=ok, steps=10, final_distance=0.0, plan_in_wall_fraction=wall,
                plan_crosses_obstacle=wall > 0, plan_max_jump=0.1, plan_step_limit=1.0, executed_collision=hit,
                path_length=1.0, expert_path_length=1.0, plan_seconds=0.01, start=np.zeros(2), goal=np.ones(2),
            )
        )  # fmt: skip
    r = seed_result(0, results)
    assert r.success_rate == 0.5
    assert r.weighted_success_rate == 2 / 8  # success, plan free: with or without an executed collision
    assert r.clean_success_rate == 2 / 8  # success, no collision: with or without a plan in a wall
    both = sum(x.success and x.plan_in_wall_fraction == 0 and not x.executed_collision for x in results)
    assert both == 1
    policy = seed_result(0, results, policy=True)
    assert policy.weighted_success_rate is None and policy.clean_success_rate == 2 / 8


def test_one_seed_shows_no_interval(tmp_path):
    """A one-seed row has no spread: the report says n/a instead of a misleading ± 0.0 [± 0.0]."""
    from cdrb_cli.stages.report import render

    row = {
        "env": "maze-tight", "method": "cdrb", "controller": "pd", "pairs": "test", "seeds": 1, "episodes": 4,
        "success_mean": 25.0, "success_std": 0.0, "success_ci95": 0.0, "weighted_success_mean": 25.0,
        "weighted_success_std": 0.0, "clean_success_mean": 25.0, "clean_success_std": 0.0, "in_wall_mean": 1.0,
        "in_wall_std": 0.0, "crossing_mean": 0.0, "first_step_ratio": 1.2, "jump_ratio": 0.5,
        "impossible_jump_mean": 0.0,
        "collision_mean": 0.0, "path_ratio": 1.1, "plan_ms": 1.0, "replans": 0.0, "episode_planning_ms": 1.0,
        "failures": "", "env_name": "Maze Tight",
    }  # fmt: skip
    text = render([row], "markdown")
    assert "25.00 ± n/a" in text and "25.0 ± n/a (1 seed)" in text and "± 0.0" not in text
    text = render([{**row, "seeds": 3, "success_std": 2.0, "success_ci95": 5.0}], "markdown")
    assert "25.0 ± 2.0 [± 5.0]" in text


def test_the_summary_marks_every_method_that_does_not_beat_the_straight_line():
    """One line per environment: the straight line is the floor column, a method at or below it is marked, a
    policy's weighted success is n/a, and a row with no straight-line eval says so rather than marking nothing."""
    from cdrb_cli.stages.report_summary import render_summary

    def row(env, method, success, weighted, seeds=3):
        return {"env": env, "env_name": env.title(), "method": method, "seeds": seeds, "episodes": 100,
                "success_mean": success, "success_std": 1.0, "weighted_success_mean": weighted}  # fmt: skip

    rows = [
        row("fetch-push", "straight", 40.0, 40.0),
        row("fetch-push", "mlp", 40.0, 10.0),
        row("fetch-push", "cdrb", 90.0, 85.0),
        row("fetch-push", "diffusion-bc", 30.0, None),
        row("fetch-reach", "cdrb", 10.0, 5.0, seeds=1),
    ]
    text = render_summary(rows)
    lines = {ln.split(" | ")[0].strip("| "): ln for ln in text.splitlines() if ln.startswith("| Fetch")}
    head = text.splitlines()[0]
    assert head.index("straight line (floor)") < min(head.index(m) for m in ("mlp", "diffusion-bc", "cdrb"))
    push = lines["Fetch-Push"]
    assert "40.0 ± 1.0 (40.0) |" in push and "40.0 ± 1.0 (10.0) ≤ floor" in push  # equal is not beating it
    assert "90.0 ± 1.0 (85.0) |" in push and "30.0 ± 1.0 (n/a) ≤ floor" in push
    reach = lines["Fetch-Reach"]
    assert "no floor measured" in reach and "10.0 ± n/a (5.0)" in reach and "≤ floor" not in reach
    assert "does not beat the straight line" in text
    assert "does not beat" not in render_summary([r for r in rows if r["method"] in ("straight", "cdrb")])
    # a second straight-line row (another executor) is a floor column too, and the higher floor is the one to beat
    text = render_summary(rows + [row("fetch-push", "straight [every 20]", 95.0, 95.0)])
    assert "straight line [every 20] (floor)" in text.splitlines()[0]
    assert "90.0 ± 1.0 (85.0) ≤ floor" in text and "| – |" in text  # Fetch-Reach has no such floor


def test_published_figures_of_methods_outside_the_registry_print_as_their_source_gives_them(tmp_path):
    """A --paper-figures file may list published methods this project does not implement (``others``): their
    column follows ours, in the file's order, with – where a row has none; whole per cents print whole (OGBench's
    table), a file with decimals prints two (the paper's Table 1). A name neither registered nor listed is refused."""
    from cdrb_cli.errors import BadInput
    from cdrb_cli.stages.report import paper_figures
    from cdrb_cli.stages.report_summary import render_summary

    path = tmp_path / "published.toml"
    path.write_text(
        'others = ["QRL", "HIQL"]\n["maze"]\nQRL = [86, 9]\nHIQL = [58, 5]\n["maze-tight"]\nQRL = [68, 7]\n'
    )
    figures = paper_figures(path)
    rows = [
        {
            "env": env,
            "env_name": env,
            "method": "cdrb",
            "seeds": 3,
            "episodes": 100,
            "success_mean": 99.0,
            "success_std": 1.0,
            "weighted_success_mean": 90.0,
        }  # fmt: skip
        for env in ("maze", "maze-tight")
    ]
    text = render_summary(rows, figures)
    assert "paper: QRL / HIQL" in text.splitlines()[0]
    lines = [ln for ln in text.splitlines() if ln.startswith("| maze")]
    assert lines[0].endswith("| 86 / 58 |") and lines[1].endswith("| 68 / – |")
    decimals = render_summary(rows, {**figures, "maze": {"QRL": (86.5, 9.0), "HIQL": (58.0, 5.0)}})
    assert "| 86.50 / 58.00 |" in decimals
    # rows the figures do not cover (a scene of one's own): no column of dashes, and a note that says so
    unknown = render_summary([{**r, "env": f"{r['env']}+mine"} for r in rows], figures)
    assert "paper" not in unknown.splitlines()[0] and "The paper gives no figures for these rows." in unknown
    path.write_text('["maze"]\nQRL = [86, 9]\n')
    with pytest.raises(BadInput, match="others"):
        paper_figures(path)


def test_the_summary_marks_a_method_above_the_floor_only_by_seed_noise():
    """Above the straight line's mean is not beating it: a gap inside the seeds' spread (Welch's one-sided test,
    5%) is marked ≈ floor, a gap well outside it is not, and with no spread on either side any gap counts."""
    from cdrb_cli.stages.report_summary import _above, render_summary

    def row(method, success, std, seeds=5):
        return {"env": "fetch-push", "env_name": "Push", "method": method, "seeds": seeds, "episodes": 100,
                "success_mean": success, "success_std": std, "weighted_success_mean": success}  # fmt: skip

    floor = row("straight", 75.0, 4.5)
    text = render_summary([floor, row("mlp", 75.2, 1.3), row("cdrb", 89.6, 4.4)])
    assert "75.2 ± 1.3 (75.2) ≈ floor" in text and "89.6 ± 4.4 (89.6) |" in text
    assert "not by more than seed noise" in text and "≤ floor" not in text
    assert "seed noise" not in render_summary([floor, row("cdrb", 89.6, 4.4)])
    # the test's own boundary: with std 2 on 5 seeds each, a gap of 2 is noise (t = 1.58), a gap of 4 is not (3.16)
    assert not _above(row("a", 52.0, 2.0), row("s", 50.0, 2.0)) and _above(row("a", 54.0, 2.0), row("s", 50.0, 2.0))
    assert _above(row("a", 50.1, 0.0), row("s", 50.0, 0.0)) and not _above(row("a", 50.0, 0.0), row("s", 50.0, 0.0))
    assert _above(row("a", 50.1, 9.0, seeds=1), row("s", 50.0, 9.0))  # one seed: no spread to test, means decide


def test_the_summary_says_a_row_whose_floor_solves_every_pair_ranks_nothing():
    """A straight line that solves (nearly) every pair leaves the row no room between floor and ceiling: the row is
    named "floor = ceiling: no comparison" with a note; a row whose floor leaves room is not."""
    from cdrb_cli.stages.report_summary import CEILING, render_summary

    def row(env, method, success):
        return {"env": env, "env_name": env.title(), "method": method, "seeds": 5, "episodes": 100,
                "success_mean": success, "success_std": 0.0, "weighted_success_mean": success}  # fmt: skip

    rows = [row("fetch-reach", "straight", 100.0), row("fetch-reach", "cdrb", 100.0)]
    rows += [row("fetch-push", "straight", CEILING - 0.2), row("fetch-push", "cdrb", 100.0)]
    text = render_summary(rows)
    lines = {ln.split(" | ")[0].strip("| "): ln for ln in text.splitlines() if ln.startswith("| Fetch")}
    assert set(lines) == {"Fetch-Reach (floor = ceiling: no comparison)", "Fetch-Push"}
    assert "cannot rank methods" in text
    assert "floor = ceiling" not in render_summary(rows[2:])


def test_the_summary_gives_a_method_one_column_whatever_preset_each_row_trained_at():
    """Rows trained at different presets (the mazes at the quick one, Fetch at the paper one) share each method's
    column and a note names the rows of the other preset; a row with a method at both presets keeps both columns."""
    from cdrb_cli.stages.report_summary import render_summary

    def row(env, method, success):
        return {"env": env, "env_name": env.title(), "method": method, "seeds": 3, "episodes": 100,
                "success_mean": success, "success_std": 1.0, "weighted_success_mean": success}  # fmt: skip

    rows = [row("maze", "straight", 10.0), row("maze", "cdrb", 99.0), row("fetch-push", "straight (paper)", 30.0),
            row("fetch-push", "cdrb (paper)", 80.0)]  # fmt: skip
    text = render_summary(rows)
    head = text.splitlines()[0]
    assert head.count("cdrb") == 1 and "(paper)" not in head and head.count("straight line") == 1
    assert "| Fetch-Push | 3 x 100 | 30.0 ± 1.0 (30.0) | 80.0 ± 1.0 (80.0) |" in text
    assert "The models of Fetch-Push were trained at the paper preset, the others' at the quick one." in text
    both = render_summary(rows + [row("fetch-push", "cdrb", 70.0)])
    assert "cdrb (paper)" in both.splitlines()[0] and "trained at the paper preset" not in both


def test_first_step_ratio_is_the_median_first_step_over_the_allowed_step():
    """The report's first-step column: per episode the first planned step (obstacle dims) over the step limit,
    the median over every episode of every eval; None without plans or without a known limit."""
    from types import SimpleNamespace

    from cdrb_cli.stages.report import first_step_ratio

    def ev(first_steps, limit):
        plans = np.zeros((len(first_steps), 3, 4))
        plans[:, 1, 0] = first_steps
        plans[:, 1, 2] = 9.0  # a velocity dim: not a position, not measured
        env = SimpleNamespace(obstacles=SimpleNamespace(dims=(0, 1)))
        arrays = {"plans": plans, "episodes/plan_step_limit": np.full(len(first_steps), limit)}
        return SimpleNamespace(arrays=arrays, manifest=SimpleNamespace(env=env))

    assert first_step_ratio([ev([0.1, 0.2, 0.9], 0.1)]) == pytest.approx(2.0)
    assert first_step_ratio([ev([0.1], 0.1), ev([0.3, 0.5], 0.1)]) == pytest.approx(3.0)
    assert first_step_ratio([ev([0.1], 0.0)]) is None
    policy = SimpleNamespace(arrays={}, manifest=None)
    assert first_step_ratio([policy]) is None


def test_a_method_whose_rows_chose_their_own_settings_is_one_summary_column_with_its_settings_named():
    """Where each row ran a method with its own re-planning settings (a tuned selection), the summary gives the
    method one column and names each row's settings under the table; what sets a method apart (a variant, a
    map-aware controller) stays in its column's name, and a row with two settings of one method keeps them apart."""
    from cdrb_cli.stages.report_summary import render_summary

    def row(env, column, settings, success):
        method = column if settings == "plain" else f"{column.split(' [')[0]} [{settings}]"
        return {"env": env, "env_name": env, "method": method, "column": column, "settings": settings, "seeds": 3,
                "episodes": 50, "success_mean": success, "success_std": 1.0, "weighted_success_mean": 5.0}  # fmt: skip

    rows = [
        row("a", "straight", "every 80, waypoints 6 ahead", 20.0),
        row("b", "straight", "every 80, waypoints 6 ahead", 30.0),
        row("c", "straight", "every 80, waypoints 6 ahead", 25.0),
        row("a", "cdrb", "every 80, waypoints 10 ahead", 90.0),
        row("b", "cdrb", "every 80, waypoints 10 ahead", 91.0),
        row("c", "cdrb", "every 80, waypoints 6 ahead", 92.0),
        row("a", "cdrb [geodesic balls]", "every 80, waypoints 10 ahead", 93.0),
    ]
    text = render_summary(rows)
    head = text.splitlines()[0]
    assert head == "| Table 1 row | seeds x pairs | straight line (floor) | cdrb | cdrb [geodesic balls] |"
    assert "| c | 3 x 50 | 25.0 ± 1.0 (5.0) | 92.0 ± 1.0 (5.0) | – |" in text
    assert "straight line: every 80, waypoints 6 ahead on every row" in text
    assert "cdrb: every 80, waypoints 10 ahead (every 80, waypoints 6 ahead on c)" in text
    assert "cdrb [geodesic balls]: every 80, waypoints 10 ahead on every row" in text
    # two settings of one method on one row: each keeps its own column, and no settings note is needed
    apart = render_summary(rows + [row("a", "cdrb", "every 20", 50.0)])
    assert "cdrb [every 80, waypoints 10 ahead]" in apart.splitlines()[0] and "cdrb [every 20]" in apart
    assert "as its row chose them" not in apart


def test_the_run_seed_reaches_an_open_loop_planners_plans(tiny_models, tmp_path, cdrb):
    """`--seed` drives every random choice of an eval, the planner's first plans too: two seeds draw other plans
    on the same pairs; the same seed draws the same; the default seed 0 draws them from the pair seed itself."""
    from cdrb_cli.seeding import eval_plan_seed

    model = tiny_models["diffuser"].path
    plans = {}
    for name, seed in (("a", "0"), ("b", "3"), ("c", "3")):
        r = cdrb("eval", model, "--episodes", "2", "--seeds", "0", "--seed", seed, "--out", tmp_path / f"{name}.h5")
        assert r.returncode == 0, r.stderr
        plans[name] = artifacts.load(tmp_path / f"{name}.h5", "eval").arrays["plans"]
    assert not np.array_equal(plans["a"], plans["b"])
    np.testing.assert_array_equal(plans["b"], plans["c"])
    assert eval_plan_seed(0, 7) == 7 and eval_plan_seed(3, 7) != 7 and eval_plan_seed(3, 7) != eval_plan_seed(3, 8)
