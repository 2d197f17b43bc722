"""`cdrb select` and the studies as experiment files: the selection rule, and the maze tuning -> select -> Table-1 ->
report chain run from the shipped files at a tiny budget."""

from __future__ import annotations

import csv
import json
import re
import shutil
import subprocess
from pathlib import Path

import pytest
import tomllib

import cdrb_cli.cli  # noqa: F401  (installs the description of the commands a grid composes)
from cdrb_cli import artifacts
from cdrb_cli.orchestration.select import RULE, Candidate, choose
from tests.conftest import call_cdrb

ROOT = Path(__file__).resolve().parent.parent


def _cand(variant, order, steps=None, success=50.0, crossing=0.0, collision=0.0, method="cdrb"):
    return Candidate("maze", method, variant, order, steps, success=success, crossing=crossing, collision=collision)


def test_the_rule_ranks_success_then_crossings_then_collisions_then_order_then_steps():
    base = _cand("a", 0)
    assert choose([base, _cand("b", 1, success=60.0)])[("maze", "cdrb")].variant == "b"
    # equal success: fewer plans through an obstacle, however many collisions
    assert (
        choose([_cand("a", 0, crossing=5.0), _cand("b", 1, crossing=1.0, collision=90.0)])[("maze", "cdrb")].variant
        == "b"
    )
    assert choose([_cand("a", 0, collision=5.0), _cand("b", 1, collision=1.0)])[("maze", "cdrb")].variant == "b"
    # a full tie: the grid's variant order, whatever order the candidates come in
    assert choose([_cand("b", 1), _cand("a", 0)])[("maze", "cdrb")].variant == "a"
    # the same variant at two training lengths: fewer steps
    assert choose([_cand("a", 0, steps=2000), _cand("a", 0, steps=1000)])[("maze", "cdrb")].steps == 1000
    # a policy has no plans (crossing None): counted as none through an obstacle
    assert (
        choose([_cand("a", 0, crossing=None, method="p"), _cand("b", 1, crossing=2.0, method="p")])[
            ("maze", "p")
        ].variant
        == "a"
    )
    # each env x method on its own
    assert set(choose([base, _cand("a", 0, method="mlp")])) == {("maze", "cdrb"), ("maze", "mlp")}
    assert "success" in RULE and "steps" in RULE


def test_the_spread_between_training_seeds_needs_two_seeds():
    from cdrb_cli.orchestration.select import seed_spread

    assert seed_spread([{"success": 40.0}]) is None and seed_spread([]) is None
    assert seed_spread([{"success": 40.0}, {"success": 60.0}]) == pytest.approx(14.1421, abs=1e-3)
    assert seed_spread([{"success": 40.0}, {"success": None}]) is None  # a point some eval did not measure


def _cdrb(*args, cwd: Path, check: bool = True) -> subprocess.CompletedProcess:
    proc = call_cdrb(*args, cwd=cwd, env={"OMP_NUM_THREADS": "1"})
    assert proc.returncode == 0 or not check, (args, proc.stderr[-3000:])
    return proc


def _point(variant, order, steps, successes, method="cdrb", map_aware=False):
    """A curve point: a candidate whose training seeds 0, 1, ... succeed as ``successes`` say."""
    c = _cand(variant, order, steps, success=sum(successes) / len(successes), method=method)
    c.models = [{"seed": i, "success": v} for i, v in enumerate(successes)]
    c.map_aware = map_aware
    return c


def test_a_curve_still_rises_when_its_best_candidate_gains_more_than_the_standard_error():
    """The points of a curve are snapshots of the same runs: the gain is judged per training seed (paired)."""
    from cdrb_cli.orchestration.select import still_rising

    cands = [
        # CDRB: the best at 5k (s8, 94.7) gained 60, 17, 33 over its own 2.5k runs: 36.7 ± 12.5, rising
        _point("k2", 0, 2500, [20.0, 30.0, 16.0]),
        _point("k2", 0, 5000, [90.0, 30.0, 27.0]),
        _point("s8", 1, 2500, [40.0, 70.0, 64.0]),
        _point("s8", 1, 5000, [100.0, 87.0, 97.0]),
        # Diffuser: the best at 5k (k2 by variant order on a tie) gained 4, -2, 1: 1.0 ± 1.7, not rising, though its
        # other candidate gained 10, -2, 2
        _point("k2", 0, 2500, [96.0, 97.0, 98.0], "diffuser"),
        _point("k2", 0, 5000, [100.0, 95.0, 99.0], "diffuser"),
        _point("s8", 1, 2500, [90.0, 96.0, 98.0], "diffuser"),
        _point("s8", 1, 5000, [100.0, 94.0, 100.0], "diffuser"),
        # one length only: no curve to judge
        _point("k2", 0, 5000, [10.0, 90.0, 50.0], "mlp"),
    ]
    rising = still_rising(cands)
    assert set(rising) == {("maze", "cdrb")}
    rise = rising[("maze", "cdrb")]
    assert rise.best.variant == "s8" and abs(rise.gain - 36.67) < 0.01 and abs(rise.se - 12.55) < 0.01
    assert rise.by == "success"
    # the same means, but every run gained alike: paired, a rise; and a gain within the noise is not one
    assert still_rising([_point("k2", 0, 1000, [50.0, 70.0, 60.0]), _point("k2", 0, 2000, [52.0, 72.0, 62.0])])
    assert not still_rising([_point("k2", 0, 1000, [50.0, 70.0, 60.0]), _point("k2", 0, 2000, [60.0, 66.0, 60.0])])
    # a paired gain at the ceiling (every seed solves every episode) leaves nothing to extend for; one seed short
    # of it still rises
    assert not still_rising([_point("k2", 0, 5000, [98.0, 97.0, 96.0]), _point("k2", 0, 10000, [100.0, 100.0, 100.0])])
    assert still_rising([_point("k2", 0, 5000, [98.0, 97.0, 96.0]), _point("k2", 0, 10000, [100.0, 100.0, 99.0])])
    # variants whose curves stop at different lengths: the best is judged against its own previous point (k2 at
    # 2k), not the grid's second-longest length (3k, where only s8 has a point)
    staggered = [
        _point("k2", 0, 1000, [5.0, 8.0, 6.0]),
        _point("k2", 0, 2000, [20.0, 25.0, 18.0]),
        _point("k2", 0, 4000, [60.0, 66.0, 58.0]),
        _point("s8", 1, 1000, [5.0, 6.0, 7.0]),
        _point("s8", 1, 2000, [10.0, 12.0, 11.0]),
        _point("s8", 1, 3000, [12.0, 12.0, 13.0]),
    ]
    rise = still_rising(staggered)[("maze", "cdrb")]
    assert rise.best.variant == "k2" and rise.best.steps == 4000 and abs(rise.gain - 40.33) < 0.01
    # the variant the rule chooses stops short of a longer, losing one: its own rise is not hidden by the other's
    # level curve (nor flagged when it had levelled off)
    short = [_point("a", 0, 50, [10.0, 20.0, 30.0]), _point("a", 0, 100, [60.0, 70.0, 80.0])]
    long = [_point("b", 1, n, [5.0, 5.0, 5.0]) for n in (50, 100, 200)]
    rise = still_rising(short + long)[("maze", "cdrb")]
    assert rise.best.variant == "a" and rise.best.steps == 100 and abs(rise.gain - 50.0) < 0.01
    level = [_point("a", 0, 50, [60.0, 70.0, 80.0]), _point("a", 0, 100, [61.0, 69.0, 80.0])]
    assert not still_rising(level + long)
    # a choice at an earlier point of its own curve (it fell later) is not the end of a rising curve
    fell = [*short, _point("a", 0, 150, [40.0, 40.0, 40.0])]
    assert not still_rising(fell + long)


