"""A hyper-parameter is declared once, as a config field: --set, --config files, `cdrb config` and the errors all
come from the config records."""

from __future__ import annotations

import json
import re

import pytest
import tomllib

from cdrb_cli.errors import BadInput
from cdrb_cli.settings import Setting, apply, lookup, parse_set, parse_value, read_config_file
from tests.conftest import run_cdrb


@pytest.mark.parametrize(
    "text, value",
    [
        ("32", 32),
        ("2e-4", 2e-4),
        ("true", True),
        ("null", None),
        ("1,4,8", [1, 4, 8]),
        ("[1, 4]", [1, 4]),
        ("log", "log"),
        (".001", 0.001),  # decimals as people write them, which JSON refuses
        ("1.", 1.0),
        ("-.5e-3", -0.0005),
        ("007", "007"),
    ],
)
def test_values_parse_as_json_then_lists_then_text(text, value):
    assert parse_value(text) == value


def test_set_keys_and_precedence():
    s = parse_set(["net.dim=8", "net.dim-mults=1,2", "net.dim=16"])
    assert [x.path for x in s] == [("net", "dim"), ("net", "dim_mults"), ("net", "dim")]
    assert lookup(s, ("net", "dim")).value == 16 and lookup(s, ("net", "dim")).source == "--set net.dim=16"
    assert apply({"net": {"dim": 1, "kind": "unet"}, "steps": 3}, s) == {
        "net": {"dim": 16, "kind": "unet", "dim_mults": [1, 2]},
        "steps": 3,
    }
    for bad in ("net.dim", "=3", "a..b=1", "1x=2"):
        with pytest.raises(BadInput, match="--set"):
            parse_set([bad])


def test_config_files(tmp_path):
    toml = tmp_path / "run.toml"
    toml.write_text('steps = 10\n"method.schedule" = "log"\n[net]\ndim = 8\n')
    got = {s.key: (s.value, s.source) for s in read_config_file(toml)}
    assert got == {
        "steps": (10, f"--config {toml}: steps"),
        "method.schedule": ("log", f"--config {toml}: method.schedule"),
        "net.dim": (8, f"--config {toml}: net.dim"),
    }
    js = tmp_path / "run.json"
    js.write_text(json.dumps({"net": {"dim": 8}}))
    assert read_config_file(js) == [Setting(("net", "dim"), 8, f"--config {js}: net.dim", from_file=True)]
    twice = tmp_path / "twice.json"  # one key in two spellings: one value would be lost without a word
    twice.write_text(json.dumps({"net": {"dim": 8}, "net.dim": 16}))
    with pytest.raises(BadInput, match="net.dim is given twice"):
        read_config_file(twice)
    bad = tmp_path / "bad.toml"
    bad.write_text("steps = = 3\n")
    with pytest.raises(BadInput, match="not valid TOML"):
        read_config_file(bad)
    with pytest.raises(BadInput, match="no such settings file"):
        read_config_file(tmp_path / "absent.toml")


def _dry(cdrb, demos, buffer, *args):
    r = cdrb("train", demos.path, "--buffer", buffer.path, "--dry-run", *args)
    assert r.returncode == 0, r.stderr
    return json.loads(r.stdout)


def test_dry_run_layers_presets_data_and_settings(small_data, tmp_path, cdrb):
    demos, buffer = small_data
    base = _dry(cdrb, demos, buffer)
    assert base["preset"] == "quick" and base["net"]["dim"] == 16 and base["method"]["diffusion_steps"] == 32
    assert base["horizon"] == demos.manifest.env.horizon and base["method"]["d_max"] == buffer.manifest.summary.diameter
    paper = _dry(cdrb, demos, buffer, "--preset", "paper")
    assert (
        paper["net"]["dim_mults"] == [1, 4, 8] and paper["method"]["diffusion_steps"] == 128 and paper["steps"] == 20000
    )
    cfg = tmp_path / "c.toml"
    cfg.write_text("steps = 7\n[net]\ndim = 24\n")
    mixed = _dry(cdrb, demos, buffer, "--config", cfg, "--set", "net.dim=32", "--steps", "9")
    assert mixed["net"]["dim"] == 32 and mixed["steps"] == 9  # the file < --set < the dedicated flags
    assert not any(tmp_path.glob("*.h5"))


