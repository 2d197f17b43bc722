"""Plan and eval configs as the one declaration of their knobs: every field reachable by --set, --config and the
Python API, the same config from every spelling, the family's avoidance by default in a scene, and --help short."""

from __future__ import annotations

import json
import re
from pathlib import Path

import pytest

from cdrb_cli.configs import AvoidConfig, EvalConfig, PlanConfig
from cdrb_cli.errors import BadInput
from cdrb_cli.settings import parse_set
from cdrb_cli.stages.configure import eval_config, plan_config

NORTH = Path(__file__).resolve().parents[1] / "experiments" / "maps" / "maze-tight-closed-north.txt"


def _leaf_keys(model, prefix=""):
    """Every settable leaf of a config record (nested records by their fields)."""
    from pydantic import BaseModel

    keys = []
    for name, f in model.model_fields.items():
        if isinstance(f.annotation, type) and issubclass(f.annotation, BaseModel):
            keys += _leaf_keys(f.annotation, f"{prefix}{name}.")
        else:
            keys.append(prefix + name)
    return keys


@pytest.mark.parametrize("stage, record", [("plan", PlanConfig), ("eval", EvalConfig)])
def test_config_lists_every_field(cdrb, stage, record):
    r = cdrb("config", stage)
    assert r.returncode == 0, r.stderr
    listed = {line.split()[0] for line in r.stdout.splitlines()[1:] if line.strip() and not line.startswith(" " * 8)}
    for key in _leaf_keys(record):
        if key != "controller":
            assert key in listed, key
    if stage == "eval":
        assert {"controller.name", "controller.look_ahead", "replan.repair_k", "avoid.best_of"} <= listed


@pytest.mark.parametrize("command", ["plan", "eval"])
def test_help_is_short(cdrb, command):
    r = cdrb(command, "--help")
    options = set(re.findall(r"^│ (?:\*\s+)?(--[a-z][a-z-]*)", r.stdout, flags=re.M)) - {"--help"}
    assert 6 <= len(options) <= 14, sorted(options)
    assert "--set" in options and "--config" in options and "--best-of" not in options


def test_every_spelling_gives_one_config(tiny_models, tmp_path):
    """A --set pair, a --config file, a keyword of the API and the same value by default are one config."""
    model = tiny_models["cdrb"]
    by_set = eval_config(model, parse_set(["avoid.best_of=3", "controller.look_ahead=2", "replan=every:40"]))
    toml = tmp_path / "run.toml"
    toml.write_text('replan = "every:40"\n[avoid]\nbest_of = 3\n[controller]\nlook_ahead = 2\n')
    from cdrb_cli.settings import read_config_file

    by_file = eval_config(model, read_config_file(toml))
    by_keyword = eval_config(model, replan="every:40", **{"avoid.best_of": 3, "controller.look_ahead": 2})
    assert by_set == by_file == by_keyword
    assert by_set.replan.mode == "every" and by_set.replan.every == 40 and by_set.avoid.best_of == 3
    assert eval_config(model).episodes == 100 and eval_config(model).seeds == [0, 1, 2, 3, 4]
    # a file's value that a later setting overrides is still checked; a valid one is overridden as asked
    toml.write_text('avoid = "plain"\n[controller]\nlook_ahead = "two"\n')
    with pytest.raises(BadInput, match=r"run.toml: controller.look_ahead: Input should be a valid integer"):
        eval_config(model, [*read_config_file(toml), *parse_set(["controller.look_ahead=2"])])
    toml.write_text('avoid = "plain"\n[controller]\nlook_ahead = 1\n')
    both = [*read_config_file(toml), *parse_set(["controller.look_ahead=2", "avoid=plain"])]
    assert eval_config(model, both).controller.look_ahead == 2
    toml.write_text('avoid = "plain"\n')  # a whole-record choice, read before validation, is overridden too
    assert plan_config(model, [*read_config_file(toml), *parse_set(["avoid=tuned"])]).avoid != AvoidConfig()