def test_the_curve_judged_still_rising_is_the_one_the_rule_can_choose():
    """A map-aware executor that solves every pair at both lengths (the best by success, never chosen) does not hide
    the rise of the candidate the rule chooses."""
    from cdrb_cli.orchestration.select import still_rising

    track = [_point("track", 1, n, v, "mlp") for n, v in ((2500, [71.0, 64.0, 67.0]), (5000, [83.0, 82.0, 84.0]))]
    aware = [_point("push-path", 0, n, [100.0, 100.0, 100.0], "mlp", map_aware=True) for n in (2500, 5000)]
    rise = still_rising(aware + track)[("maze", "mlp")]
    assert rise.best.variant == "track" and abs(rise.gain - 15.67) < 0.01
    assert not still_rising(aware)


def test_a_planner_is_never_chosen_with_a_controller_that_reads_the_map():
    from cdrb_cli.errors import BadInput

    aware = _cand("push-path", 0, success=90.0)
    aware.map_aware = True
    assert choose([aware, _cand("track", 1, success=70.0)])[("maze", "cdrb")].variant == "track"
    with pytest.raises(BadInput, match="every candidate is executed by a controller that reads the map"):
        choose([aware])
    from cdrb_cli.envs.registry import CONTROLLERS

    assert CONTROLLERS.get("fetch-push-path").knows_map and not CONTROLLERS.get("fetch-track").knows_map


def test_a_shared_budget_trains_every_planner_of_an_environment_to_one_length():
    """Chosen alone, CDRB stops at 5k and Diffuser runs to 10k; with a shared budget both are chosen at 10k (CDRB by
    the rule among its 10k candidates), the policy and the untrained straight line keep their own."""

    def cands():
        return [
            _cand("k2", 0, 5000, success=80.0),
            _cand("k2", 0, 10000, success=78.0, crossing=5.0),
            _cand("s8", 1, 10000, success=79.0, crossing=9.0),
            _cand("k2", 0, 5000, success=60.0, method="diffuser"),
            _cand("k2", 0, 10000, success=70.0, method="diffuser"),
            _cand("policy", 0, 2500, success=50.0, crossing=None, method="diffusion-bc"),
            _cand("policy", 0, 10000, success=40.0, crossing=None, method="diffusion-bc"),
            _cand("base", 0, None, success=10.0, method="straight"),
        ]

    alone = choose(cands())
    assert alone[("maze", "cdrb")].steps == 5000 and alone[("maze", "diffuser")].steps == 10000
    listed = cands()
    for c in listed:
        c.planner = c.method != "diffusion-bc"
    shared = choose(listed, shared_budget=True)
    assert shared[("maze", "cdrb")].steps == 10000 and shared[("maze", "cdrb")].variant == "s8"
    assert shared[("maze", "diffuser")].steps == 10000
    assert shared[("maze", "diffusion-bc")].steps == 2500 and shared[("maze", "straight")].steps is None


def test_a_curve_whose_plans_through_obstacles_still_fall_is_extended_with_its_environment():
    from cdrb_cli.orchestration.select import still_rising

    def point(steps, successes, crossings, method="cdrb"):
        c = _cand("k2", 0, steps, success=sum(successes) / 3, crossing=sum(crossings) / 3, method=method)
        c.models = [
            {"seed": i, "success": s, "plans_through_obstacle": x} for i, (s, x) in enumerate(zip(successes, crossings))
        ]
        return c

    cands = [
        # CDRB: success flat within noise, its plans through the obstacle falling 81 -> 27 on every seed
        point(2500, [70.0, 75.0, 72.0], [81.0, 85.0, 80.0]),
        point(5000, [72.0, 70.0, 74.0], [30.0, 25.0, 27.0]),
        point(2500, [60.0, 62.0, 61.0], [50.0, 52.0, 51.0], "diffuser"),
        point(5000, [61.0, 60.0, 62.0], [51.0, 50.0, 52.0], "diffuser"),
    ]
    assert set(still_rising(cands)) == {("maze", "cdrb")}
    shared = still_rising(cands, shared_budget=True)
    assert set(shared) == {("maze", "cdrb"), ("maze", "diffuser")}
    assert shared[("maze", "cdrb")].by == "crossings" and shared[("maze", "diffuser")].by == "shared"
    assert shared[("maze", "cdrb")].text().endswith("success points, fewer plans through an obstacle")
    # success level at the ceiling, or unchanged on every seed, while the crossings fall: a rise by crossings, said so
    ceiling = [point(2500, [98.0, 97.0, 96.0], [40.0, 41.0, 39.0]), point(5000, [100.0] * 3, [10.0, 12.0, 11.0])]
    flat = [point(2500, [70.0] * 3, [40.0, 41.0, 39.0]), point(5000, [70.0] * 3, [10.0, 12.0, 11.0])]
    for case in (ceiling, flat):
        rise = still_rising(case)[("maze", "cdrb")]
        assert rise.by == "crossings" and "fewer plans through an obstacle" in rise.text(), rise
    # no plan left through an obstacle: nothing left to fall
    done = [point(2500, [70.0, 75.0, 72.0], [9.0, 8.0, 7.0]), point(5000, [72.0, 70.0, 74.0], [0.0, 0.0, 0.0])]
    assert not still_rising(done)