def test_config_template_round_trips(small_data, tmp_path, cdrb):
    """`cdrb config --format toml` is a valid --config file that reproduces the defaults."""
    demos, buffer = small_data
    for method, fmt in (("cdrb", "toml"), ("diffuser", "json"), ("diffusion-bc", "toml")):  # bc: a null default
        r = cdrb("config", "train", "--method", method, "--preset", "paper", "--format", fmt)
        assert r.returncode == 0, r.stderr
        path = tmp_path / f"{method}.{fmt}"
        path.write_text(r.stdout)
        extra = ["--buffer", buffer.path] if method == "cdrb" else []
        a = json.loads(cdrb("train", demos.path, *extra, "--config", path, "--dry-run").stdout)
        b = json.loads(cdrb("train", demos.path, *extra, "--method", method, "--preset", "paper", "--dry-run").stdout)
        assert a == b


@pytest.mark.parametrize("args", [["plan"], ["eval"], ["eval", "--controller", "fetch-track"]])
def test_plan_and_eval_templates_comment_every_key_and_uncomment_to_the_defaults(args, cdrb):
    """A plan/eval template sets nothing (the model's profile, its env and --scene choose defaults first); each
    commented key uncomments to valid TOML holding the table's default; JSON, which cannot comment, is refused."""
    from cdrb_cli.stages.show_config import config_template

    r = cdrb("config", *args, "--format", "toml")
    assert r.returncode == 0, r.stderr
    doc = tomllib.loads(r.stdout)
    assert all(v == {} for v in doc.values()), doc  # only empty tables: no key is set
    uncommented = re.sub(r"(?m)^# (?=[a-z_]+ = (?!\.\.\.))", "", r.stdout)
    values = tomllib.loads(uncommented)
    controller = args[2] if len(args) > 2 else None
    rows = config_template(args[0], controller=controller, every_controller=False)
    active = [row for row in rows if not row.placeholder and row.default is not None]
    assert active
    for row in active:
        node = values
        for part in row.key.split("."):
            node = node[part]
        assert node == (list(row.default) if isinstance(row.default, tuple) else row.default), row.key
    r = cdrb("config", args[0], "--format", "json")
    assert r.returncode == 2 and "--format toml" in r.stderr and not r.stdout


def test_toml_template_nests_records_and_keeps_descriptions_to_one_comment_line():
    """A record nested in a record gets its own table (a plugin's method or controller may declare one), keys that
    are not bare are quoted, and a description with line breaks or control characters stays one comment."""
    from cdrb_cli.stages.show_config import Row, render_template

    rows = [
        Row("steps", "int", 3, "two\nlines = 9"),
        Row("method.sub.inner", "float", 0.5, "a\x07bell"),
        Row("method.w", "int", 2, ""),
        Row("method.sub.my key", "int", 5, ""),
        Row("controller.gain", "float", None, "null\rdefault"),
        Row("controller.tag", "str", "(v2)", "a text default that looks like a note"),
        Row("seed", "int", "(--seed)", "", placeholder=True),
    ]
    text = render_template(rows, "toml")
    expected = {"steps": 3, "method": {"w": 2, "sub": {"inner": 0.5, "my key": 5}}, "controller": {"tag": "(v2)"}}
    assert tomllib.loads(text) == expected and json.loads(render_template(rows, "json"))["controller"] == {
        "gain": None,
        "tag": "(v2)",
    }
    assert text.index("[method]") < text.index("[method.sub]") and "\x07" not in text
    assert "# (seed: give --seed, not a key here)" in text  # a flag's field is no key to uncomment
    commented = render_template(rows, "toml", all_commented=True)
    uncommented = re.sub(r'(?m)^# (?=[a-z_"][^=\n]* = (?!\.\.\.))', "", commented)
    assert tomllib.loads(uncommented) == tomllib.loads(text)