def test_a_scene_is_avoided_by_default(tiny_models):
    from cdrb_cli.envs.pointmaze import PointMazeFamily

    cdrb = tiny_models["cdrb"]
    tuned = AvoidConfig(**{**PointMazeFamily.scene_avoid["cdrb"], "route_k": 7})  # the tiny model's T - 1
    assert tuned != AvoidConfig()
    assert plan_config(cdrb).avoid == AvoidConfig()  # no scene: as the paper plans
    assert plan_config(cdrb, scene_file=NORTH).avoid == tuned
    assert plan_config(cdrb, parse_set(["avoid=plain"]), scene_file=NORTH).avoid == AvoidConfig()
    one = plan_config(cdrb, parse_set(["avoid.best_of=8"]), scene_file=NORTH).avoid
    assert one == tuned.model_copy(update={"best_of": 8})  # a field on top of the default
    assert plan_config(cdrb, parse_set(["avoid=tuned"])).avoid == tuned
    # a method with nothing chosen for it plans as it is; an eval in the scene gets the same default
    assert plan_config(tiny_models["mlp"], scene_file=NORTH).avoid == AvoidConfig()
    assert eval_config(cdrb, scene_file=NORTH, protocol="detour").avoid == tuned
    with pytest.raises(BadInput, match="avoid is plain or tuned"):
        plan_config(cdrb, parse_set(["avoid=maybe"]))


def test_replanning_uses_the_settings_chosen_for_it_by_default(tiny_models):
    from cdrb_cli.envs.pointmaze import PointMazeFamily

    cdrb, diffuser = tiny_models["cdrb"], tiny_models["diffuser"]
    chosen = PointMazeFamily.replan_tuned
    once = eval_config(cdrb)
    assert once.controller.look_ahead == 0 and once.avoid == AvoidConfig()  # one plan per episode: the paper's
    every = eval_config(cdrb, replan="every:50")
    assert every.controller.look_ahead == chosen["cdrb"]["controller.look_ahead"] == 2
    assert every.avoid.best_of == chosen["cdrb"]["avoid.best_of"] == 8
    assert eval_config(diffuser, replan="deviation:0.5").controller.look_ahead == 4
    # what the user sets wins, field by field; avoid=plain drops the avoidance part; a repair keeps its own
    mine = eval_config(cdrb, parse_set(["replan=every:50", "controller.look_ahead=0"]))
    assert mine.controller.look_ahead == 0 and mine.avoid.best_of == 8
    plain = eval_config(cdrb, parse_set(["replan=every:50", "avoid=plain"]))
    assert plain.avoid == AvoidConfig() and plain.controller.look_ahead == 2
    repair = eval_config(cdrb, parse_set(["replan=every:50", "replan.repair_k=2"]))
    assert repair.controller.look_ahead == 0 and repair.avoid == AvoidConfig()
    # the official executor has no plan clock to move: only the avoidance part applies
    official = eval_config(cdrb, protocol="official-code", replan="every:50")
    assert official.controller.name == "waypoint" and official.avoid.best_of == 8
    # the time-indexed clock (max_lag null) has no gate for a look-ahead to move: that default is left out
    timed = eval_config(cdrb, parse_set(["replan=every:50", "controller.max_lag=null"]))
    assert timed.controller.look_ahead == 0 and timed.controller.max_lag is None and timed.avoid.best_of == 8


def _corridor_and_centre(model):
    """A start in the map's start region and one in the outer corridor (a free cell that is no start cell)."""
    import numpy as np

    from cdrb_cli.envs.pointmaze.maze import MazeGeometry

    geom = MazeGeometry(model.manifest.env.scene.maze)
    outer = np.argwhere(geom.free & ~np.isin(geom.grid, ["S", "C"]))[0]
    centre, corridor = geom.cell_to_xy(geom.start_cells[0]), geom.cell_to_xy(outer)
    return np.r_[centre, 0.0, 0.0], np.r_[corridor, 0.0, 0.0]


