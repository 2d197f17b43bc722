"""The benchmark scripts run end to end on tiny settings (the same code paths as the recorded runs)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parent.parent


@pytest.mark.slow
def test_table1_script_tiny(tmp_path):
    out = tmp_path / "t1"
    cmd = [
        sys.executable,
        str(ROOT / "benchmarks" / "table1.py"),
        "--tiny",
        "--out",
        str(out),
        "--envs",
        "maze-tight",
        "--methods",
        "mlp,cdrb",
        "--seeds",
        "0,1",
        "--timed-too",
    ]
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=900)
    assert proc.returncode == 0, proc.stderr[-2000:]
    table = (out / "table1.md").read_text()
    assert "| Maze Tight |" in table and "Maze Tight (paper)" in table
    assert (out / "table1_timings.json").exists() and (out / "table1.png").stat().st_size > 5000
    timed = (out / "table1-timed.md").read_text()
    assert "| Maze Tight | mlp | pd (kp 10.0, kd 1.0, max_lag None, max_wait None) | test | 2 x 3 |" in timed
    # a second run skips every stage
    again = subprocess.run(cmd, capture_output=True, text=True, timeout=900)
    assert again.returncode == 0
    stages = [line for line in again.stdout.splitlines() if line.startswith(("done", "skip"))]
    assert stages and all(line.startswith("skip") for line in stages if " cdrb report " not in line), stages
    # the grid runs in parts: a Fetch row added later joins the rows already there, in the paper's order
    fetch = [*cmd[: cmd.index("--envs")], "--envs", "fetch-reach", "--methods", "mlp,cdrb", "--seeds", "0,1"]
    proc = subprocess.run(fetch, capture_output=True, text=True, timeout=900)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert "cdrb collect fetch-reach -n 40 " in proc.stdout  # --tiny caps the Fetch default of 5000 demos
    table = (out / "table1.md").read_text()
    assert table.index("| Maze Tight |") < table.index("| Reach |") and "Reach (paper)" in table
    # ... and so do methods: a policy's column joins the planners' (no plan clock, no official executor for it)
    policy = [
        *cmd[: cmd.index("--methods")],
        "--methods",
        "diffusion-bc",
        "--seeds",
        "0,1",
        "--official-too",
        "--timed-too",
    ]
    proc = subprocess.run(policy, capture_output=True, text=True, timeout=900)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert "official" not in proc.stdout.split("diffusion-bc", 1)[1] and not list(
        out.glob("*/eval-diffusion-bc*-timed*")
    )
    table = (out / "table1.md").read_text()
    for row in (
        "| Maze Tight | mlp |",
        "| Maze Tight | cdrb |",
        "| Maze Tight | diffusion-bc | closed loop",
        "| Reach | cdrb |",
    ):
        assert row in table, row


def test_planning_script(tmp_path, small_data):
    from cdrb_cli.methods.config import train_config
    from cdrb_cli.stages.train import train
    from tests.test_train import tiny

    demos, buffer = small_data
    model = train(demos, buffer, train_config(demos, buffer, "cdrb", tiny("cdrb", steps=10)), tmp_path / "m.h5")
    proc = subprocess.run(
        [sys.executable, str(ROOT / "benchmarks" / "planning.py"), str(model.path), "--pairs", "4"],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert "| cdrb (quick) | paper (8) |" in proc.stdout


@pytest.mark.slow
def test_comparison_script_tunes_fetch_controllers_and_keeps_other_envs(tmp_path):
    """On Fetch the comparison tunes each method's controller among the task's candidates (the same controllers for
    every method; a method with denoising steps also tries each with fewer of them) on the tuning stream, and
    `write` keeps the settings already chosen for other environments. A training budget cut with `--steps` trains
    the sweep so and is recorded in the settings, so that table1.py trains every seed the same."""
    import csv
    import json

    from cdrb_cli import artifacts

    out = tmp_path / "cmp"
    out.mkdir()
    (out / "tuned.json").write_text(json.dumps({"meta": {}, "settings": {"maze": {"mlp": {"candidate": "x"}}}}))
    cmd = [sys.executable, str(ROOT / "benchmarks" / "comparison.py"), "all", "--tiny", "--out", str(out)]
    cmd += ["--envs", "fetch-reach", "--methods", "mlp,cdrb", "--device", "cpu", "--steps", "40"]
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=900)
    assert proc.returncode == 0, proc.stderr[-2000:]
    settings = json.loads((out / "tuned.json").read_text())["settings"]
    assert settings["maze"] == {"mlp": {"candidate": "x"}}
    from benchmarks.comparison import FETCH_CONTROLLERS, FETCH_SAMPLE_STEPS, clocks_for

    for method in ("mlp", "cdrb"):
        t = settings["fetch-reach"][method]
        assert t["candidate"] == "quick" and t["train_flags"] == ["--steps", "40"]
        assert artifacts.load(t["model"], "model").manifest.config.steps == 40
        assert t["eval_flags"] == clocks_for("fetch-reach", method)[t["clock"]]
        assert t["curve_models"] == {"0": t["model"]} and Path(t["model"]).name == f"{method}-quick.h5"
    assert settings["fetch-reach"]["mlp"]["eval_flags"] in FETCH_CONTROLLERS["reach"].values()  # no sampling steps
    with open(out / "tuning_clock.csv") as fh:
        rows = list(csv.DictReader(fh))
    controllers = FETCH_CONTROLLERS["reach"]
    stepped = [f"{c}, {n} sampling steps" for c in controllers for n in FETCH_SAMPLE_STEPS]
    assert sorted((r["method"], r["clock"]) for r in rows) == sorted(
        [("mlp", c) for c in controllers] + [("cdrb", c) for c in [*controllers, *stepped]]
    )
    assert clocks_for("fetch-reach", "cdrb")[stepped[-1]][-2:] == ["--sample-steps", str(FETCH_SAMPLE_STEPS[-1])]
    assert not (out / "fetch-reach" / "buffer-k1000-state-action.h5").exists()  # no sweep candidate needs it
    with open(out / "tuning.csv") as fh:
        assert [int(r["steps"]) for r in csv.DictReader(fh)] == [40, 40]


def test_table1_seeds_merges_earlier_parts_and_writes_the_docs_rows(tmp_path):
    """`table1_seeds.py --merge --docs`: the (env, method) pairs re-measured replace their old rows, every other row
    is kept (an older CSV without the sampling-steps column gets "all"), the markdown block shows mean ± sample std,
    failures by cause, the sampling steps and the paper's figure; with nothing measured nothing is written."""
    import csv

    from tests import factories

    csv_path, doc = tmp_path / "t.csv", tmp_path / "doc.md"
    old = "env,method,seed,episodes,success,in_obstacle,plans_through_obstacle,collisions,plan_ms,controller,preset,"
    old += "failed_plan,failed_grasp,failed_collision,failed_tracking\n"
    old += "fetch-reach,cdrb,0,100,100.0,0.0,0.0,0.0,1.0,fetch-track,quick,,,,\n"
    old += "fetch-push,cdrb,0,100,50.0,0.0,0.0,0.0,1.0,fetch-track,quick,,,,\n"
    old += "fetch-reach-obstacle,cdrb,0,100,50.0,1.0,40.0,40.0,1.0,fetch-track,quick,50,0,0,0\n"
    old += "fetch-reach-obstacle,cdrb,1,100,70.0,3.0,20.0,20.0,1.0,fetch-track,quick,29,0,1,0\n"
    old += "maze-tight,mlp,0,5,80.0,1.0,20.0,0.0,1.0,pd,quick,1,0,0,0\n"
    old += "maze-tight,cdrb,0,5,10.0,1.0,20.0,0.0,1.0,pd,quick,4,0,0,1\n"
    csv_path.write_text(old)
    doc.write_text("# T\n\n<!-- fetch-rows:begin -->\nstale\n<!-- fetch-rows:end -->\n\ntail\n")
    runs = tmp_path / "runs"
    (runs / "maze-tight").mkdir(parents=True)
    script = [sys.executable, str(ROOT / "benchmarks" / "table1_seeds.py"), "--runs", str(runs)]
    script += ["--envs", "maze-tight", "--methods", "cdrb", "--out", str(csv_path), "--merge", "--docs", str(doc)]
    # nothing measured yet: an error, and the CSV and the docs stay as they were
    proc = subprocess.run(script, capture_output=True, text=True, timeout=120)
    assert proc.returncode != 0 and "nothing written" in proc.stderr
    assert csv_path.read_text() == old and "stale" in doc.read_text()
    factories.write(runs / "maze-tight" / "eval-cdrb-tuned-s0.h5", "eval")  # 5 episodes, all successes
    proc = subprocess.run(script, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    with csv_path.open() as f:
        rows = list(csv.DictReader(f))
    got = [(r["env"], r["method"], r["seed"], r["sample_steps"], r["success"]) for r in rows]
    assert got == [  # Table 1's row order
        ("maze-tight", "cdrb", "0", "all", "100.0"),  # re-measured
        ("maze-tight", "mlp", "0", "all", "80.0"),  # not re-measured: kept
        ("fetch-reach-obstacle", "cdrb", "0", "all", "50.0"),
        ("fetch-reach-obstacle", "cdrb", "1", "all", "70.0"),
        ("fetch-reach", "cdrb", "0", "all", "100.0"),
        ("fetch-push", "cdrb", "0", "all", "50.0"),
    ]
    assert rows[0]["success_no_collision"] == "100.0" and rows[0]["failed_plan"] == ""  # the factory has no causes
    text = doc.read_text()
    assert "stale" not in text and text.endswith("tail\n")
    lines = text.splitlines()
    line = next(x for x in lines if x.startswith("| Reach Obstacle"))
    assert "| 60.0 ± 14.1 | – |" in line and "| 2.00 |" in line and "| 79 / 0 / 1 / 0 |" in line and "97.92" in line
    assert "– (all succeeded)" in next(x for x in lines if x.startswith("| Reach |"))
    assert "– (not classified)" in next(x for x in lines if x.startswith("| Push |"))
    assert "| 100.0 ± – | 100.0 |" in next(x for x in lines if x.startswith("| Maze Tight | CDRB"))
    # a closed-loop policy's eval (no plan arrays): its plan measures are "n/a", never a 0 that reads as "no wall hit"
    policy = factories.write(runs / "maze-tight" / "eval-diffusion-bc-tuned-s0.h5", "eval")
    with factories.tampered(policy) as f:
        for name in ("plan_in_wall_fraction", "plan_crosses_obstacle", "plan_max_jump", "plan_step_limit"):
            del f[f"episodes/{name}"]
    script[script.index("cdrb")] = "diffusion-bc"
    proc = subprocess.run(script, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    assert "no plans (closed-loop policy)" in proc.stdout
    with csv_path.open() as f:
        row = next(r for r in csv.DictReader(f) if r["method"] == "diffusion-bc")
    assert row["in_obstacle"] == row["plans_through_obstacle"] == "" and row["controller"] == "closed loop (paper)"
    line = next(x for x in doc.read_text().splitlines() if x.startswith("| Maze Tight | diffusion-bc"))
    assert "| `closed loop (paper)` |" in line and "| n/a | n/a |" in line


def test_table1_summary_joins_the_maze_and_fetch_rows_in_table1_order(tmp_path):
    """`table1_summary.py`: the maze report's aggregated rows (official-code protocol left out) and the Fetch per-seed
    rows, averaged with the sample std, and the policies' report rows, in Table 1's order with the paper's figure;
    the README block shows every Table-1 row, each method in its own column, "not measured yet" where nothing is; a
    missing input is a one-line error and writes nothing."""
    import csv

    mazes, fetch, out, readme = (tmp_path / n for n in ("m.csv", "f.csv", "all.csv", "README.md"))
    policies = tmp_path / "p.csv"
    head = "env,method,seeds,episodes,protocol,controller,success_mean,success_std,in_wall_mean,crossing_mean,"
    head += "collision_mean\n"
    mazes.write_text(
        head + "maze,cdrb,5,100,ours,pd,99.0,1.0,0.5,2.0,3.0\nmaze,cdrb,5,100,official-code,pd,50.0,1.0,0.5,2.0,3.0\n"
    )
    fhead = "env,method,seed,episodes,success,in_obstacle,plans_through_obstacle,collisions,controller,sample_steps\n"
    fetch.write_text(
        fhead
        + "fetch-push,mlp,0,100,80.0,1.0,10.0,5.0,fetch-track,all\n"
        + "fetch-push,mlp,1,100,90.0,3.0,20.0,5.0,fetch-track,all\n"
        + "fetch-reach,cdrb,0,100,100.0,0.0,0.0,0.0,fetch-track,2\n"
    )
    policies.write_text(head + "maze,diffusion-ql,3,100,ours,closed loop,88.0,2.0,,,40.0\n")  # a policy: no plans
    readme.write_text("x\n<!-- table1-all:begin -->\nstale\n<!-- table1-all:end -->\ny\n")
    script = [sys.executable, str(ROOT / "benchmarks" / "table1_summary.py"), "--mazes", str(mazes)]
    proc = subprocess.run(
        [*script, "--fetch", str(tmp_path / "nope.csv"), "--out", str(out)], capture_output=True, text=True
    )
    assert proc.returncode != 0 and "--fetch" in proc.stderr and "Traceback" not in proc.stderr
    assert not out.exists()
    proc = subprocess.run(
        [*script, "--fetch", str(fetch), "--policies", str(tmp_path / "nope.csv"), "--out", str(out)],
        capture_output=True,
        text=True,
    )
    assert proc.returncode != 0 and "--policies" in proc.stderr and "Traceback" not in proc.stderr
    assert not out.exists()
    proc = subprocess.run(
        [*script, "--fetch", str(fetch), "--policies", str(policies), "--out", str(out), "--readme", str(readme)],
        capture_output=True,
        text=True,
    )
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.strip() == str(out)
    with out.open() as f:
        rows = list(csv.DictReader(f))
    got = [(r["env"], r["method"]) for r in rows]
    assert got == [("maze", "diffusion-ql"), ("maze", "cdrb"), ("fetch-reach", "cdrb"), ("fetch-push", "mlp")]
    assert rows[1]["success_mean"] == "99.0" and rows[1]["paper_mean"] == "95.33"
    dql = rows[0]
    assert (dql["success_mean"], dql["in_obstacle"], dql["collisions"], dql["paper_mean"]) == (
        "88.0",
        "",
        "40.0",
        "100.0",
    )
    push = rows[3]
    assert (push["training_seeds"], push["success_mean"], push["success_std"]) == ("2", "85.0", "7.071")
    assert (push["in_obstacle"], push["plans_through_obstacle"], push["paper_mean"]) == ("2.0", "15.0", "2.45")
    assert rows[2]["setting"] == "fetch-track, 2 sampling steps" and rows[2]["success_std"] == ""
    lines = readme.read_text().splitlines()
    assert "stale" not in lines and lines[0] == "x" and lines[-1] == "y"
    table = [x for x in lines if x.startswith("| ") and not x.startswith("| Table 1")]
    assert len(table) == 8  # every Table-1 row, measured or not
    # columns: MLP, Diffuser, Diffusion BC, Diffusion-QL, CDRB, CDRB's obstacle rates, the paper's five
    maze = next(x for x in table if x.startswith("| Maze |"))
    assert "| – | – | – | 88.0 ± 2.0 | **99.0 ± 1.0** | 0.50 / 2.0 | 74.22 / 100.00 / 90.13 / 100.00 / 95.33 |" in maze
    assert "| 85.0 ± 7.1 | – | – | – | – | – |" in next(x for x in table if x.startswith("| Push |"))
    assert "not measured yet" in next(x for x in table if x.startswith("| Pick & Place |"))


def test_policy_actions_draws_held_out_expert_transitions_and_scores_agreement(small_data):
    """policy_actions.py: the transitions come from validation episodes only, with the episode's final state as
    goal and the expert's own action (the first-step set: each validation episode's first row); the expert scores
    error 0 / cosine 1, its reverse cosine -1 (every action off), a half-strength copy keeps the direction and has
    norm ratio 0.5."""
    sys.path.insert(0, str(ROOT / "benchmarks"))
    from policy_actions import agreement, first_steps, held_out

    from cdrb_cli.buffer import Normalizer, demo_features

    demos, _ = small_data
    raw = demo_features(demos, "state-action")
    norm = Normalizer(low=raw.min(axis=0), high=raw.max(axis=0))
    obs_dim, goal_dims = demos.manifest.env.obs_dim, list(demos.manifest.env.goal_dims)
    states, goals, actions = held_out(demos, norm, obs_dim, goal_dims, 300, 0)
    valid = set(demos.episode_ids("valid").tolist())
    assert valid and len(valid) < len(demos.episode_length)
    episode = np.repeat(np.arange(len(demos.episode_length)), demos.episode_length)
    last = demos.episode_start + demos.episode_length - 1
    # each drawn (state, action) is a demonstration row of a validation episode, its goal that episode's final state
    dist = np.abs(raw[None, :, :obs_dim] - states[:, None]).max(axis=2)
    row = dist.argmin(axis=1)
    assert dist[np.arange(len(row)), row].max() < 1e-4
    np.testing.assert_allclose(raw[row, obs_dim:], actions, atol=1e-4)
    assert set(episode[row].tolist()) <= valid
    np.testing.assert_allclose(raw[last[episode[row]]][:, goal_dims], goals, atol=1e-4)
    # the first-step set: every validation episode's first row, at rest, its goal the episode's final state
    s0, g0, a0 = first_steps(demos, obs_dim, goal_dims)
    ids = demos.episode_ids("valid")
    np.testing.assert_array_equal(s0, raw[demos.episode_start[ids], :obs_dim])
    np.testing.assert_array_equal(a0, raw[demos.episode_start[ids], obs_dim:])
    np.testing.assert_array_equal(g0, raw[last[ids]][:, goal_dims])

    same = agreement(actions, actions)
    assert same["mean_abs_error"] == 0 and same["median_cosine"] == 1 and same["off_by_25deg"] == 0
    assert same["norm_ratio"] == 1
    rev = agreement(-actions, actions)
    assert rev["median_cosine"] == -1 and rev["off_by_25deg"] == 1
    half = agreement(0.5 * actions, actions)
    assert half["median_cosine"] == 1 and half["norm_ratio"] == 0.5 and half["off_by_25deg"] == 0


@pytest.mark.slow
def test_comparison_script_tunes_a_policys_sampler_in_place_of_a_clock(tmp_path):
    """A closed-loop policy has no plan clock: `clock` tries its samplers on the tuning stream instead (its default
    first, which keeps a tie; its eval is the sweep's own, copied, not run again), and `write` records the pick's
    flags for table1.py."""
    import csv
    import json

    from benchmarks.comparison import clocks_for

    out = tmp_path / "cmp"
    cmd = [sys.executable, str(ROOT / "benchmarks" / "comparison.py"), "all", "--tiny", "--out", str(out)]
    cmd += ["--envs", "maze", "--methods", "diffusion-bc", "--candidates", "1", "--device", "cpu"]
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=900)
    assert proc.returncode == 0, proc.stderr[-2000:]
    samplers = clocks_for("maze", "diffusion-bc")
    assert samplers == {"ddpm-x": [], "ddpm": ["--sampler", "ddpm"]}  # every sampler of its config, the default first
    assert list(clocks_for("maze", "diffusion-ql")) == ["q-softmax", "ddpm"]
    sweep = out / "maze" / "sweep"
    default = sweep / "clock-diffusion-bc-ddpm-x.h5"
    assert default.read_bytes() == next(sweep.glob("eval-diffusion-bc-*.h5")).read_bytes()
    assert "clock-diffusion-bc-ddpm-x.h5: copied from eval-diffusion-bc-" in proc.stdout
    assert "--out " + str(default) not in proc.stdout  # never evaluated a second time
    t = json.loads((out / "tuned.json").read_text())["settings"]["maze"]["diffusion-bc"]
    with open(out / "tuning_clock.csv") as fh:
        rows = {r["clock"]: float(r["success"]) for r in csv.DictReader(fh)}
    assert set(rows) == {"ddpm-x", "ddpm"}
    best = "ddpm" if rows["ddpm"] > rows["ddpm-x"] else "ddpm-x"
    assert t["clock"] == best and t["eval_flags"] == samplers[best]


def test_closed_loop_pools_an_earlier_runs_rows_as_if_every_seed_were_one_run(tmp_path):
    """closed_loop.py `write --pool-with`: success over two runs' seeds is the mean and sample std of all the seeds'
    values (here recovered from each run's mean, std and count), rates are seed-weighted, failures summed, the
    earlier tuning rows kept; a seed in both runs, a CSV that is not one, and a method the picks lack are errors."""
    sys.path.insert(0, str(ROOT / "benchmarks"))
    import argparse
    import json

    from closed_loop import picks, pool, pool_rows, read_rows

    rng = np.random.default_rng(0)
    for _ in range(20):
        a, b = rng.integers(0, 101, rng.integers(1, 5)), rng.integers(0, 101, rng.integers(2, 5))
        sd = lambda x: float(np.std(x, ddof=1)) if len(x) > 1 else 0.0  # noqa: E731
        mean, std = pool(len(a), a.mean(), sd(a), len(b), b.mean(), sd(b))
        both = np.concatenate([a, b])
        assert np.isclose(mean, both.mean()) and np.isclose(std, np.std(both, ddof=1))

    earlier = tmp_path / "old.csv"
    earlier.write_text(
        "stage,env,method,setting,training_seeds,success,success_std,crossing,collision,replans,planning_ms\n"
        "tune,maze-tight,cdrb,open loop,1,100.0,0.0,0.0,0.0,0.0,140.0\n"
        "tune,maze-tight,cdrb,every 20,1,92.0,0.0,32.0,0.0,16.0,900.0\n"
        "test,maze-tight,cdrb,open loop,3,99.0,1.0,0.3,1.0,0.0,148.0\n"
    )
    mine = [
        dict(stage="test", env="maze-tight", method="cdrb", setting="open loop", training_seeds=2, seeds="3 4",
             success=97.0, success_std=1.41, crossing=1.0, collision=2.0, replans=0.0, planning_ms=150.0,
             failed_plan=1, failed_tracking=4),
        dict(stage="test", env="maze-tight", method="mlp", setting="open loop", training_seeds=2, seeds="3 4",
             success=70.0, success_std=0.0, crossing=40.0, collision=30.0, replans=0.0, planning_ms=0.2,
             failed_plan=60, failed_tracking=0),
    ]  # fmt: skip
    rows = pool_rows(mine, read_rows(earlier))
    tune = [r for r in rows if r["stage"] == "tune"]
    assert [r["setting"] for r in tune] == ["open loop", "every 20"]
    cdrb = next(r for r in rows if r["stage"] == "test" and r["method"] == "cdrb")
    seeds = [98, 99, 100, 96, 98]  # the values behind both runs' means and stds
    assert cdrb["training_seeds"] == 5 and cdrb["success"] == round(np.mean(seeds), 2)
    assert abs(cdrb["success_std"] - np.std(seeds, ddof=1)) < 0.01
    assert cdrb["crossing"] == round((3 * 0.3 + 2 * 1.0) / 5, 2) and cdrb["planning_ms"] == 148.8
    assert cdrb["failed_plan"] is None  # the earlier run did not count its failures: no sum
    assert cdrb["seeds"] == "(3 earlier) 3 4"
    mlp = next(r for r in rows if r["method"] == "mlp")
    assert mlp == mine[1]  # nothing earlier to pool with
    with pytest.raises(SystemExit, match=r"training seed\(s\) \['3'\] twice"):
        pool_rows(mine, [dict(r, seeds="2 3") for r in read_rows(earlier)])
    (tmp_path / "bad.csv").write_text("a,b\n1,2\n")
    with pytest.raises(SystemExit, match="--pool-with .*bad.csv"):
        read_rows(tmp_path / "bad.csv")
    recorded = tmp_path / "picks.json"
    recorded.write_text(json.dumps({"cdrb": {"open loop": "open loop"}}))
    args = argparse.Namespace(picks=recorded, methods=["cdrb"], out=tmp_path, env="maze-tight")
    assert picks(args) == {"cdrb": {"open loop": "open loop"}}
    with pytest.raises(SystemExit, match="--picks .*no picks for mlp"):
        picks(argparse.Namespace(**{**vars(args), "methods": ["cdrb", "mlp"]}))


def test_policy_actions_measures_every_sampler_a_policy_allows_and_refuses_a_planner(small_data, tmp_path):
    """policy_actions.py's `measure`: one row per set and per sampler the method's config allows (the model's own
    first), the same list comparison.py tunes; a planner's model is a one-line error."""
    sys.path.insert(0, str(ROOT / "benchmarks"))
    from comparison import policy_samplers
    from policy_actions import measure

    from cdrb_cli.methods.config import train_config
    from cdrb_cli.stages.train import train

    demos, _ = small_data
    tiny = {"net.embed_dim": 16, "net.hidden": 32, "method.diffusion_steps": 4, "batch_size": 8, "steps": 2}
    cfg = train_config(demos, None, "diffusion-bc", {**tiny, "method.sampler": "ddpm"})
    train(demos, None, cfg, tmp_path / "bc.h5")
    rows = measure(tmp_path / "bc.h5", 16, 0)
    assert [(r["set"], r["sampler"]) for r in rows] == [
        (s, sampler) for s in ("transitions", "first step") for sampler in ("ddpm", "ddpm-x")
    ]
    assert set(policy_samplers("diffusion-bc")) == {"ddpm", "ddpm-x"}
    assert rows[0]["pairs"] == 16 and 0 <= rows[0]["off_by_25deg"] <= 1
    mlp = train_config(demos, None, "mlp", {"steps": 2, "batch_size": 8})
    train(demos, None, mlp, tmp_path / "mlp.h5")
    with pytest.raises(SystemExit, match="mlp.h5: mlp is a planner"):
        measure(tmp_path / "mlp.h5", 16, 0)