def test_config_table_lists_every_field_with_its_description(cdrb):
    from cdrb_cli.configs import TrainConfig
    from cdrb_cli.methods.cdrb import CDRBParams

    r = cdrb("config", "train")
    assert r.returncode == 0
    for name, f in TrainConfig.model_fields.items():
        if name not in ("method", "net"):
            assert name in r.stdout and f.description[:30] in r.stdout, name
    for name in CDRBParams.model_fields:
        assert f"method.{name}" in r.stdout
    r = cdrb("config", "eval", "--controller", "pd")
    assert "controller.kp" in r.stdout and "controller.max_lag" in r.stdout


def test_eval_settings_name_the_flag(small_data, tmp_path, cdrb):
    from cdrb_cli.methods.config import train_config
    from cdrb_cli.stages.train import train
    from tests.test_train import tiny

    demos, buffer = small_data
    model = train(demos, buffer, train_config(demos, buffer, "cdrb", tiny("cdrb", steps=2)), tmp_path / "m.h5")
    r = cdrb("eval", model.path, "--set", "controller.kp=fast", "--out", tmp_path / "e.h5")
    assert r.returncode == 2 and "--set controller.kp=fast" in r.stderr and r.stderr.count("\n") == 1
    r = cdrb("eval", model.path, "--set", "controller.max_lag=-1", "--out", tmp_path / "e.h5")
    assert r.returncode == 2 and "--set controller.max_lag=-1" in r.stderr
    r = cdrb("eval", model.path, "--episodes", "5", "--set", "episodes=7", "--out", tmp_path / "e.h5")
    assert r.returncode == 2 and "give it once" in r.stderr
    r = cdrb("eval", model.path, "--seeds", str(2**40), "--out", tmp_path / "e.h5")
    assert r.returncode == 2 and "32-bit" in r.stderr
    r = cdrb("eval", model.path, "--set", "scene=x.txt", "--out", tmp_path / "e.h5")
    assert r.returncode == 2 and "scene is not a setting" in r.stderr and "--scene FILE" in r.stderr
    r = cdrb("eval", model.path, "--set", "episodes=0", "--out", tmp_path / "e.h5")
    assert r.returncode == 2 and "--set episodes=0" in r.stderr
    assert not (tmp_path / "e.h5").exists()


def test_config_file_errors_name_the_key(small_data, tmp_path, cdrb):
    demos, buffer = small_data
    bad = tmp_path / "inf.toml"
    bad.write_text("lr = inf\n")
    r = cdrb("train", demos.path, "--buffer", buffer.path, "--config", bad, "--dry-run")
    assert r.returncode == 2 and f"--config {bad}: lr: Input should be a finite number" in r.stderr
    # overridden by --set or a flag, the file's value is still checked (the file is reused elsewhere as it is)
    for override in (["--set", "lr=0.001"], ["--set", "lr=0.001", "--steps", "3"]):
        r = cdrb("train", demos.path, "--buffer", buffer.path, "--config", bad, *override, "--dry-run")
        assert r.returncode == 2 and f"--config {bad}: lr: Input should be a finite number" in r.stderr, r.stderr
        assert "overrides it here" in r.stderr and r.stderr.count("\n") == 1
    bad.write_text('steps = "many"\n')
    r = cdrb("train", demos.path, "--buffer", buffer.path, "--config", bad, "--steps", "3", "--dry-run")
    assert r.returncode == 2 and f"--config {bad}: steps: Input should be a valid integer" in r.stderr, r.stderr
    # a valid file value overridden is fine, and the override wins
    bad.write_text("steps = 5\nlr = 0.01\n")
    r = cdrb("train", demos.path, "--buffer", buffer.path, "--config", bad, "--steps", "3", "--dry-run")
    assert r.returncode == 0, r.stderr


def test_a_second_run_names_the_settings_that_differ(small_data, tmp_path, cdrb):
    from cdrb_cli.methods.config import train_config
    from cdrb_cli.stages.train import train
    from tests.test_train import TINY_FLAGS, tiny

    demos, buffer = small_data
    out = tmp_path / "m.h5"
    train(demos, buffer, train_config(demos, buffer, "cdrb", tiny("cdrb", steps=2)), out)
    r = cdrb("train", demos.path, "--buffer", buffer.path, "--steps", "2", *TINY_FLAGS, "--set", "lr=0.1", "--out", out)
    assert r.returncode == 2 and "other settings: lr" in r.stderr
    r = cdrb("train", demos.path, "--buffer", buffer.path, "--steps", "4", *TINY_FLAGS, "--out", out)
    assert r.returncode == 2 and "a finished model at step 2" in r.stderr and "--resume" in r.stderr


