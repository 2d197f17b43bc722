"""Model folders (`cdrb export MODEL --dir`, `cdrb import model`, `api.Planner(DIR)`): the round trip gives the same
model and the same plans, the folder loads with safetensors and json alone, and a tampered folder is refused."""

from __future__ import annotations

import json
import os
import shutil

import numpy as np
import pytest

from cdrb_cli import artifacts
from cdrb_cli.errors import BadInput
from tests.conftest import ROOT


@pytest.fixture(scope="module")
def folder(tiny_models, tmp_path_factory):
    """The tiny CDRB model exported, with one eval of it in the model card."""
    from cdrb_cli import api
    from cdrb_cli.stages.share import export_folder

    root = tmp_path_factory.mktemp("share")
    model = tiny_models["cdrb"]
    api.evaluate(model.path, root / "eval.h5", episodes=2, seeds=[0])
    return export_folder(model, root / "cdrb-folder", [artifacts.load(root / "eval.h5", "eval")])


def test_export_import_and_the_api_give_the_same_model_and_plans(tiny_models, folder, tmp_path, cdrb):
    from safetensors.numpy import load_file

    from cdrb_cli import api

    model = tiny_models["cdrb"]
    assert sorted(p.name for p in folder.iterdir()) == ["README.md", "SHA256SUMS", "config.json", "model.safetensors"]
    # the folder without cdrb: every array by its artifact name, the manifest as JSON
    arrays = load_file(str(folder / "model.safetensors"))
    assert arrays.keys() == model.arrays.keys()
    for k, a in arrays.items():  # the same values (NaN where the curve has none) and types
        np.testing.assert_array_equal(a, model.arrays[k], err_msg=k)
        assert a.dtype == model.arrays[k].dtype and a.shape == model.arrays[k].shape, k  # an optimizer's 0-d step
    config = json.loads((folder / "config.json").read_text())
    assert config["config"]["method"]["name"] == "cdrb" and config["env"]["id"] == model.manifest.env.id
    card = (folder / "README.md").read_text()
    assert "# cdrb on maze-tight" in card and "| centre-start/corner-goal | test, seeds 0 x 2 |" in card

    mine = tmp_path / "back.h5"
    mine.write_text("my notes\n")
    for out, needle in ((mine, "file exists"), (folder / "model.safetensors", "inside the imported folder")):
        r = cdrb("import", "model", folder, "--out", out)  # nothing written over without --force, nor what is read
        assert r.returncode == 2 and needle in r.stderr, r.stderr
    assert mine.read_text() == "my notes\n"
    r = cdrb("import", "model", folder, "--out", tmp_path / "back.h5", "--force")
    assert r.returncode == 0, r.stderr
    back = artifacts.load(tmp_path / "back.h5", "model")
    assert back.data_sha256 == model.data_sha256 and back.manifest == model.manifest
    assert all(back.arrays[k].shape == a.shape for k, a in model.arrays.items())
    plans = {}
    for name, path in (("original", model.path), ("imported", tmp_path / "back.h5")):
        r = cdrb("plan", path, "--pairs", "3", "-n", "2", "--seed", "4", "--out", tmp_path / f"{name}.h5")
        assert r.returncode == 0, r.stderr
        plans[name] = artifacts.load(tmp_path / f"{name}.h5", "plans").arrays["plans"]
    np.testing.assert_array_equal(plans["original"], plans["imported"])
    a = api.Planner(model.path).plan([0.0, 0.0], [1.0, 1.0], n=3, seed=2)
    b = api.Planner(folder).plan([0.0, 0.0], [1.0, 1.0], n=3, seed=2)
    np.testing.assert_array_equal(a.features, b.features)


def _copy(folder, tmp_path):
    import shutil

    return shutil.copytree(folder, tmp_path / "copy")


def _edit(path, keys, change) -> str:
    """The JSON file's text with the value at ``keys`` changed by ``change``."""
    data = json.loads(path.read_text())
    inner = data
    for k in keys[:-1]:
        inner = inner[k]
    inner[keys[-1]] = change(inner[keys[-1]])
    return json.dumps(data)


def _resum(path):
    from cdrb_cli.files import sha256_file

    names = ("model.safetensors", "config.json", "README.md")
    (path / "SHA256SUMS").write_text("".join(f"{sha256_file(path / n)}  {n}\n" for n in names))


def _no_start(config: dict) -> str:
    maze = config["env"]["scene"]["maze"]
    maze["rows"] = [r.replace("S", ".").replace("C", "G") for r in maze["rows"]]
    return json.dumps(config)