def test_curves_still_rising_at_the_grids_cap_are_named_in_one_line_and_no_extension_passes_it(tmp_path, monkeypatch):
    """`steps_cap`: `cdrb select` sums up in one line the curves that still rise at the cap (they stop there by the
    grid's rule) and asks to extend only those below it, never past it; a grid whose [[extend]] entry goes past its
    own cap is refused in one line."""
    from cdrb_cli.errors import BadInput
    from cdrb_cli.orchestration.grid import load_grid
    from cdrb_cli.orchestration.select import Rise, rising_notes

    at_cap, below = _cand("k2", 0, 10000), _cand("k2", 0, 5000, method="diffuser")
    rising = {("maze", "cdrb"): Rise(at_cap, 12.0, 4.0, "success"), ("maze", "diffuser"): Rise(below, 0, 0, "shared")}
    line, warnings = rising_notes(rising, 10000)
    cap = "1 curves still rise at the grid's cap of 10000 steps (steps_cap), where they stop: "
    assert line == cap + "maze / cdrb +12.0 ± 4.0 success points"
    falling = {("maze", "mlp"): Rise(at_cap, -3.7, 0.9, "crossings")}  # rises only by fewer plans through an obstacle
    falls = "maze / mlp -3.7 ± 0.9 success points, fewer plans through an obstacle"
    assert rising_notes(falling, 10000)[0].endswith(falls)
    assert len(warnings) == 1 and warnings[0].startswith("maze / diffuser: the curve still rises at 5000 steps")
    assert warnings[0].endswith("steps = 10000)")  # doubling would pass the cap
    line, warnings = rising_notes(rising, None)  # no cap: each is asked to be extended, to twice its length
    assert line is None and [w.rsplit("steps = ", 1)[1] for w in warnings] == ["20000)", "10000)"]
    # the curve that rises is one variant's: the entry extends its runs alone; a shared budget names none
    assert 'methods = ["cdrb"], variants = ["k2"], steps = 20000)' in warnings[0] and "variants" not in warnings[1]
    grid = tmp_path / "tune.toml"
    grid.write_text(
        'out = "t"\nenvs = ["maze-tight"]\nmethods = ["mlp"]\nseeds = [0]\nsteps = 100\nsteps_cap = 200\n'
        'eval_stream = "tune"\n[[extend]]\nsteps = 400\n'
    )
    with pytest.raises(BadInput, match="beyond steps_cap = 200"):
        load_grid(grid)
    grid.write_text(grid.read_text().replace("steps = 400", "steps = 200"))
    assert load_grid(grid).steps_cap == 200
    grid.write_text(grid.read_text().replace("steps_cap = 200", "steps_cap = 50"))  # below the first stage
    with pytest.raises(BadInput, match="steps_cap = 50 is below the grid's steps = 100"):
        load_grid(grid)
    # without the grid's steps, each training's own length is held to the cap: the preset's, or its flags'
    base = 'out = "t"\nenvs = ["maze-tight"]\nmethods = ["mlp"]\nseeds = [0]\neval_stream = "tune"\n'
    for text, needle in (
        (base + "steps_cap = 10\n", r"on maze-tight runs 3000 steps \(the quick preset\), beyond steps_cap = 10"),
        (base + 'steps_cap = 100\n[[settings]]\nmethod = "mlp"\ntrain = ["--steps", "500"]\n',
         r"runs 500 steps \(its train flags\), beyond steps_cap = 100"),
    ):  # fmt: skip
        grid.write_text(text)
        with pytest.raises(BadInput, match=needle):
            load_grid(grid)
    grid.write_text(base + 'steps_cap = 3000\n[[variants]]\nname = "same"\ntrain = { lr = 0.01 }\n')
    assert load_grid(grid).steps_cap == 3000
    # with them, a variant's own length is replaced by the grid's, and a warning says so (the same length: nothing)
    warned: list[str] = []
    monkeypatch.setattr("cdrb_cli.ui.warn", warned.append)
    grid.write_text(base + 'steps = 100\n[[variants]]\nname = "long"\ntrain = { steps = 500 }\n')
    assert load_grid(grid).steps == 100 and len(warned) == 1
    assert "the grid's steps = 100 replaces the steps its train flags set (mlp's training on maze-tight" in warned[0]
    assert "in variant long: 500)" in warned[0]
    grid.write_text(base + 'steps = 100\n[[settings]]\nmethod = "mlp"\ntrain = { steps = 100 }\n')
    assert load_grid(grid).steps == 100 and len(warned) == 1


def test_an_eval_of_the_same_file_at_another_training_length_is_refused(tmp_path):
    """A run's final model keeps its name when an [[extend]] entry trains it further: an eval made before (archived,
    its model elsewhere) has the very command of the longer run's eval, and only the training length it records
    tells the two apart."""
    from cdrb_cli.errors import BadInput
    from cdrb_cli.orchestration.grid import expand, load_grid
    from cdrb_cli.orchestration.select_evals import checked_eval
    from tests import factories

    grid = tmp_path / "tune.toml"
    grid.write_text(
        'out = "t"\nenvs = ["maze-tight"]\nmethods = ["mlp"]\nseeds = [0]\nsteps = 100\nsnapshot_at = [50]\n'
        'eval_stream = "tune"\n'
    )
    spec = load_grid(grid)
    task = next(t for t in expand(spec) if t.id == "eval maze-tight/mlp-s0")
    manifest, arrays = factories.build("eval")

    def made(steps):
        summary = manifest.summary.model_copy(update={"model_steps": steps})
        path = tmp_path / f"eval-{steps}.h5"
        artifacts.save(
            path, "eval", manifest.model_copy(update={"argv": ["cdrb", *task.argv], "summary": summary}), arrays
        )
        return path

    with pytest.raises(BadInput, match=r"after 50 training steps; this grid's task \(eval maze-tight/mlp-s0\) meas"):
        checked_eval(spec, task, made(50))
    unchecked = []
    assert checked_eval(spec, task, made(100), unchecked).manifest.summary.model_steps == 100 and unchecked == []
    checked_eval(spec, task, made(None), unchecked)  # an eval from before evals recorded it, its model not here
    assert unchecked == [tmp_path / "eval-None.h5"]
    # the same command on another env's model of the same name (a file copied from another env's folder)
    from cdrb_cli.envs.registry import make_spec

    other = tmp_path / "eval-maze.h5"
    summary = manifest.summary.model_copy(update={"model_steps": 100})
    update = {"argv": ["cdrb", *task.argv], "summary": summary, "env": make_spec("maze")}
    artifacts.save(other, "eval", manifest.model_copy(update=update), arrays)
    with pytest.raises(BadInput, match=r"an eval on maze, where this grid's task \(eval maze-tight/mlp-s0\) measures"):
        checked_eval(spec, task, other)
    # an eval variant among obstacles of its own: its env is the task's env with the scene's name
    (tmp_path / "closed.txt").write_text((ROOT / "experiments" / "maps" / "maze-tight-closed-north.txt").read_text())
    grid.write_text(
        grid.read_text() + '[[variants]]\nname = "scened"\neval = ["--scene", "closed.txt", "--protocol", "detour"]\n'
    )
    spec = load_grid(grid)
    task = next(t for t in expand(spec) if t.id == "eval maze-tight/scened/mlp-s0")
    for ran, ok in (("maze-tight+closed", True), ("maze+closed", False)):
        path = tmp_path / f"eval-{ran}.h5"
        env = make_spec("maze-tight").model_copy(update={"id": ran})
        update = {"argv": ["cdrb", *task.argv], "summary": summary, "env": env}
        artifacts.save(path, "eval", manifest.model_copy(update=update), arrays)
        if ok:
            assert checked_eval(spec, task, path).manifest.env.id == ran
        else:
            with pytest.raises(BadInput, match=rf"an eval on {re.escape(ran)}, where this grid's task"):
                checked_eval(spec, task, path)