def test_plans_from_anywhere_use_the_settings_chosen_for_them_by_default(tiny_models):
    import numpy as np

    from cdrb_cli.envs.pointmaze import PointMazeFamily

    cdrb = tiny_models["cdrb"]
    n = PointMazeFamily.start_tuned["cdrb"]["avoid.best_of"]
    assert n > 1
    # the family's second try from a buffer route, its k cut to the tiny model's last repair step (T = 8)
    chosen = PointMazeFamily.start_tuned["cdrb"]
    k = min(7, chosen["avoid.fallback_route_k"])
    tuned = AvoidConfig(
        best_of=n,
        fallback_route_k=k,
        fallback_route_itself=chosen["avoid.fallback_route_itself"],
        first_step=chosen["avoid.first_step"],
        retime=chosen["avoid.retime"],
    )
    centre, corridor = _corridor_and_centre(cdrb)
    assert plan_config(cdrb, starts=centre[None]).avoid == AvoidConfig()  # where the data start: the paper's
    assert plan_config(cdrb, starts=np.stack([centre, corridor])).avoid == tuned
    # the second try turned off takes its last resort with it
    off = plan_config(cdrb, parse_set(["avoid.fallback_route_k=null"]), starts=corridor[None]).avoid
    assert off == AvoidConfig(best_of=n, first_step=chosen["avoid.first_step"], retime=chosen["avoid.retime"])
    # what the user sets wins; avoid=plain drops it; a method with nothing chosen plans as it is
    assert plan_config(cdrb, parse_set(["avoid=plain"]), starts=corridor[None]).avoid == AvoidConfig()
    assert plan_config(cdrb, parse_set(["avoid.best_of=2"]), starts=corridor[None]).avoid.best_of == 2
    assert plan_config(tiny_models["mlp"], starts=corridor[None]).avoid == AvoidConfig()
    # an eval under the protocol of starts anywhere takes it; the stock protocol keeps one plan per pair
    assert eval_config(cdrb, protocol="anywhere").avoid == tuned
    assert eval_config(cdrb).avoid == AvoidConfig()
    assert (
        eval_config(tiny_models["diffuser"], protocol="anywhere").avoid.best_of
        == PointMazeFamily.start_tuned["diffuser"]["avoid.best_of"]
    )
    # beside a scene's avoidance, the larger best-of
    scene = eval_config(cdrb, scene_file=NORTH, protocol="anywhere").avoid
    assert scene.mask_buffer and scene.best_of == max(n, PointMazeFamily.scene_avoid["cdrb"]["best_of"])


def test_the_start_default_is_what_a_call_may_change():
    """The Python API applies the default per call by changing the prepared planner's best-of and second try, so a
    family's choice for plans from anywhere may hold those settings alone."""
    from cdrb_cli.api import PER_CALL
    from cdrb_cli.envs.registry import FAMILIES

    for family in FAMILIES.builtin_entries():
        for settings in family.start_tuned.values():
            assert {f"avoid.{f}" for f in PER_CALL} >= set(settings), family.name
            AvoidConfig(**{key.split(".")[1]: value for key, value in settings.items()})


def test_cli_and_api_plans_from_the_corridor_keep_the_best_of_several(tiny_models, tmp_path, cdrb, monkeypatch):
    from cdrb_cli import api, artifacts
    from cdrb_cli.envs.pointmaze import PointMazeFamily
    from cdrb_cli.stages import plan as plan_stage

    model = tiny_models["cdrb"]
    n = PointMazeFamily.start_tuned["cdrb"]["avoid.best_of"]
    centre, corridor = _corridor_and_centre(model)
    point = ",".join(f"{v:g}" for v in corridor[:2])
    goal = ",".join(f"{v:g}" for v in centre[:2])
    r = cdrb("plan", model.path, "--start", point, "--goal", goal, "--out", tmp_path / "p.h5")
    assert r.returncode == 0, r.stderr
    assert artifacts.load(tmp_path / "p.h5", "plans").manifest.config.avoid.best_of == n
    assert f"best of {n}" in r.stderr
    seen = []
    real = plan_stage.sample_plans

    def spy(*a, **k):
        avoid = k["avoid"]
        seen.append((avoid.best_of, avoid.fallback_route_k, avoid.fallback_route_itself, avoid.first_step))
        return real(*a, **k)

    monkeypatch.setattr(plan_stage, "sample_plans", spy)
    planner = api.Planner(model.path)
    planner.plan(corridor[:2], centre[:2])
    planner.plan(centre[:2], corridor[:2])
    # from the corridor: the best of n and a second try from a buffer route (its graph built for it); from the
    # centre, the paper's one plan
    k = min(7, PointMazeFamily.start_tuned["cdrb"]["avoid.fallback_route_k"])
    assert seen == [(n, k, True, True), (1, None, False, False)] and planner.avoidance.best_of == 1
    assert planner.avoidance.graph is not None


def test_cli_plans_avoid_a_new_wall_by_default(tiny_models, tmp_path, cdrb):
    r = cdrb("plan", tiny_models["cdrb"].path, "--pairs", "2", "--scene", NORTH, "--out", tmp_path / "p.h5")
    assert r.returncode == 0, r.stderr
    from cdrb_cli import artifacts

    plans = artifacts.load(tmp_path / "p.h5", "plans")
    # the family's k = 8, cut to the tiny model's last repair step (T = 8)
    assert plans.manifest.config.avoid.route_k == 7 and plans.manifest.config.avoid.mask_buffer
    assert "avoiding obstacles: masked buffer" in r.stderr