def _link_outside(folder, name):
    """``name`` moved out of the folder and linked back (same bytes, same checksum)."""
    outside = folder.parent / f"outside-{name}"
    (folder / name).rename(outside)
    (folder / name).symlink_to(outside)


def _flip_byte(path, offset):
    data = bytearray(path.read_bytes())
    data[offset] ^= 0x01
    path.write_bytes(bytes(data))


@pytest.mark.parametrize(
    "damage, needle",
    [
        (lambda p: _flip_byte(p / "model.safetensors", -3), "its sha256 is not the one SHA256SUMS lists"),
        (lambda p: (p / "README.md").unlink(), "README.md: missing"),
        (lambda p: (p / "SHA256SUMS").write_text("0" * 64 + "  ../etc/passwd\n"), "is not a line it writes"),
        (lambda p: (p / "SHA256SUMS").unlink(), "SHA256SUMS"),
        (lambda p: _link_outside(p, "model.safetensors"), "model.safetensors: a symbolic link"),
        # consistent checksums over damaged content: the schema and the artifact's own checks refuse it
        (lambda p: (_flip_byte(p / "model.safetensors", 2), _resum(p)), "not a safetensors file"),
        (
            lambda p: (
                (p / "config.json").write_text(
                    json.dumps({**json.loads((p / "config.json").read_text()), "kind": "eval"})
                ),
                _resum(p),
            ),
            "not a model's manifest",
        ),
        (
            lambda p: (
                (p / "config.json").write_text((p / "config.json").read_text().replace('"horizon": ', '"horizon": -')),
                _resum(p),
            ),
            ".horizon: Input should be greater than",
        ),
        (  # a network's width edited, the weights left as they were
            lambda p: (
                (p / "config.json").write_text(_edit(p / "config.json", ["config", "net", "dim"], lambda d: 2 * d)),
                _resum(p),
            ),
            "config.json: tensor /ema/net/down.0.0.first.0.bias has shape (8,), but its config builds (16,)",
        ),
        (  # a map edited to one the protocol cannot draw pairs on (no start cell left)
            lambda p: (
                (p / "config.json").write_text(_no_start(json.loads((p / "config.json").read_text()))),
                _resum(p),
            ),
            "the map has no start cell",
        ),
    ],
)
def test_a_damaged_folder_is_refused_in_one_line_and_nothing_is_written(folder, tmp_path, cdrb, damage, needle):
    copy = _copy(folder, tmp_path)
    damage(copy)
    r = cdrb("import", "model", copy, "--out", tmp_path / "m.h5")
    assert r.returncode == 2 and needle in r.stderr and "Traceback" not in r.stderr, r.stderr
    assert len(r.stderr.strip().splitlines()) <= 2 and not (tmp_path / "m.h5").exists()


def test_arrays_that_disagree_with_the_manifest_are_refused(folder, tmp_path, cdrb):
    from safetensors.numpy import load_file, save_file

    copy = _copy(folder, tmp_path)
    arrays = load_file(str(copy / "model.safetensors"))
    arrays["buffer/points"] = arrays["buffer/points"][:, :1].copy()  # states of another dimension
    save_file(arrays, str(copy / "model.safetensors"))
    _resum(copy)
    r = cdrb("import", "model", copy, "--out", tmp_path / "m.h5")
    assert r.returncode == 2 and "buffer/points" in r.stderr and not (tmp_path / "m.h5").exists(), r.stderr


@pytest.mark.parametrize("value", [np.nan, np.inf, 1e30])
def test_weights_no_artifact_may_hold_are_the_folders_fault(folder, tmp_path, cdrb, value):
    """A weight made NaN, infinite or huge with consistent checksums: refused by name as the folder's (the CLI and
    the API alike), not a ValueError from writing the artifact."""
    from safetensors.numpy import load_file, save_file

    from cdrb_cli import api

    copy = _copy(folder, tmp_path)
    arrays = load_file(str(copy / "model.safetensors"))
    name = next(k for k, v in arrays.items() if k.startswith("ema/") and v.dtype.kind == "f")
    arrays[name] = arrays[name].copy()
    arrays[name].flat[0] = value
    save_file(arrays, str(copy / "model.safetensors"))
    _resum(copy)
    r = cdrb("import", "model", copy, "--out", tmp_path / "m.h5")
    assert r.returncode == 2 and f"tensor {name} holds non-finite" in r.stderr and r.stderr.count("\n") == 1, r.stderr
    with pytest.raises(BadInput, match="non-finite or out-of-range"):
        api.Planner(copy)