def _one_mlp_tuning_grid(tmp_path, variants: str = "", variant: str = ""):
    """A tuning grid of one MLP run (100 steps; ``variants``: more of the file, e.g. [[variants]] entries), expanded:
    its spec, tasks, trainings by output, the eval and training tasks of ``variant`` (the base by default), and an
    eval file recording that eval task's command."""
    from cdrb_cli.orchestration.grid import expand, load_grid
    from tests import factories

    grid = tmp_path / "tune.toml"
    grid.write_text(
        'out = "t"\nenvs = ["maze-tight"]\nmethods = ["mlp"]\nseeds = [0]\nsteps = 100\neval_stream = "tune"\n'
        + variants
    )
    spec = load_grid(grid)
    tasks = expand(spec)
    trains = {o: t for t in tasks if t.kind == "train" for o in t.outputs}
    at = f"{variant}/" if variant else ""
    task = next(t for t in tasks if t.id == f"eval maze-tight/{at}mlp-s0")
    train = next(t for t in tasks if t.id == f"train maze-tight/{at}mlp-s0")
    manifest, arrays = factories.build("eval")
    ev = tmp_path / "eval.h5"
    artifacts.save(ev, "eval", manifest.model_copy(update={"argv": ["cdrb", *task.argv]}), arrays)
    return spec, tasks, trains, task, train, ev


def test_an_eval_whose_model_here_was_trained_with_other_flags_is_refused(tmp_path):
    """select run without the --include or --set the grid ran with sees the same eval commands, but the models
    beside them record other training flags: those evals are not this grid's to score. A curve's stages differ in
    training length (and a resume) alone, which is no difference."""
    from cdrb_cli.errors import BadInput
    from cdrb_cli.orchestration.select_evals import checked_eval
    from tests import factories

    spec, tasks, trains, task, train, ev = _one_mlp_tuning_grid(tmp_path)
    m_manifest, m_arrays = factories.build("model")
    model = task.inputs[0]
    model.parent.mkdir(parents=True, exist_ok=True)
    steps = train.argv.index("--steps")
    for argv, ok in [
        (train.argv, True),
        ([*train.argv[:steps], "--steps", "50", *train.argv[steps + 2 :], "--resume"], True),
        ([*train.argv, "--set", "lr=0.5"], False),
    ]:
        artifacts.save(model, "model", m_manifest.model_copy(update={"argv": ["cdrb", *argv]}), m_arrays)
        spec._shas.clear()
        if ok:
            checked_eval(spec, task, ev, [], trains)
        else:
            with pytest.raises(BadInput, match=r"not trained as this grid's task .*setting lr: 0.5 there, \(not set\)"):
                checked_eval(spec, task, ev, [], trains)


def test_an_eval_whose_model_was_trained_on_other_data_than_the_grid_makes_is_refused(tmp_path):
    """The data chain: the demos the grid's collect task writes must be what its command makes (`--set demos=41`
    at select time, where the grid collected 40), and the model must have been trained on what that file holds now
    (the data made again since)."""
    from cdrb_cli.errors import BadInput
    from cdrb_cli.orchestration.select_evals import checked_eval
    from tests import factories

    spec, tasks, trains, task, train, ev = _one_mlp_tuning_grid(tmp_path)
    makers = {o: t for t in tasks if t.kind in ("collect", "cluster") for o in t.outputs}
    collect = next(t for t in tasks if t.kind == "collect")
    demos_path, model = collect.outputs[0], task.inputs[0]
    model.parent.mkdir(parents=True, exist_ok=True)

    def data(argv, seed=0):
        d_manifest, d_arrays = factories.build("demos", seed=seed)
        artifacts.save(demos_path, "demos", d_manifest.model_copy(update={"argv": ["cdrb", *argv]}), d_arrays)
        return artifacts.load(demos_path, "demos")

    m_manifest, m_arrays = factories.build("model")
    trained_on = data(collect.argv)
    parents = [artifacts.parent_ref(trained_on)]
    artifacts.save(model, "model", m_manifest.model_copy(update={"argv": ["cdrb", *train.argv], "parents": parents}),
                   m_arrays)  # fmt: skip
    spec._shas.clear()
    checked_eval(spec, task, ev, [], trains, makers)
    n = collect.argv.index("-n")
    data([*collect.argv[: n + 1], "41", *collect.argv[n + 2 :]])
    spec._shas.clear()
    with pytest.raises(BadInput, match=r"trained on .*demos.h5, which was not made as this grid's task"):
        checked_eval(spec, task, ev, [], trains, makers)
    data(collect.argv, seed=1)  # the same command, other data in the file than the model was trained on
    spec._shas.clear()
    with pytest.raises(BadInput, match="its model was trained on other demos than"):
        checked_eval(spec, task, ev, [], trains, makers)


def test_a_model_and_data_read_from_elsewhere_are_checked_where_the_eval_records_them(tmp_path):
    """A grid that reuses another grid's runs, or runs whose files were moved, has no model or data at its own paths:
    the model the eval read and the data that model read, at the paths they record and with the bytes they record,
    are checked as the grid's own would be (another lr, or demos made with another -n, are refused)."""
    from cdrb_cli.errors import BadInput
    from cdrb_cli.orchestration.select_evals import checked_eval
    from tests import factories

    spec, tasks, trains, task, train, _ = _one_mlp_tuning_grid(tmp_path)
    makers = {o: t for t in tasks if t.kind in ("collect", "cluster") for o in t.outputs}
    collect = next(t for t in tasks if t.kind == "collect")
    elsewhere = tmp_path / "other"
    elsewhere.mkdir()
    assert not task.inputs[0].exists() and not collect.outputs[0].exists()
    n = collect.argv.index("-n")
    e_manifest, e_arrays = factories.build("eval")

    def eval_of(train_argv, collect_argv):
        d_manifest, d_arrays = factories.build("demos")
        demos = elsewhere / "demos.h5"
        artifacts.save(demos, "demos", d_manifest.model_copy(update={"argv": ["cdrb", *collect_argv]}), d_arrays)
        m_manifest, m_arrays = factories.build("model")
        model = elsewhere / "mlp-s0.h5"
        update = {"argv": ["cdrb", *train_argv], "parents": [artifacts.parent_ref(artifacts.load(demos, "demos"))]}
        artifacts.save(model, "model", m_manifest.model_copy(update=update), m_arrays)
        ev = elsewhere / "eval.h5"
        update = {"argv": ["cdrb", *task.argv], "parents": [artifacts.parent_ref(artifacts.load(model, "model"))]}
        artifacts.save(ev, "eval", e_manifest.model_copy(update=update), e_arrays)
        spec._shas.clear()
        return ev

    checked_eval(spec, task, eval_of(train.argv, collect.argv), [], trains, makers)
    with pytest.raises(BadInput, match=r"not trained as this grid's task .*setting lr: 0.5 there, \(not set\)"):
        checked_eval(spec, task, eval_of([*train.argv, "--set", "lr=0.5"], collect.argv), [], trains, makers)
    other_n = [*collect.argv[: n + 1], "41", *collect.argv[n + 2 :]]
    with pytest.raises(BadInput, match=r"trained on .*other/demos.h5, which was not made as this grid's task"):
        checked_eval(spec, task, eval_of(train.argv, other_n), [], trains, makers)
    # a recorded file whose bytes changed since is not the one the eval read: nothing to check it against
    ev = eval_of([*train.argv, "--set", "lr=0.5"], collect.argv)
    with open(elsewhere / "mlp-s0.h5", "ab") as f:
        f.write(b"\0")
    spec._shas.clear()
    checked_eval(spec, task, ev, [], trains, makers)