@pytest.mark.parametrize(
    "source, needle",
    [
        ("raise RuntimeError('boom')", "failed to import: RuntimeError: boom"),
        ("import sys; sys.exit('bye')", "failed to import: SystemExit: bye"),
        ("raise KeyboardInterrupt", "it raised KeyboardInterrupt itself"),  # not the user's Ctrl-C: not exit 130
        (
            "from cdrb_cli.methods.registry import METHODS\nMETHODS.register(object())",
            "a method entry must be a MethodEntry",
        ),
    ],
)
def test_broken_plugins_are_one_line(tmp_path, source, needle):
    (tmp_path / "myplugin.py").write_text(source + "\n")
    env = {"CDRB_PLUGINS": "myplugin", "PYTHONPATH": str(tmp_path)}
    r = run_cdrb("methods", env=env)  # a fresh process: plugins load once per process, from its PYTHONPATH
    assert r.returncode == 2 and "plugin 'myplugin'" in r.stderr and needle in r.stderr, r.stderr
    assert r.stderr.count("\n") == 1 and r.stdout == ""


def test_options_of_the_other_stage_are_refused(cdrb):
    assert cdrb("config", "eval", "--method", "mlp").returncode == 2
    assert cdrb("config", "train", "--controller", "pd").returncode == 2
    r = cdrb("config", "collect", "--format", "toml")
    assert r.returncode == 2 and "collect reads no --config file" in r.stderr


@pytest.mark.parametrize(
    "setting", ["steps=true", "lr=true", "net.residual=1", 'net.residual="yes"', "steps=3.5", "steps=3.0"]
)
def test_settings_are_not_coerced(small_data, tmp_path, cdrb, setting):
    """A value of another type is an error naming the setting, never coerced (true was 1 step, 1 was true)."""
    demos, buffer = small_data
    r = cdrb("train", demos.path, "--buffer", buffer.path, "--set", setting, "--dry-run")
    assert r.returncode == 2 and f"--set {setting}:" in r.stderr and r.stderr.count("\n") == 1
    toml = tmp_path / "c.toml"
    key, value = setting.split("=", 1)
    section, _, field = key.rpartition(".")
    toml.write_text((f"[{section}]\n" if section else "") + f"{field} = {value}\n")
    r = cdrb("train", demos.path, "--buffer", buffer.path, "--config", toml, "--dry-run")
    assert r.returncode == 2 and f"--config {toml}" in r.stderr


def test_a_json_key_given_twice_is_refused(small_data, tmp_path, cdrb):
    """JSON lets the last of two equal keys win silently; a settings file or --set value with one is exit 2."""
    demos, buffer = small_data
    cfg = tmp_path / "c.json"
    cfg.write_text('{"steps": 5, "lr": 0.001, "steps": 7}')
    r = cdrb("train", demos.path, "--buffer", buffer.path, "--config", cfg, "--dry-run")
    assert r.returncode == 2 and "'steps' is given twice" in r.stderr and r.stderr.count("\n") == 1
    r = cdrb("train", demos.path, "--buffer", buffer.path, "--set", 'net={"dim": 8, "dim": 16}', "--dry-run")
    assert r.returncode == 2 and "'dim' is given twice" in r.stderr