def test_export_asks_for_one_target_and_keeps_a_folder_unless_forced(tiny_models, folder, tmp_path, cdrb):
    model = tiny_models["cdrb"].path
    r = cdrb("export", model)
    assert r.returncode == 2 and "give one of --minari NAME" in r.stderr
    r = cdrb("export", model, "--dir", folder)
    assert r.returncode == 2 and "exists and is not empty" in r.stderr
    r = cdrb("export", tiny_models["mlp"].path, "--dir", tmp_path / "m", "--eval", folder.parent / "eval.h5")
    assert r.returncode == 2 and "evaluates another model" in r.stderr and not (tmp_path / "m").exists()
    shutil.copy(folder.parent / "eval.h5", tmp_path / "again.h5")  # the same eval under another name
    r = cdrb(
        "export", model, "--dir", tmp_path / "m", "--eval", folder.parent / "eval.h5", "--eval", tmp_path / "again.h5"
    )
    assert r.returncode == 2 and "the same eval as --eval" in r.stderr and not (tmp_path / "m").exists(), r.stderr
    r = cdrb("export", model, "--dir", tmp_path / "m")
    assert r.returncode == 0 and r.stdout.strip() == str(tmp_path / "m")
    assert "No evaluation was exported" in (tmp_path / "m" / "README.md").read_text()
    mask = os.umask(0)
    os.umask(mask)
    modes = {p.name: p.stat().st_mode & 0o777 for p in [tmp_path / "m", *(tmp_path / "m").iterdir()]}
    assert modes == {"m": 0o777 & ~mask, **{n: 0o666 & ~mask for n in modes if n != "m"}}, modes  # the umask's
    # --force replaces a model folder, never one holding other files: they would go with it
    (tmp_path / "m" / "mine.txt").write_text("old")
    r = cdrb("export", tiny_models["mlp"].path, "--dir", tmp_path / "m", "--force")
    assert r.returncode == 2 and "holds files a model folder does not (mine.txt)" in r.stderr, r.stderr
    assert (tmp_path / "m" / "mine.txt").read_text() == "old"
    # a model folder is replaced whole: the old one is set aside before the new one goes in, then removed
    (tmp_path / "m" / "mine.txt").unlink()
    r = cdrb("export", tiny_models["mlp"].path, "--dir", tmp_path / "m", "--force")
    assert r.returncode == 0 and "mlp" in (tmp_path / "m" / "README.md").read_text().split("\n")[0]
    assert sorted(p.name for p in tmp_path.iterdir() if p.name.startswith(".m.")) == []


def test_export_never_replaces_a_folder_holding_its_inputs_or_the_working_folder(tiny_models, tmp_path, cdrb):
    """--force replaces the folder whole, so a folder holding the model or an eval given, the working folder or one
    above it, a link, a path through a file and a name with a newline are refused first, with nothing removed."""
    import shutil

    runs = tmp_path / "runs"
    runs.mkdir()
    model = runs / "model.h5"
    shutil.copy(tiny_models["cdrb"].path, model)
    (runs / "notes.txt").write_text("mine")
    before = sorted(p.name for p in runs.iterdir())
    r = cdrb("export", model, "--dir", runs, "--force")
    assert r.returncode == 2 and "an input of this command" in r.stderr and r.stderr.count("\n") == 1, r.stderr
    assert sorted(p.name for p in runs.iterdir()) == before
    (tmp_path / "link").symlink_to(tmp_path / "elsewhere", target_is_directory=True)
    (tmp_path / "afile").write_text("")
    cases = {
        ".": "is the working folder or holds it",
        "..": "is the working folder or holds it",
        "link": "is a symbolic link",
        "afile/sub": "is not a folder",
        "nl\ndir": "a control character",
    }
    for folder, message in cases.items():
        r = cdrb("export", model, "--dir", folder, "--force", cwd=runs if folder in (".", "..") else tmp_path)
        assert r.returncode == 2 and message in r.stderr and r.stderr.count("\n") == 1, (folder, r.stderr)
    assert sorted(p.name for p in runs.iterdir()) == before
    r = cdrb("export", model, "--dir", tmp_path / "nodir" / "m")  # its folder must exist, as for every --out
    assert r.returncode == 2 and "does not exist" in r.stderr and r.stderr.count("\n") == 1, r.stderr
    r = cdrb("export", model, "--dir", "/proc/cdrb-m")  # a folder that takes no new file: said before any work
    assert r.returncode == 2 and "--dir /proc/cdrb-m: cannot write in /proc" in r.stderr, r.stderr
    assert sorted(p.name for p in tmp_path.iterdir()) == ["afile", "link", "runs"]