def test_an_eval_whose_settings_file_changed_since_the_grid_ran_it_is_refused(tmp_path):
    """Commands name a --config file, and compare it by name: an edit of it since the grid ran the training (or the
    eval) changed what the task asks for, and the grid's memo of the task, which hashed the file, tells."""
    from cdrb_cli.errors import BadInput
    from cdrb_cli.orchestration.grid.memo import write_memo
    from cdrb_cli.orchestration.select_evals import checked_eval

    (tmp_path / "tc.toml").write_text("lr = 0.01\n")
    (tmp_path / "ev.toml").write_text("[controller]\nmax_lag = 0.3\n")
    cfg = '[[variants]]\nname = "cfg"\ntrain = ["--config", "tc.toml"]\neval = ["--config", "ev.toml"]\n'
    spec, _, trains, task, train, ev = _one_mlp_tuning_grid(tmp_path, cfg, "cfg")
    for t in (train, task):
        write_memo(spec, t, spec._shas)
    checked_eval(spec, task, ev, [], trains)
    for name, edit, ran in (("tc.toml", "lr = 0.5\n", train), ("ev.toml", "[controller]\nmax_lag = 0.9\n", task)):
        before = (tmp_path / name).read_text()
        (tmp_path / name).write_text(edit)
        spec._shas.clear()
        with pytest.raises(BadInput, match=rf"{name} changed since the grid ran {re.escape(ran.id)} with it"):
            checked_eval(spec, task, ev, [], trains)
        (tmp_path / name).write_text(before)
    spec._shas.clear()
    checked_eval(spec, task, ev, [], trains)


def test_the_summary_shows_each_chosen_setting_in_a_column_per_method():
    """One line per environment: the chosen candidate's success ± std at its training length, its plans through an
    obstacle (none for a policy), and * where its curve still rises."""
    from cdrb_cli.orchestration.select import still_rising, summary_text

    def point(variant, order, steps, successes, method, crossing=0.0):
        mean = sum(successes) / len(successes)
        c = _cand(variant, order, steps, success=mean, crossing=crossing, method=method)
        c.models = [{"seed": i, "success": v} for i, v in enumerate(successes)]
        c.success_std = (sum((v - mean) ** 2 for v in successes) / (len(successes) - 1)) ** 0.5
        return c

    cands = [
        point("k2", 0, 1000, [20.0, 30.0, 16.0], "cdrb", crossing=40.0),
        point("k2", 0, 2500, [90.0, 95.0, 97.0], "cdrb", crossing=3.2),  # gained 70, 65, 81: still rising
        point("base", 0, 1000, [50.0, 50.0, 52.0], "mlp", crossing=80.0),
        point("base", 0, 2500, [40.0, 44.0, 42.0], "mlp", crossing=85.0),  # the shorter run wins: no rise
        point("policy", 0, 10000, [30.0, 31.0, 35.0], "diffusion-bc", crossing=None),
    ]
    text = summary_text(cands, choose(cands), still_rising(cands))
    head, rule, row = text.splitlines()[:3]
    assert head == "| Task | mlp | cdrb | diffusion-bc |" and rule == "|---|---:|---:|---:|"
    assert row == "| Maze | 50.7 ± 1.2 @1k (80%) | 94.0 ± 3.6 @2.5k* (3%) | 32.0 ± 2.6 @10k |"
    assert "*: the curve still rises" in text