def test_a_very_deep_or_very_long_key_is_one_short_line(small_data, tmp_path, cdrb):
    """A 5,000-part dotted key (on --set, in a settings file, in a grid file) is refused in one line that names the
    flag or file without echoing the key; a 4.5 KB key is cut in the error."""
    demos, buffer = small_data
    deep = ".".join(["a"] * 5000)
    r = cdrb("train", demos.path, "--buffer", buffer.path, "--set", f"{deep}=1", "--dry-run")
    assert r.returncode == 2 and "at most 8 dotted parts" in r.stderr, r.stderr[-500:]
    assert r.stderr.count("\n") == 1 and len(r.stderr) < 400
    cfg = tmp_path / "deep.toml"
    cfg.write_text(f"{deep} = 1\n")
    r = cdrb("train", demos.path, "--buffer", buffer.path, "--config", cfg, "--dry-run")
    assert r.returncode == 2 and f"--config {cfg}" in r.stderr and r.stderr.count("\n") == 1, r.stderr[-500:]
    assert len(r.stderr) < 400 + len(str(cfg))
    grid = tmp_path / "deep-grid.toml"
    grid.write_text(f'out = "g"\nenvs = ["maze-tight"]\nmethods = ["mlp"]\nseeds = [0]\n{deep} = 1\n')
    r = cdrb("grid", grid, "--dry-run")
    assert r.returncode == 2 and str(grid) in r.stderr and r.stderr.count("\n") == 1, r.stderr[-500:]
    assert len(r.stderr) < 400 + len(str(grid))
    long_key = "k" * 4500
    r = cdrb("train", demos.path, "--buffer", buffer.path, "--set", f"{long_key}=1", "--dry-run")
    assert r.returncode == 2 and r.stderr.count("\n") == 1 and len(r.stderr) < 400, r.stderr[-500:]


def test_a_setting_is_strict_inside_registry_records_and_given_once(small_data, tmp_path, cdrb):
    """`true` is not a number inside a controller's record either, and a field given by a flag and by --set is
    refused rather than one silently winning."""
    demos, buffer = small_data
    r = cdrb("train", demos.path, "--buffer", buffer.path, "--steps", "10", "--set", "steps=true", "--dry-run")
    assert r.returncode == 2 and "give it once" in r.stderr, r.stderr
    from cdrb_cli.methods.config import train_config
    from cdrb_cli.stages.train import train
    from tests.test_train import tiny

    model = train(demos, buffer, train_config(demos, buffer, "cdrb", tiny("cdrb", steps=2)), tmp_path / "m.h5")
    for setting in ("controller.look_ahead=true", "controller.kp=true", 'controller.kp="3"'):
        r = cdrb("eval", model.path, "--set", setting, "-n", "1", "--out", tmp_path / "e.h5")
        assert r.returncode == 2 and f"--set {setting}" in r.stderr and not (tmp_path / "e.h5").exists(), r.stderr


def test_a_toml_table_lists_its_null_settings_and_tables_round_trip(tmp_path):
    """TOML has no null: a table names its null settings in a ``null`` list (a config file, a grid's table); the
    tables a settings file writes read back as the same settings, as flags and as a --config file alike."""
    import cdrb_cli.cli  # noqa: F401  (installs the description of the commands)
    from cdrb_cli.orchestration.grid import as_table, parse_command, table_flags
    from cdrb_cli.settings import toml_value

    path = tmp_path / "c.toml"
    path.write_text('episodes = 3\nnull = ["sample_steps"]\n[controller]\nkp = 2.0\nnull = ["max_lag"]\n')
    got = {s.key: s.value for s in read_config_file(path)}
    assert got == {"episodes": 3, "sample_steps": None, "controller.kp": 2.0, "controller.max_lag": None}
    flags = ["--max-lag", "0", "--set", "controller.max_wait=10", "--best-of", "4", "--seeds", "0,1"]
    table = as_table(flags, "eval")
    assert table == {"avoid": {"best_of": 4}, "controller": {"max_wait": 10}, "seeds": [0, 1],
                     "null": ["controller.max_lag"]}  # fmt: skip
    back = table_flags(tomllib.loads("x = " + toml_value(table))["x"])
    assert parse_command(["eval", "m.h5", *back]) == parse_command(["eval", "m.h5", *flags])
    path.write_text("".join(f"{k} = {toml_value(v)}\n" for k, v in table.items()))  # the table as a --config file
    assert {s.key: s.value for s in read_config_file(path)} == {
        "avoid.best_of": 4, "controller.max_wait": 10, "seeds": [0, 1], "controller.max_lag": None}  # fmt: skip
    # flags that are more than settings (a file, a scene) stay flags
    assert as_table(["--scene", "x.txt", "--best-of", "4"], "eval") is None
    assert as_table(["--route-buffer", "b.h5"], "eval") is None