def test_replace_folder_keeps_one_whole_folder_at_every_step(tmp_path, monkeypatch):
    """A failed second rename puts the old folder back in its place; Ctrl-C between the two renames is answered
    after the second, so the folder is never left only under its aside name."""
    import signal

    from cdrb_cli import files, interrupts

    final, new = tmp_path / "out", tmp_path / ".out.new"
    final.mkdir()
    (final / "a").write_text("old")
    new.mkdir()
    (new / "a").write_text("new")
    real = os.replace
    calls = []

    def crash_on_second(src, dst):
        calls.append((src, dst))
        if len(calls) == 2:
            raise OSError("crash")
        return real(src, dst)

    monkeypatch.setattr(files.os, "replace", crash_on_second)
    with pytest.raises(OSError):
        files.replace_folder(new, final)
    assert (final / "a").read_text() == "old" and (new / "a").read_text() == "new"
    assert sorted(p.name for p in tmp_path.iterdir()) == [".out.new", "out"]

    def interrupt_on_first(src, dst):  # the signal arrives just after the old folder was moved aside
        real(src, dst)
        if os.path.basename(dst).startswith(".out.old-"):
            os.kill(os.getpid(), signal.SIGINT)

    monkeypatch.setattr(files.os, "replace", interrupt_on_first)
    # a suite started as a background job inherits SIGINT ignored, and install() leaves an ignored SIGINT alone
    outer = signal.signal(signal.SIGINT, signal.default_int_handler)
    restore = interrupts.install()
    try:
        with pytest.raises(KeyboardInterrupt):
            files.replace_folder(new, final)
    finally:
        restore()
        signal.signal(signal.SIGINT, outer)
    assert (final / "a").read_text() == "new" and sorted(p.name for p in tmp_path.iterdir()) == ["out"]
    monkeypatch.setattr(files.os, "replace", real)
    final2, new2 = tmp_path / "out2", tmp_path / ".out2.new"
    final2.mkdir()
    (final2 / "b").write_text("old")
    new2.mkdir()
    (new2 / "a").write_text("new")
    files.replace_folder(new2, final2)
    assert (final2 / "a").read_text() == "new" and not (final2 / "b").exists()
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".out2.old-")]