@pytest.mark.slow
def test_maze_tuning_select_and_table1_files_run_end_to_end_at_a_tiny_budget(tmp_path):
    """The documented chain on the shipped files (copied, so the tuned files written are the copies'), narrowed to
    Maze Tight x {MLP, CDRB} with tiny nets: each `cdrb select` writes the settings the next file includes, and the
    Table-1 models are trained with exactly the settings the last selection chose."""
    exp = tmp_path / "experiments"
    shutil.copytree(ROOT / "experiments", exp)
    small = ["--set", 'envs=["maze-tight"]', "--set", 'methods=["mlp", "cdrb"]', "--set", "demos=40"]
    small += ["--set", "k=50", "--set", "eval_episodes=2", "--include", ROOT / "tests" / "data" / "tiny-settings.toml"]
    pool = ["--backend", "pool", "-j", "2"]  # the local pool: no Ray start-up for each grid
    tune = [*small, "--set", "eval_seeds=[0]", *pool]

    def grid_select(name: str, tuned: str, *extra) -> list[dict]:
        args = [*tune, "--set", f"out={tmp_path / 'runs' / name}", *extra]
        _cdrb("grid", exp / "tune" / f"{name}.toml", *args, cwd=tmp_path)
        table = tmp_path / f"{name}.csv"
        sel = [a for a in args if a not in ("--backend", "pool", "-j", "2")]
        out = _cdrb("select", exp / "tune" / f"{name}.toml", *sel, "--out", exp / "tuned" / tuned, "--force",
                    "--table", table, cwd=tmp_path).stdout  # fmt: skip
        assert out.strip() == str(exp / "tuned" / tuned)
        with open(table, newline="") as fh:
            return list(csv.DictReader(fh))

    rows = grid_select("mazes-sweep", "mazes-sweep.toml", "--set", "steps=20")
    tuned = tomllib.loads((exp / "tuned" / "mazes-sweep.toml").read_text())
    assert tuned["meta"]["rule"] == RULE
    assert {(s["env"], s["method"]) for s in tuned["settings"]} == {("maze-tight", "mlp"), ("maze-tight", "cdrb")}
    for s in tuned["settings"]:
        mine = [r for r in rows if r["method"] == s["method"]]
        assert len(mine) == 6  # six candidates per method: the equal budget
        best = max(float(r["success"]) for r in mine)
        chosen = next(r for r in mine if r["chosen"] == "True")
        assert float(chosen["success"]) == best and s["chosen"].startswith(chosen["candidate"])

    # select reads only the evals the grid's tasks made: other settings, another method's eval put in place, or an
    # eval of a model trained again since are refused (one line, exit 2, nothing written)
    sweep_args = [a for a in tune if a not in ("--backend", "pool", "-j", "2")] + ["--set", "steps=20"]
    copy = tmp_path / "runs" / "sweep-copy"
    shutil.copytree(tmp_path / "runs" / "mazes-sweep", copy)
    again = ["select", exp / "tune" / "mazes-sweep.toml", *sweep_args, "--set", f"out={copy}"]
    # --docs writes the choices' summary into the marked block; a file without the block is refused before the
    # settings file is written
    doc = tmp_path / "doc.md"
    doc.write_text("# tuning\n\n<!-- tuning:begin -->\n<!-- tuning:end -->\n")
    _cdrb(*again, "--out", tmp_path / "d.toml", "--docs", doc, "--block", "tuning", cwd=tmp_path)
    written = doc.read_text()
    assert "| Task | mlp | cdrb |" in written and "\n| Maze Tight | " in written and written.startswith("# tuning")
    r = _cdrb(*again, "--out", tmp_path / "e.toml", "--docs", doc, "--block", "other", cwd=tmp_path, check=False)
    assert r.returncode == 2 and "no <!-- other:begin -->" in r.stderr and not (tmp_path / "e.toml").exists()
    r = _cdrb(*again, "--set", "eval_episodes=3", "--out", tmp_path / "x.toml", cwd=tmp_path, check=False)
    assert r.returncode == 2 and "not this grid's eval" in r.stderr
    assert "setting episodes: 2 there, 3 in the grid" in r.stderr
    quick = copy / "maze-tight" / "quick"
    shutil.copy(quick / "eval-mlp-s0.h5", quick / "eval-cdrb-s0.h5")
    r = _cdrb(*again, "--out", tmp_path / "x.toml", cwd=tmp_path, check=False)
    assert r.returncode == 2 and "it reads mlp-s0.h5, the grid's task cdrb-s0.h5" in r.stderr
    shutil.copy(tmp_path / "runs" / "mazes-sweep" / "maze-tight" / "quick" / "eval-cdrb-s0.h5", quick)
    model = copy / "maze-tight" / "cdrb-s0.h5"  # the base model the eval-only variant "quick" evaluates
    model.write_bytes(model.read_bytes())  # written again, unchanged: still the model it evaluated
    assert _cdrb(*again, "--out", tmp_path / "x.toml", cwd=tmp_path).returncode == 0
    shutil.copy(copy / "maze-tight" / "T64" / "cdrb-s0.h5", model)  # another model under its name
    r = _cdrb(*again, "--out", tmp_path / "y.toml", cwd=tmp_path, check=False)
    assert r.returncode == 2 and "evaluates another cdrb-s0.h5" in r.stderr and not (tmp_path / "y.toml").exists()
    shutil.copy(tmp_path / "runs" / "mazes-sweep" / "maze-tight" / "cdrb-s0.h5", model)
    # an eval copied from another variant's folder reads as the same command (files compared by name), even with
    # no model here to compare: it is refused by the place it was written for
    (copy / "maze-tight" / "dim32" / "cdrb-s0.h5").unlink()
    shutil.copy(copy / "maze-tight" / "T64" / "eval-cdrb-s0.h5", copy / "maze-tight" / "dim32" / "eval-cdrb-s0.h5")
    r = _cdrb(*again, "--out", tmp_path / "y.toml", cwd=tmp_path, check=False)
    assert r.returncode == 2 and "T64/eval-cdrb-s0.h5, for another place in a grid than maze-tight/dim32/" in r.stderr
    shutil.copy(
        tmp_path / "runs" / "mazes-sweep" / "maze-tight" / "dim32" / "eval-cdrb-s0.h5", copy / "maze-tight" / "dim32"
    )

    # the later grids take the sweep's demos and buffer (`reuse`) instead of collecting and clustering again
    reuse = ["--set", f'reuse=["{tmp_path / "runs" / "mazes-sweep"}"]']
    rows = grid_select("mazes-clock", "mazes-clock.toml", "--set", "steps=20", *reuse)
    reused = json.loads((tmp_path / "runs" / "mazes-clock" / "grid.json").read_text())["reused"]
    assert (
        "collect maze-tight" in reused and not (tmp_path / "runs" / "mazes-clock" / "maze-tight" / "demos.h5").exists()
    )
    assert {r["candidate"] for r in rows} == {
        "time-indexed", "gated-0.6", "gated-0.6-wait10", "gated-0.3-wait10", "official-executor"
    }  # fmt: skip
    rows = grid_select("mazes-curves", "mazes.toml", "--set", "steps=100", "--set", "snapshot_at=[50]", *reuse)
    assert sorted({int(r["steps"]) for r in rows}) == [50, 100]
    for path in (tmp_path / "runs" / "mazes-curves").rglob("eval-*.h5"):  # each eval names its model's length
        assert artifacts.load(path, "eval").manifest.summary.model_steps == (50 if ".step50." in path.name else 100)
    # the learning curves: one row per candidate x training length x training seed, whose mean is the pooled score
    curves_args = [*tune, "--set", f"out={tmp_path / 'runs' / 'mazes-curves'}", "--set", "steps=100", *reuse]
    curves_args = [a for a in curves_args if a not in ("--backend", "pool", "-j", "2")] + ["--set", "snapshot_at=[50]"]
    _cdrb("select", exp / "tune" / "mazes-curves.toml", *curves_args, "--out", tmp_path / "again.toml",
          "--curves", tmp_path / "curves.csv", cwd=tmp_path)  # fmt: skip
    with open(tmp_path / "curves.csv", newline="") as fh:
        points = list(csv.DictReader(fh))
    seeds = tomllib.loads((exp / "tune" / "mazes-curves.toml").read_text())["seeds"]
    for r in rows:
        key = (r["method"], r["candidate"], r["steps"])
        mine = [p for p in points if (p["method"], p["candidate"], p["steps"]) == key]
        assert sorted(int(p["seed"]) for p in mine) == sorted(seeds)
        assert float(r["success"]) == pytest.approx(sum(float(p["success"]) for p in mine) / len(mine), abs=0.01)
    final = tomllib.loads((exp / "tuned" / "mazes.toml").read_text())["settings"]

    out = tmp_path / "runs" / "table1"
    _cdrb(
        "grid",
        exp / "table1" / "mazes.toml",
        *small,
        "--set",
        f"out={out}",
        "--set",
        "seeds=[0, 1]",
        *reuse,
        *pool,
        cwd=tmp_path,
    )
    for s in final:
        steps = s["train"]["steps"]  # a table of settings
        for seed in (0, 1):
            model = artifacts.load(out / "maze-tight" / f"{s['method']}-s{seed}.h5", "model")
            assert model.manifest.config.steps == steps  # trained as selected on the tuning stream
            ev = artifacts.load(out / "maze-tight" / "ours" / f"eval-{s['method']}-s{seed}.h5", "eval")
            assert ev.manifest.config.stream == "test" and ev.manifest.config.seeds == [seed]
            official = artifacts.load(out / "maze-tight" / "official-code" / f"eval-{s['method']}-s{seed}.h5", "eval")
            assert official.manifest.config.protocol == "official-code"
    # per-seed rows list evals of both protocols side by side (the grouped table refuses to mix them)
    both = sorted((out / "maze-tight").glob("*/eval-*.h5"))
    rows = list(
        csv.DictReader(_cdrb("report", *both, "--per-seed", "--format", "csv", cwd=tmp_path).stdout.splitlines())
    )
    assert len(rows) == 8 and {r["protocol"] for r in rows} == {"centre-start/corner-goal", "official-code"}
    docs = tmp_path / "doc.md"
    docs.write_text("intro\n<!-- t1:begin -->\nold\n<!-- t1:end -->\nafter\n")
    evals = sorted((out / "maze-tight" / "ours").glob("eval-*.h5"))
    _cdrb("report", *evals, "--paper", "--docs", docs, "--block", "t1", cwd=tmp_path)
    text = docs.read_text()
    assert text.startswith("intro\n<!-- t1:begin -->\n| Success rate (%) |") and text.endswith(
        "<!-- t1:end -->\nafter\n"
    )
    assert "| Maze Tight (paper) | 38.29 ± 1.80 | 98.00 ± 0.00 |" in text and "old" not in text