def test_a_selection_file_applies_its_choice_to_one_eval(tiny_models, tmp_path, cdrb):
    """`--config experiments/tuned/X.toml`: the eval settings `cdrb select` chose for the model's env and method (a
    table, or flags), read as `cdrb eval` reads them, under what the command line itself sets; `cdrb plan` takes
    those that are plan settings."""
    model = tiny_models["cdrb"]
    env = model.manifest.env.id
    chosen = tmp_path / "tuned.toml"
    chosen.write_text(
        '[meta]\nrule = "r"\n\n[[settings]]\nmethod = "cdrb"\neval = ["--sample-steps", "4"]\n\n'
        f'[[settings]]\nenv = "{env}"\nmethod = "cdrb"\nchosen = "x"\n'
        'eval = { replan = "every:40", avoid = { best_of = 3 }, controller = { look_ahead = 1 } }\n'
        f'\n[[settings]]\nenv = "{env}"\nmethod = "diffuser"\nchosen = "y"\neval = ["--best-of", "5"]\n'
    )
    base = ("eval", model.path, "-n", "1", "--seeds", "0", "--config", chosen, "--json")
    r = cdrb(*base, "--set", "controller.look_ahead=0", "--out", tmp_path / "e.h5")
    assert r.returncode == 0, r.stderr
    assert "deprecated" not in r.stderr
    from cdrb_cli import artifacts

    config = artifacts.load(tmp_path / "e.h5", "eval").manifest.config
    assert config.replan.every == 40 and config.avoid.best_of == 3 and config.sample_steps == 4
    assert config.controller.look_ahead == 0  # the command line wins
    r = cdrb("plan", model.path, "--pairs", "2", "-n", "1", "--config", chosen, "--out", tmp_path / "p.h5")
    assert r.returncode == 0, r.stderr
    plan = artifacts.load(tmp_path / "p.h5", "plans").manifest.config
    assert plan.avoid.best_of == 3 and plan.sample_steps == 4
    other = tmp_path / "other.toml"
    other.write_text('[meta]\nrule = "r"\n\n[[settings]]\nenv = "fetch-push"\nmethod = "cdrb"\neval = []\n')
    r = cdrb(*base[:-3], "--config", other, "--out", tmp_path / "f.h5")
    assert r.returncode == 2 and "chooses nothing for cdrb on" in r.stderr and "cdrb on fetch-push" in r.stderr
    assert not (tmp_path / "f.h5").exists()


def test_moved_flags_still_work_with_a_note(tiny_models, tmp_path, cdrb):
    model = tiny_models["cdrb"].path
    base = ("eval", model, "-n", "2", "--seeds", "0", "--json")
    old = cdrb(*base, "--best-of", "2", "--max-lag", "0", "--out", tmp_path / "old.h5")
    assert old.returncode == 0, old.stderr
    assert "--best-of is deprecated: write --set avoid.best_of=2" in old.stderr
    assert "--max-lag is deprecated: write --set controller.max_lag=null" in old.stderr
    new = cdrb(*base, "--set", "avoid.best_of=2", "--set", "controller.max_lag=null", "--out", tmp_path / "new.h5")
    assert new.returncode == 0 and "deprecated" not in new.stderr, new.stderr
    from cdrb_cli import artifacts

    a, b = (artifacts.load(tmp_path / f"{n}.h5", "eval").manifest for n in ("old", "new"))
    assert a.config == b.config
    assert json.loads(old.stdout)["summary"]["success_mean"] == json.loads(new.stdout)["summary"]["success_mean"]


def test_api_builds_the_same_configs(tiny_models, tmp_path):
    from cdrb_cli import api

    model = tiny_models["cdrb"].path
    planner = api.Planner(model, scene=NORTH, settings={"avoid.best_of": 2})
    assert planner.config.avoid.best_of == 2 and planner.config.avoid.route_k == 7
    assert api.Planner(model, best_of=3).config.avoid == AvoidConfig(best_of=3)
    with pytest.raises(BadInput, match="repeated seeds"):
        api.evaluate(model, tmp_path / "e.h5", episodes=1, seeds=[0, 0])
    with pytest.raises(BadInput, match="best_of=2 and settings"):
        api.evaluate(model, tmp_path / "e.h5", episodes=1, best_of=2, settings={"avoid.best_of": 3})
    with pytest.raises(BadInput, match="diffuser samples from no replay buffer"):
        api.Planner(tiny_models["diffuser"].path, mask_buffer=True)
    assert not (tmp_path / "e.h5").exists()