def test_a_flag_and_a_set_that_reach_one_field_in_other_spellings_are_refused():
    """A shortcut written out or a table's fields count as the fields they write: ``--replan every:20`` with ``--set
    replan.every=30``, or a controller flag with a controller table, is one field given twice; a shortcut with a
    field it does not write, or an ``avoid`` mode with an avoid field, is not."""
    from cdrb_cli.cli.options import run_settings

    replan = [("--replan every:20", "replan", "every:20")]
    with pytest.raises(BadInput, match=re.escape("--replan every:20 with --set replan.every=30 (give it once)")):
        run_settings(None, ["replan.every=30"], replan, {})
    with pytest.raises(BadInput, match="--controller pd with --set controller="):
        run_settings(None, ['controller={name = "waypoint"}'], [("--controller pd", "controller.name", "pd")], {})
    assert [s.path for s in run_settings(None, ["replan.repair_k=3"], replan, {})] == [
        ("replan",),
        ("replan", "repair_k"),
    ]
    assert len(run_settings(None, ["avoid.best_of=4"], [("--avoid tuned", "avoid", "tuned")], {})) == 2


def test_one_file_reaching_a_field_twice_is_refused_and_the_last_set_wins(tmp_path):
    """Within one source too, a shortcut and the field it writes are one field given twice (one would silently
    win); an ``avoid`` mode with an avoid field, or the shortcut with another field, is no clash."""
    from cdrb_cli.cli.options import run_settings

    clash = tmp_path / "clash.toml"
    clash.write_text('controller = "pd"\n"controller.name" = "waypoint"\n')
    with pytest.raises(BadInput, match=re.escape(f"--config {clash}: controller and controller.name both set")):
        run_settings(clash, [], [], {})
    clash.write_text('replan = "every:20"\n"replan.every" = 30\n')
    with pytest.raises(BadInput, match="both set replan.every"):
        run_settings(clash, [], [], {})
    # the --set flags have an order: the last one wins, as documented
    last = run_settings(None, ["replan=every:20", "replan.every=30", "n=2", "n=3"], [], {})
    assert [(s.path, s.value) for s in last][-2:] == [(("n",), 2), (("n",), 3)]
    fine = tmp_path / "fine.toml"
    fine.write_text('avoid = "tuned"\n"avoid.best_of" = 4\nreplan = "every:20"\n"replan.repair_k" = 3\n')
    assert len(run_settings(fine, [], [], {})) == 4


def test_a_toml_date_is_named_with_its_file_and_key(small_data, tmp_path):
    """TOML has dates and times, JSON (what settings are validated as) has not: the error names the key."""
    from cdrb_cli.methods.config import buffer_info, resolve_train_config, user_settings

    demos, buffer = small_data
    cfg = tmp_path / "c.toml"
    cfg.write_text("[net]\ndim = 1979-05-27T07:32:00\n")
    with pytest.raises(BadInput, match=re.escape(f"--config {cfg}: net.dim: a datetime is not a setting value")):
        resolve_train_config(demos.manifest.env, buffer_info(buffer), user_settings(config_file=cfg))


def test_a_check_across_fields_names_the_one_setting_it_names_not_the_last_applied():
    """A record-wide check (empty error location) that names one setting is blamed on that setting's source, not on
    whichever setting was applied last."""
    from pydantic import BaseModel, ConfigDict, model_validator

    from cdrb_cli.errors import BadInput
    from cdrb_cli.settings import validate

    class Inner(BaseModel):
        model_config = ConfigDict(extra="forbid")
        route_buffer: str | None = None

    class Outer(BaseModel):
        model_config = ConfigDict(extra="forbid")
        episodes: int = 1
        avoid: Inner = Inner()

        @model_validator(mode="after")
        def _needs(self):
            if self.avoid.route_buffer is not None:
                raise ValueError("avoid.route_buffer needs a route")
            return self

    given = [
        Setting(("avoid", "route_buffer"), "b.h5", "--config rb.toml: avoid.route_buffer"),
        Setting(("episodes",), 2, "--episodes 2"),
    ]
    data = {"episodes": 2, "avoid": {"route_buffer": "b.h5"}}
    with pytest.raises(BadInput) as err:
        validate(Outer, data, given, "eval")
    assert str(err.value).startswith("--config rb.toml: avoid.route_buffer: "), str(err.value)