def test_settings_files_hold_any_name_as_valid_toml():
    from cdrb_cli.errors import BadInput
    from cdrb_cli.settings import toml_string

    for text in ["plain", "tune 😀.toml", 'q"b\\c', "del\x7f nul\x00 nl\n tab\t", "é 中 \u2028", ""]:
        assert tomllib.loads(f"v = {toml_string(text)}")["v"] == text
    with pytest.raises(BadInput, match="not valid Unicode"):
        toml_string("bad \udcff byte")


def test_select_refuses_two_outputs_on_one_file_before_reading_anything(tmp_path):
    grid = tmp_path / "missing.toml"  # never read: the outputs are checked first
    for extra in (["--table", tmp_path / "s.toml"], ["--table", tmp_path / "t.md", "--curves", tmp_path / "t.md"]):
        r = _cdrb("select", grid, "--out", tmp_path / "s.toml", *extra, "--force", cwd=tmp_path, check=False)
        assert r.returncode == 2 and "the same file as" in r.stderr, r.stderr
    assert list(tmp_path.iterdir()) == []


def test_paper_figures_come_from_the_data_file_and_a_bad_file_is_one_line(tmp_path):
    from cdrb_cli.errors import BadInput
    from cdrb_cli.stages.docs_blocks import replace_block
    from cdrb_cli.stages.report import paper_figures

    figures = paper_figures()
    assert len(figures) == 8 and figures["maze-tight"]["cdrb"] == (98.0, 0.0)
    assert set(figures["fetch-push"]) == {"mlp", "diffuser", "diffusion-bc", "diffusion-ql", "cdrb"}
    own = tmp_path / "own.toml"
    own.write_text('["maze"]\ncdrb = [1, 2.5]\n')
    assert paper_figures(own) == {"maze": {"cdrb": (1.0, 2.5)}}
    bad = ['["maze"]\ncdrb = [1]\n', "maze = 3\n", '["maze"]\ncdrb = ["a", 1]\n', "= =\n", ""]
    bad += ['["maze"]\ncdrb = [nan, 1]\n', '["maze"]\ncdrb = [-5, 1]\n', '["maze"]\ncdrb = [50, 1e308]\n']
    bad += ['["maze"]\ncdrb = [true, false]\n', '["mazee"]\ncdrb = [1, 2]\n', '["maze"]\ncdrbb = [1, 2]\n']
    bad += ['others = "QRL"\n["maze"]\ncdrb = [1, 2]\n', 'others = ["QRL"]\n["maze"]\nHIQL = [1, 2]\n']
    for text in bad:
        own.write_text(text)
        with pytest.raises(BadInput, match="--paper-figures"):
            paper_figures(own)
    # published methods the project does not implement, when the file lists them (OGBench's file ships so)
    own.write_text('others = ["QRL"]\n["maze"]\nQRL = [86, 9]\ncdrb = [1, 2]\n')
    assert paper_figures(own) == {"maze": {"QRL": (86.0, 9.0), "cdrb": (1.0, 2.0)}}
    published = paper_figures(Path(__file__).resolve().parent.parent / "docs/results/ogbench_published.toml")
    assert len(published) == 6 and published["pointmaze-giant-navigate-v0"]["QRL"] == (68.0, 7.0)
    doc = "a\n<!-- t:begin -->\nold\n<!-- t:end -->\nb\n<!-- u:begin -->\nkeep\n<!-- u:end -->\n"
    assert replace_block(doc, "t", "new\n", "doc.md").startswith("a\n<!-- t:begin -->\nnew\n<!-- t:end -->\nb\n")
    assert "keep" in replace_block(doc, "t", "new", "doc.md")  # only the named block
    with pytest.raises(BadInput, match="no <!-- v:begin -->"):
        replace_block(doc, "v", "new", "doc.md")
    with pytest.raises(BadInput, match="ambiguous"):
        replace_block(doc + doc, "t", "new", "doc.md")
    with pytest.raises(BadInput, match="holds a t marker"):
        replace_block(doc, "t", "x\n<!-- t:end -->\n", "doc.md")


def test_names_from_an_artifact_cannot_break_a_markdown_table_or_its_block():
    from cdrb_cli.stages.report import markdown_safe

    row = markdown_safe({"method": "a|b\n<!-- t:end -->\n<script>", "success_mean": 1.0})
    assert row == {"method": "a\\|b &lt;!-- t:end --> &lt;script>", "success_mean": 1.0}


def test_a_chosen_candidate_keeps_its_buffer_flags_in_the_settings_it_writes(tmp_path):
    """A variant that trains on its own buffer (cluster flags, e.g. state-action features): the settings file
    carries those flags, so the test grid that includes it clusters the same buffer for that method."""
    from cdrb_cli.orchestration.grid import expand, load_grid, parse_command
    from cdrb_cli.orchestration.select import Candidate, settings_text

    tune = tmp_path / "tune.toml"
    tune.write_text(
        'out = "t"\nenvs = ["maze-tight"]\nmethods = ["cdrb", "mlp"]\nseeds = [0]\nsteps = 20\neval_stream = "tune"\n'
        '[[variants]]\nname = "quick"\n'
        '[[variants]]\nname = "sa"\ncluster = ["--features", "state-action"]\n'
        'train = ["--set", "features=state-action"]\n'
        '[[variants]]\nname = "timed"\neval = ["--max-lag", "0"]\n'
    )
    spec = load_grid(tune)
    best = {
        ("maze-tight", "cdrb"): Candidate("maze-tight", "cdrb", "sa", 1, 20),
        ("maze-tight", "mlp"): Candidate("maze-tight", "mlp", "timed", 2, 20),
    }
    (tmp_path / "tuned.toml").write_text(settings_text(spec, tune, best))
    test = tmp_path / "test.toml"
    test.write_text(
        'include = ["tuned.toml"]\nout = "x"\nenvs = ["maze-tight"]\nmethods = ["cdrb", "mlp"]\nseeds = [0]\n'
    )
    tasks = {t.id: t for t in expand(load_grid(test))}
    (cluster,) = [t for t in tasks.values() if t.kind == "cluster"]
    assert cluster.argv[cluster.argv.index("--features") + 1] == "state-action"
    train = tasks["train maze-tight/cdrb-s0"].argv
    settings = dict(parse_command(train)[2])  # the chosen training, written as a table of settings
    assert str(cluster.outputs[0]) in train and settings["features"] == '"state-action"' and settings["steps"] == "20"
    mlp = tasks["train maze-tight/mlp-s0"].argv  # an eval-only pick: the base model's flags, and its eval knob
    assert "features" not in dict(parse_command(mlp)[2]) and "--buffer" not in mlp
    assert dict(parse_command(tasks["eval maze-tight/mlp-s0"].argv)[2])["controller.max_lag"] == "null"