def test_a_model_trained_with_a_selection_records_it_and_starts_from_its_eval_settings(small_data, tmp_path, cdrb):
    """`cdrb train --config SELECTION`: the training chosen for the env and method, and the model records the choice;
    its plans and evals then start from the eval settings chosen with it (not those of one run: episodes, the
    re-planning trigger), the command line and a protocol's own executor still winning."""
    from cdrb_cli import artifacts

    demos, _ = small_data
    chosen = tmp_path / "tuned.toml"
    chosen.write_text(
        '[meta]\nrule = "r"\n\n[[settings]]\nenv = "maze-tight"\nmethod = "mlp"\nchosen = "base @ 20 steps"\n'
        "train = { steps = 20, net = { hidden = [16, 16] }, horizon = 16 }\n"
        "eval = { controller = { max_lag = 0.3, look_ahead = 1 }, avoid = { best_of = 2 }, episodes = 3, "
        'replan = "every:40" }\n'
    )
    model = tmp_path / "m.h5"
    r = cdrb("train", demos.path, "--method", "mlp", "--config", chosen, "--set", "stride=10", "--out", model)
    assert r.returncode == 0, r.stderr
    m = artifacts.load(model, "model").manifest
    assert m.config.steps == 20 and m.config.net.hidden == [16, 16] and m.config.stride == 10
    assert m.profile.file == "tuned.toml" and m.profile.chosen == "base @ 20 steps"
    assert m.profile.eval == {"controller.max_lag": 0.3, "controller.look_ahead": 1, "avoid.best_of": 2}

    def run(*args):
        out = tmp_path / f"e{len(list(tmp_path.glob('e*.h5')))}.h5"
        r = cdrb("eval", model, "-n", "1", "--seeds", "0", *args, "--out", out)
        assert r.returncode == 0, r.stderr
        return artifacts.load(out, "eval").manifest.config

    plain = run()
    assert (plain.controller.max_lag, plain.controller.look_ahead, plain.avoid.best_of) == (0.3, 1, 2)
    assert plain.replan.mode == "never" and plain.episodes == 1
    assert run("--set", "controller.max_lag=0.5").controller.look_ahead == 1  # the command line wins where it speaks
    assert run("--set", "controller.max_lag=0.5").controller.max_lag == 0.5
    official = run("--protocol", "official-code")  # its own executor: none of the profile's controller settings
    assert official.controller.name == "waypoint" and official.avoid.best_of == 2
    r = cdrb("plan", model, "--pairs", "1", "--out", tmp_path / "p.h5")
    assert r.returncode == 0, r.stderr
    assert artifacts.load(tmp_path / "p.h5", "plans").manifest.config.avoid.best_of == 2
    other = tmp_path / "other.toml"
    other.write_text('[meta]\nrule = "r"\n\n[[settings]]\nenv = "maze"\nmethod = "mlp"\ntrain = { steps = 5 }\n')
    r = cdrb("train", demos.path, "--method", "mlp", "--config", other, "--out", tmp_path / "x.h5")
    assert r.returncode == 2 and "chooses nothing for mlp on maze-tight" in r.stderr
    assert not (tmp_path / "x.h5").exists()


@pytest.mark.parametrize(
    "entry, words",
    [
        ('eval = ["--help"]', "eval flags --help: ask for help"),
        ('eval = ["--config", "more.toml"]', "name another settings file with --config"),
        ('eval = "best_of"', "settings.0.eval"),
        ("chosen = 3", "settings.0.chosen"),
    ],
)
def test_a_selection_that_cannot_be_read_whole_is_one_line(tiny_models, tmp_path, cdrb, entry, words):
    """A selection file's entry is read as the command reads its own line: flags asking for help (which printed
    it and stopped), naming another settings file (whose settings were dropped) or of the wrong type are refused,
    naming the file."""
    model = tiny_models["cdrb"]
    (tmp_path / "more.toml").write_text("sample_steps = 4\n")
    chosen = tmp_path / "tuned.toml"
    chosen.write_text(
        f'[meta]\nrule = "r"\n\n[[settings]]\nenv = "{model.manifest.env.id}"\nmethod = "cdrb"\n{entry}\n'
    )
    r = cdrb("eval", model.path, "-n", "1", "--seeds", "0", "--config", chosen, "--out", tmp_path / "e.h5")
    assert r.returncode == 2 and r.stdout == "" and str(chosen) in r.stderr and words in r.stderr, r.stderr
    assert r.stderr.count("\n") == 1 and not (tmp_path / "e.h5").exists()