def test_a_compact_eval_drops_the_plans_and_reports_the_same(tiny_models, tmp_path, cdrb):
    """`cdrb export EVAL --compact FILE`: the eval without its plans, with what `cdrb report` measures on them kept
    per episode, so the report is the same (here with walls added at eval time, so the plans-through-a-new-wall
    column has figures); an eval written before evals stored those measures has them computed from its plans."""
    from cdrb_cli.stages.plan_metrics import FIRST_STEP, NEW_CROSSING, PLAN_STATES

    closed = ROOT / "experiments" / "maps" / "maze-tight-closed-north.txt"
    full, compact = tmp_path / "eval.h5", tmp_path / "kept" / "eval.h5"
    r = cdrb("eval", tiny_models["cdrb"].path, "--maze-map", closed, "--episodes", "6", "--seeds", "0,1", "--out", full)
    assert r.returncode == 0, r.stderr
    ev = artifacts.load(full, "eval")
    assert {FIRST_STEP, NEW_CROSSING, PLAN_STATES} <= set(ev.arrays) and "plans" in ev.arrays
    assert ev.arrays[NEW_CROSSING].any()  # untrained plans run through the added walls: the column is not empty
    compact.parent.mkdir()
    r = cdrb("export", full, "--compact", compact)
    assert r.returncode == 0 and r.stdout.strip() == str(compact)
    kept = artifacts.load(compact, "eval")
    assert "plans" not in kept.arrays and kept.manifest.config == ev.manifest.config
    assert compact.stat().st_size < full.stat().st_size

    def report(path):
        r = cdrb("report", path, "--format", "csv")
        assert r.returncode == 0, r.stderr
        return r.stdout.replace(str(path), "EVAL")

    assert report(compact) == report(full)
    r = cdrb("report", full, compact, "--per-seed")  # an eval and its compact copy: one evaluation, refused
    assert r.returncode == 2 and "the same eval twice (pass each eval once" in r.stderr, r.stderr
    again = tmp_path / "again.h5"  # the same model, settings and seeds evaluated again: another run, listed
    r = cdrb("eval", tiny_models["cdrb"].path, "--maze-map", closed, "--episodes", "6", "--seeds", "0,1", "--out",
             again)  # fmt: skip
    assert r.returncode == 0, r.stderr
    r = cdrb("report", full, again, "--per-seed", "--format", "csv")
    assert r.returncode == 0 and len(r.stdout.strip().splitlines()) == 5, r.stderr
    # an eval of an older schema (plans, no stored measures) gives the same compact eval's measures
    older = {name: a for name, a in ev.arrays.items() if name not in (FIRST_STEP, NEW_CROSSING, PLAN_STATES)}
    artifacts.save(tmp_path / "older.h5", "eval", ev.manifest, older)
    assert report(tmp_path / "older.h5") == report(full)
    r = cdrb("export", tmp_path / "older.h5", "--compact", tmp_path / "older-kept.h5")
    assert r.returncode == 0, r.stderr
    again = artifacts.load(tmp_path / "older-kept.h5", "eval")
    for name in (FIRST_STEP, NEW_CROSSING, PLAN_STATES):
        np.testing.assert_array_equal(again.arrays[name], ev.arrays[name])
    # one target at a time; an existing file kept unless forced; never the input itself
    r = cdrb("export", full, "--compact", tmp_path / "x.h5", "--dir", tmp_path / "d")
    assert r.returncode == 2 and "--compact FILE (an eval)" in r.stderr and not (tmp_path / "x.h5").exists()
    r = cdrb("export", full, "--compact", compact)
    assert r.returncode == 2 and "file exists" in r.stderr
    r = cdrb("export", full, "--compact", full, "--force")
    assert r.returncode == 2 and "is an input of this command" in r.stderr
    assert artifacts.load(full, "eval").arrays.keys() == ev.arrays.keys()
    # nothing to drop (a policy's eval, one without plans): kept as written, so a table's folder compacts in one loop
    r = cdrb("export", compact, "--compact", tmp_path / "twice.h5")
    assert r.returncode == 0 and "holds no plans" in r.stderr
    assert (tmp_path / "twice.h5").read_bytes() == compact.read_bytes()
    # a file that cannot be kept as it is: refused in one line, nothing written
    r = cdrb("export", ROOT / "tests" / "data" / "v1" / "eval.h5", "--compact", tmp_path / "v1.h5")
    assert r.returncode == 2 and "measured less" in r.stderr and not (tmp_path / "v1.h5").exists()
    r = cdrb("export", full, "--compact", tmp_path / "y.h5", "--eval", full)
    assert r.returncode == 2 and "goes with --dir" in r.stderr and not (tmp_path / "y.h5").exists()


def test_stored_plan_measures_are_checked_when_read(tmp_path):
    """Counts of planned states in an obstacle by body must come with the plans' lengths and lie within them."""
    from types import SimpleNamespace

    from cdrb_cli.artifacts.kinds import Eval

    manifest = SimpleNamespace(config=SimpleNamespace(seeds=[0], episodes=2))
    base = {"episodes/seed": np.array([0, 0]), "episodes/success": np.array([True, False])}
    good = {**base, "episodes/plan_states": np.array([5, 5]), "bodies/block/states_in_obstacle": np.array([0, 5])}
    assert Eval.check_data(manifest, good) is None
    for bad in (
        {**good, "bodies/block/states_in_obstacle": np.array([0, 6])},
        {**good, "bodies/block/states_in_obstacle": np.array([-1, 0])},
        {k: v for k, v in good.items() if k != "episodes/plan_states"},
        {**good, "episodes/plan_states": np.array([0, 5])},
        {**good, "bodies/block/crossing": np.array([True])},
    ):
        assert Eval.check_data(manifest, bad) is not None


def test_an_imported_model_trains_on_where_it_stopped(tiny_models, small_data, folder, tmp_path, cdrb):
    """A model brought back from its folder is a checkpoint like any other: `--resume` continues it (its
    optimizers' 0-d step counts came back 0-d)."""
    from cdrb_cli.methods.config import train_config
    from cdrb_cli.stages.train import train
    from tests.test_train import tiny

    demos, buffer = small_data
    assert cdrb("import", "model", folder, "--out", tmp_path / "back.h5").returncode == 0
    cfg = train_config(demos, buffer, "cdrb", tiny("cdrb", steps=40, checkpoint_every=30))
    longer = train(demos, buffer, cfg, tmp_path / "back.h5", resume=True)
    assert longer.manifest.state.step == 40 and longer.manifest.state.finished