def test_selected_file_flags_are_relative_to_the_settings_file(tmp_path):
    from cdrb_cli.orchestration.select import relative_files

    folder = tmp_path / "experiments" / "tuned"
    maps = tmp_path / "experiments" / "maps" / "closed.txt"
    flags = ["--max-lag", "0.6", "--maze-map", str(tmp_path / "experiments" / "tune" / ".." / "maps" / "closed.txt")]
    flags += [f"--route-buffer={tmp_path / 'runs' / 'b.h5'}", "--protocol", "detour"]
    out = relative_files(flags, "eval", folder)
    assert out == ["--max-lag", "0.6", "--maze-map", "../maps/closed.txt", "--route-buffer=../../runs/b.h5"] + [
        "--protocol",
        "detour",
    ]
    assert (folder / out[3]).resolve() == maps.resolve()


def test_select_never_writes_over_a_file_the_grid_reads_or_writes(tmp_path, monkeypatch):
    """--force overwrites an earlier output, never an input: the settings file the grid includes, or any artifact
    under its `out` (here an eval the selection would read)."""
    from cdrb_cli.errors import BadInput
    from cdrb_cli.orchestration.grid import expand, load_grid
    from cdrb_cli.orchestration.select import select

    monkeypatch.chdir(tmp_path)
    (tmp_path / "data.toml").write_text('[[settings]]\ntrain = ["--steps", "20"]\n')
    grid = tmp_path / "tune.toml"
    grid.write_text(
        'include = ["data.toml"]\nout = "t"\nenvs = ["maze-tight"]\nmethods = ["mlp"]\nseeds = [0]\n'
        'eval_stream = "tune"\n'
    )
    (ev,) = [t.outputs[0] for t in expand(load_grid(grid)) if t.kind == "eval"]
    ev.parent.mkdir(parents=True)
    ev.write_bytes(b"an eval")
    for victim in (tmp_path / "data.toml", ev):
        before = victim.read_bytes()
        with pytest.raises(BadInput, match="is an input of this command"):
            select(grid, victim, force=True)
        with pytest.raises(BadInput, match="is an input of this command"):
            select(grid, tmp_path / "s.toml", force=True, curves=victim)
        assert victim.read_bytes() == before
    assert not (tmp_path / "s.toml").exists()


def _level_field_problems(tuned: dict) -> list[str]:
    """What breaks one training budget per task or executes a planner with a controller that reads the map, in a
    settings file (parsed TOML) `cdrb select` wrote."""
    from cdrb_cli.envs.registry import CONTROLLERS
    from cdrb_cli.methods.registry import METHODS

    def controller(flags) -> str | None:
        if isinstance(flags, dict):
            return (flags.get("controller") or {}).get("name")
        flags = list(flags)
        return flags[flags.index("--controller") + 1] if "--controller" in flags else None

    problems, lengths = [], {}
    for s in tuned["settings"]:
        if METHODS.get(s["method"]).kind != "planner":
            continue
        name = controller(s.get("eval", []))
        if name is not None and CONTROLLERS.get(name).knows_map:
            problems.append(f"{s['env']} / {s['method']}: executed by {name}, which reads the map")
        steps = s["train"].get("steps") if isinstance(s.get("train"), dict) else None
        if steps is not None:
            lengths.setdefault(s["env"], {})[s["method"]] = steps
    problems += [
        f"{env}: planners at {sorted(set(m.values()))} steps" for env, m in lengths.items() if len(set(m.values())) > 1
    ]
    return problems


def test_tuned_files_under_a_shared_budget_give_planners_one_length_and_no_map_aware_controller():
    """A settings file `cdrb select` wrote under a grid's shared budget says so (`meta.budget`); every such shipped
    file trains the planners of a task to one length and executes none with a controller that reads the map. The
    check itself finds both faults in a file that has them."""
    from cdrb_cli.orchestration.grid import load_grid
    from cdrb_cli.orchestration.select import SHARED_BUDGET, settings_text

    grid = ROOT / "experiments" / "tune" / "fetch-curves.toml"
    assert f"budget = {SHARED_BUDGET!r}".replace("'", '"') in settings_text(load_grid(grid), grid, {})
    for path in sorted((ROOT / "experiments" / "tuned").glob("*.toml")):
        tuned = tomllib.loads(path.read_text())
        if tuned.get("meta", {}).get("budget") == SHARED_BUDGET:
            assert _level_field_problems(tuned) == [], path
    bad = {
        "settings": [
            {"env": "e", "method": "cdrb", "train": {"steps": 5000}, "eval": {"controller": {"name": "fetch-track"}}},
            {"env": "e", "method": "diffuser", "train": {"steps": 10000}, "eval": ["--controller", "fetch-push-path"]},
            {"env": "e", "method": "diffusion-bc", "train": {"steps": 2500}, "eval": []},
        ]
    }
    assert _level_field_problems(bad) == [
        "e / diffuser: executed by fetch-push-path, which reads the map",
        "e: planners at [5000, 10000] steps",
    ]


def test_a_candidates_evals_of_models_trained_otherwise_are_refused_without_the_models(tmp_path):
    """The seeds of one candidate are pooled: an eval whose recorded training digest differs (a model retrained with
    other settings, then moved away) is refused; evals that record none (older files) are not judged."""
    from cdrb_cli import artifacts
    from cdrb_cli.errors import BadInput
    from cdrb_cli.orchestration.select_evals import trained_alike
    from tests.factories import build

    def ev(name: str, digest: str | None):
        manifest, arrays = build("eval")
        summary = manifest.summary.model_copy(update={"model_training": digest})
        manifest = manifest.model_copy(update={"summary": summary})
        artifacts.save(tmp_path / name, "eval", manifest, arrays)
        return artifacts.load(tmp_path / name, "eval")

    same = [ev("a.h5", "1" * 64), ev("b.h5", "1" * 64), ev("c.h5", None)]
    trained_alike(same)
    with pytest.raises(BadInput, match="d.h5: evaluates a model trained with other settings than"):
        trained_alike([*same, ev("d.h5", "2" * 64)])
