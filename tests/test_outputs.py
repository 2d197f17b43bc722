"""One rule for every output path: existing -> error unless
--force; never an input of the same run; only regular files are replaced; pictures and reports checked before
any work; one writer per output at a time; files honour the umask; temp files of a killed writer are cleaned."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import pytest

from cdrb_cli import artifacts
from cdrb_cli.errors import BadInput
from tests.factories import write


def test_outputs_that_are_not_regular_files_or_are_inputs(tmp_path, cdrb):
    demos = write(tmp_path / "d.h5", "demos")
    fifo = tmp_path / "fifo.h5"
    os.mkfifo(fifo)
    link = tmp_path / "link.h5"
    link.symlink_to(demos)
    cases = [
        (["cluster", demos, "--k", "2", "--out", fifo, "--force"], "is not a regular file"),
        (["cluster", demos, "--k", "2", "--out", "/dev/null", "--force"], "is not a regular file"),
        (["cluster", demos, "--k", "2", "--out", link, "--force"], "is a symbolic link"),
        (["cluster", demos, "--k", "2", "--out", demos, "--force"], "is an input of this command"),
    ]
    for args, needle in cases:
        r = cdrb(*args)
        assert r.returncode == 2 and needle in r.stderr and r.stderr.count("\n") == 1, (args, r.stderr)
    assert fifo.is_fifo() and link.is_symlink() and artifacts.load(demos).kind == "demos"


def test_report_out_follows_the_rule(tmp_path, cdrb):
    ev = write(tmp_path / "e.h5", "eval")
    before = ev.read_bytes()
    r = cdrb("report", ev, "--out", ev, "--force")
    assert r.returncode == 2 and "is an input" in r.stderr and ev.read_bytes() == before
    out = tmp_path / "r.md"
    out.write_text("mine")
    r = cdrb("report", ev, "--out", out)
    assert r.returncode == 2 and "--force" in r.stderr and out.read_text() == "mine"
    assert cdrb("report", ev, "--out", out, "--force").returncode == 0 and "Success rate" in out.read_text()


def test_pictures_are_checked_before_any_work(tmp_path, cdrb):
    out = tmp_path / "d.h5"
    for plot, needle in [
        (tmp_path / "d.txt", "unsupported file type"),
        (tmp_path / "nowhere" / "d.png", "does not exist"),
        (out, "the same file as --out"),
    ]:
        r = cdrb("collect", "maze-tight", "-n", "2", "--out", out, "--plot", plot)
        assert r.returncode == 2 and needle in r.stderr, r.stderr
        assert not out.exists()
    picture = tmp_path / "d.png"
    picture.write_bytes(b"mine")
    r = cdrb("collect", "maze-tight", "-n", "2", "--out", out, "--plot", picture)
    assert r.returncode == 2 and "--plot" in r.stderr and not out.exists() and picture.read_bytes() == b"mine"


@pytest.mark.skipif(shutil.which("chattr") is None, reason="needs chattr")
def test_an_unwritable_folder_is_found_before_any_work(tmp_path, cdrb):
    demos = write(tmp_path / "d.h5", "demos")
    folder = tmp_path / "frozen"
    folder.mkdir()
    if subprocess.run(["chattr", "+i", str(folder)], capture_output=True).returncode != 0:
        pytest.skip("the filesystem has no immutable attribute")
    try:
        r = cdrb("cluster", demos, "--k", "2", "--out", folder / "b.h5")
        assert r.returncode == 2 and "cannot write in" in r.stderr, r.stderr
    finally:
        subprocess.run(["chattr", "-i", str(folder)])


def test_artifacts_honour_the_umask(tmp_path):
    old = os.umask(0o022)
    try:
        path = write(tmp_path / "d.h5", "demos")
        assert path.stat().st_mode & 0o777 == 0o644
        os.umask(0o077)
        write(path, "demos", seed=3)
        assert path.stat().st_mode & 0o777 == 0o600
    finally:
        os.umask(old)


def test_two_runs_on_one_output_the_second_stops(small_data, tmp_path, cdrb):
    from tests.test_train import TINY_FLAGS

    demos, buffer = small_data
    out = tmp_path / "m.h5"
    args = ["train", demos.path, "--buffer", buffer.path, "--steps", "100000", *TINY_FLAGS, "--out", out]
    first = subprocess.Popen(
        [sys.executable, "-m", "cdrb_cli", "-q", *map(str, args)], stdout=subprocess.PIPE, stderr=subprocess.PIPE
    )
    try:
        deadline = time.time() + 60
        while not (tmp_path / ".m.h5.lock").exists() and time.time() < deadline:
            time.sleep(0.05)
        r = cdrb(*args)
        assert r.returncode == 2 and f"another cdrb run is writing it (pid {first.pid})" in r.stderr, r.stderr
    finally:
        first.kill()
        first.wait()
    # a killed writer's temp files are removed by the next writer of the same output
    stale = tmp_path / ".m.h5.tmp-stale123"  # the 8 random characters mkstemp gives
    stale.write_bytes(b"x" * 100)
    r = cdrb(*[a if a != "100000" else "3" for a in args], "--force")
    assert r.returncode == 0, r.stderr
    assert not stale.exists() and not (tmp_path / ".m.h5.lock").exists()


def test_report_docs_block_is_an_output_like_out(tmp_path, cdrb):
    """`report --docs FILE --block NAME` rewrites FILE in place: never an input of the run, never a binary file, and
    only the marked block changes."""
    ev = write(tmp_path / "e.h5", "eval")
    r = cdrb("report", ev, "--docs", ev, "--block", "t")
    assert r.returncode == 2 and "is an input of this command" in r.stderr
    binary = tmp_path / "b.md"
    binary.write_bytes(ev.read_bytes())
    r = cdrb("report", ev, "--docs", binary, "--block", "t")
    assert r.returncode == 2 and "not a text file" in r.stderr and binary.read_bytes() == ev.read_bytes()
    doc = tmp_path / "d.md"
    doc.write_text("head\n<!-- t:begin -->\nold\n<!-- t:end -->\ntail\n")
    r = cdrb("report", ev, "--docs", doc, "--block", "t")
    assert r.returncode == 0 and r.stdout.strip() == str(doc)
    text = doc.read_text()
    assert text.startswith("head\n<!-- t:begin -->\n| Success rate (%) |") and text.endswith("<!-- t:end -->\ntail\n")
    assert not [p for p in tmp_path.iterdir() if ".tmp-" in p.name or p.name.endswith(".lock")]
    # the file keeps its permissions; a read-only one is refused, not replaced
    doc.chmod(0o600)
    assert cdrb("report", ev, "--docs", doc, "--block", "t").returncode == 0 and doc.stat().st_mode & 0o777 == 0o600
    doc.chmod(0o444)
    before = doc.read_bytes()
    r = cdrb("report", ev, "--docs", doc, "--block", "t")
    assert r.returncode == 2 and "is read-only" in r.stderr and doc.read_bytes() == before
    r = cdrb("report", ev, "--docs", tmp_path, "--block", "t")
    assert r.returncode == 2 and "not a regular file" in r.stderr
    # markers that leave the block ambiguous: nothing is rewritten
    for bad in ("<!-- t:begin -->\na\n<!-- t:end -->\n<!-- t:begin -->\nb\n<!-- t:end -->\n",
                "<!-- t:begin -->\n<!-- t:begin -->\na\n<!-- t:end -->\n"):  # fmt: skip
        doc.chmod(0o644)
        doc.write_text(bad)
        r = cdrb("report", ev, "--docs", doc, "--block", "t")
        assert r.returncode == 2 and "ambiguous" in r.stderr and doc.read_text() == bad, r.stderr


def test_a_lock_file_that_is_a_hard_link_is_refused_and_its_target_kept(tmp_path):
    """A planted hard link as the lock file would have the writer's pid written into (and truncate) its target."""
    from cdrb_cli.artifacts.outputs import claim_output

    victim = tmp_path / "victim.txt"
    victim.write_text("precious\n")
    os.link(victim, tmp_path / ".o1.h5.lock")
    with pytest.raises(BadInput, match="is a hard link to another file"):
        with claim_output(tmp_path / "o1.h5", force=False):
            pass
    assert victim.read_text() == "precious\n" and not (tmp_path / "o1.h5").exists()


@pytest.mark.parametrize("name", ["model[1].h5", "*.h5", "m?.h5"])
def test_stale_temps_are_matched_literally(tmp_path, name):
    """Clean-up removes only the output's own temp files (its name taken literally, the random part mkstemp gives):
    another output's live temp file is never touched, whatever characters the name holds."""
    from cdrb_cli.artifacts.outputs import claim_output

    others = [tmp_path / n for n in (".model1.h5.tmp-abcd1234", ".x.h5.tmp-abcd1234", ".m1.h5.tmp-abcd1234")]
    longer = tmp_path / f".{name}.tmp-x.h5.tmp-abcd1234"  # a temp of an output whose name extends this one's
    own = tmp_path / f".{name}.tmp-abcd1234"
    for p in [*others, longer, own]:
        p.write_bytes(b"x")
    with claim_output(tmp_path / name, force=False):
        pass
    assert all(p.exists() for p in [*others, longer]) and not own.exists()


def test_select_docs_may_not_be_another_output(tmp_path, cdrb):
    notes = tmp_path / "notes.md"
    notes.write_text("my notes\n")
    for other in ("--out", "--table", "--curves"):
        args = ["--out", tmp_path / "s.toml"] if other != "--out" else []
        r = cdrb("select", tmp_path / "tune.toml", *args, other, notes, "--docs", notes, "--block", "x", "--force")
        assert r.returncode == 2 and "the same file as" in r.stderr, r.stderr
    assert notes.read_text() == "my notes\n"
    (tmp_path / "tune.toml").write_text(
        'out = "t"\nenvs = ["maze-tight"]\nmethods = ["mlp"]\nseeds = [0]\neval_stream = "tune"\n'
    )
    r = cdrb("select", tmp_path / "tune.toml", "--out", tmp_path / "s.json")
    assert r.returncode == 2 and "writes a TOML settings file" in r.stderr and not (tmp_path / "s.json").exists()


def test_an_output_may_not_overwrite_a_text_input(tiny_models, tmp_path, cdrb):
    """Every file a command reads is an input, whatever its kind: a scene, a settings file, a map, paper figures
    (pictures are refused by their suffix already)."""
    scene = tmp_path / "closed.txt"
    shutil.copy(Path(__file__).resolve().parents[1] / "experiments" / "maps" / "maze-tight-closed-north.txt", scene)
    before = scene.read_bytes()
    model = tiny_models["cdrb"].path
    attacks = [
        ("plan", model, "--start", "0,0", "--goal", "6,6", "--scene", scene, "--out", scene),
        ("eval", model, "-n", "1", "--seeds", "0", "--scene", scene, "--out", scene),
        ("collect", "--maze-map", scene, "-n", "2", "--out", scene),
    ]
    for args in attacks:
        r = cdrb(*args, "--force")
        assert r.returncode == 2 and "is an input of this command" in r.stderr, (args, r.stderr)
        assert scene.read_bytes() == before
    settings = tmp_path / "run.toml"
    settings.write_text("steps = 2\n")
    demos = tiny_models["cdrb"].manifest.parents[0].path
    r = cdrb("train", demos, "--method", "mlp", "--config", settings, "--out", settings, "--force")
    assert r.returncode == 2 and "is an input of this command" in r.stderr and settings.read_text() == "steps = 2\n"
    ev = write(tmp_path / "e.h5", "eval")
    figures = tmp_path / "figures.toml"
    figures.write_text("[maze]\n")
    for out in (["--out", figures], ["--docs", figures, "--block", "t"]):
        r = cdrb("report", ev, "--paper", "--paper-figures", figures, *out, "--force")
        assert r.returncode == 2 and "is an input of this command" in r.stderr, r.stderr
    assert figures.read_text() == "[maze]\n"
    from cdrb_cli import api

    with pytest.raises(BadInput, match="is an input"):
        api.evaluate(model, scene, episodes=1, scene=scene, force=True)
    assert scene.read_bytes() == before


def test_output_names_too_long_or_with_control_characters_are_one_line(tmp_path, cdrb):
    """A name the file system cannot take once the temp file's marks are added, or one with a newline (stdout
    prints the path written, one per line), is refused before any work; a picture flag's folder hint names a
    picture."""
    from cdrb_cli.artifacts import check_output

    for name in ("a" * 250 + ".h5", "a\nb.h5", "tab\there.h5", "bell\x07.h5"):
        with pytest.raises(BadInput) as err:
            check_output(tmp_path / name, False)
        assert str(err.value).count("\n") == 0 and ("bytes" in str(err.value) or "control" in str(err.value))
    check_output(tmp_path / ("a" * 197 + ".h5"), False)  # 200 bytes: taken
    for text in (f"{tmp_path}/x.h5/", f"{tmp_path}/x.h5/.", "."):  # Path() would drop the slash and write x.h5
        with pytest.raises(BadInput, match="names a folder"):
            check_output(text, False)
    (tmp_path / "d.png").mkdir()
    with pytest.raises(BadInput, match="such as plot.png"):
        check_output(tmp_path / "d.png", True, "--plot", suffixes=(".png",))
    r = cdrb("collect", "maze-tight", "-n", "1", "--out", tmp_path / ("b" * 240 + ".h5"))
    assert r.returncode == 2 and "--out" in r.stderr and r.stderr.count("\n") == 1, r.stderr
    assert not [p for p in tmp_path.iterdir() if p.name.startswith("b")]
    r = cdrb("collect", "maze-tight", "-n", "1", "--out", f"{tmp_path}/c.h5/")
    assert r.returncode == 2 and "names a folder" in r.stderr and r.stderr.count("\n") == 1, r.stderr
    assert not (tmp_path / "c.h5").exists()
    ev = write(tmp_path / "ev.h5", "eval")
    r = cdrb("export", ev, "--compact", f"{tmp_path}/e.h5/")
    assert r.returncode == 2 and "names a folder" in r.stderr and r.stderr.count("\n") == 1, r.stderr
    assert not (tmp_path / "e.h5").exists()
    # '-', stdout's usual spelling, would be a file named '-' in the current folder
    r = cdrb("report", ev, "--out", "-", cwd=tmp_path)
    assert r.returncode == 2 and "'-' would be a file named '-'" in r.stderr and r.stderr.count("\n") == 1, r.stderr
    assert not (tmp_path / "-").exists()


def test_a_failed_run_leaves_no_empty_folders_it_made(tmp_path):
    """new_folder (GIF folders, Minari namespaces): interrupted, the folders it made and left empty go; a folder
    that existed, or one holding a file, stays; a block that ends well keeps its folder."""
    from cdrb_cli.files import new_folder

    (tmp_path / "had").mkdir()
    with pytest.raises(KeyboardInterrupt), new_folder(tmp_path / "had" / "a" / "b"):
        raise KeyboardInterrupt
    assert list((tmp_path / "had").iterdir()) == []
    with pytest.raises(OSError), new_folder(tmp_path / "c" / "d") as folder:
        (folder.parent / "kept.txt").write_text("x")
        raise OSError("disk full")
    assert sorted(p.name for p in (tmp_path / "c").iterdir()) == ["kept.txt"]
    with new_folder(tmp_path / "e") as folder:
        pass
    assert folder.is_dir()


def test_an_output_path_past_the_systems_limit_is_one_line(tmp_path):
    """A path longer than the system allows makes stat itself fail (ENAMETOOLONG): a one-line refusal with the path
    clipped, not an OSError traceback."""
    from cdrb_cli.artifacts.outputs import check_output

    deep = tmp_path
    for _ in range(os.pathconf(tmp_path, "PC_PATH_MAX") // 200 + 1):
        deep = deep / ("d" * 200)
    with pytest.raises(BadInput, match="choose a shorter path") as caught:
        check_output(deep / "r.md", False, "--out")
    assert len(str(caught.value)) < 200


def test_a_probe_file_an_interrupted_run_left_behind_does_not_block_an_output(tmp_path):
    """The writability probe takes a fresh name each time: a leftover probe (an interrupt between its creation and
    its removal) under any name a later process might pick does not read as an unwritable folder."""
    from cdrb_cli.artifacts import check_output

    for pid in range(os.getpid() - 5, os.getpid() + 5):
        (tmp_path / f".cdrb-probe-{pid}").write_bytes(b"")
    check_output(tmp_path / "p.h5", False, "--out")
    assert sorted(p.name for p in tmp_path.iterdir() if not p.name.startswith(".cdrb-probe-")) == []
    assert len(list(tmp_path.iterdir())) == 10  # its own probe removed


def test_a_reader_that_stops_reading_is_not_a_failed_run(tiny_models, tmp_path):
    """`cdrb inspect F | head -1`: stdout's reader goes away before the command writes. The command ends quietly
    with 141 (128 + SIGPIPE, as a Unix tool stopped by it), not 1 (a failed run), for a plain result line and for
    rich's output alike; what it made is written."""
    model = tiny_models["mlp"].path
    for args in (["inspect", model], ["plan", model, "--pairs", "2", "--out", tmp_path / "p.h5"]):
        proc = subprocess.Popen(
            [sys.executable, "-m", "cdrb_cli", *map(str, args)], stdout=subprocess.PIPE, stderr=subprocess.PIPE
        )
        proc.stdout.close()  # before the command has imported anything, let alone written
        err = proc.stderr.read().decode()
        assert proc.wait(timeout=300) == 141, err
        assert "Traceback" not in err and "error" not in err and "Exception ignored" not in err, err
    assert artifacts.load(tmp_path / "p.h5", "plans").plans.shape[0] == 2


def test_columns_zero_in_the_environment_still_shows_the_log(tiny_models, tmp_path):
    """COLUMNS=0 (a terminal that reports no width) made rich print nothing: every log line and warning vanished."""
    from tests.conftest import run_cdrb

    r = run_cdrb("plan", tiny_models["mlp"].path, "--pairs", "1", "--out", tmp_path / "p.h5", env={"COLUMNS": "0"})
    assert r.returncode == 0 and "plans for 1 pairs" in r.stderr, r.stderr


def test_a_command_blocked_by_an_output_leaves_its_failure_as_data(tmp_path, cdrb):
    """With CDRB_ERROR_FILE set, a refused command writes its error's parts there; an output that blocks it is
    named as data (what a grid acts on), any other failure says none."""
    import json

    demos = write(tmp_path / "d.h5", "demos")
    taken = tmp_path / "b.h5"
    taken.write_text("my notes\n")
    record = tmp_path / "error.json"
    r = cdrb("cluster", demos, "--k", "2", "--out", taken, env={"CDRB_ERROR_FILE": str(record)})
    got = json.loads(record.read_text())
    assert r.returncode == 2 and got["exit_code"] == 2 and got["output_exists"] == str(taken)
    assert r.stderr.strip() == f"error: {got['message']} ({got['hint']})" and "--force" in got["hint"]
    record.unlink()
    r = cdrb(
        "cluster", tmp_path / "absent.h5", "--k", "2", "--out", tmp_path / "c.h5", env={"CDRB_ERROR_FILE": str(record)}
    )
    got = json.loads(record.read_text())
    assert r.returncode == 2 and got["output_exists"] is None and got["message"] in r.stderr
    assert taken.read_text() == "my notes\n" and not list(tmp_path.glob("error.json.*"))


def test_the_error_file_is_never_a_way_to_overwrite_a_file_and_covers_every_failure(tmp_path, cdrb):
    """CDRB_ERROR_FILE names where a record goes, not a file to clobber: a file of the user's, a link or a device
    is left as it is (a warning says so); a usage error and a run's own failure leave their record too."""
    import json

    demos = write(tmp_path / "d.h5", "demos")
    mine, target = tmp_path / "notes.txt", tmp_path / "target.txt"
    mine.write_text("my notes\n")
    target.write_text("kept\n")
    link = tmp_path / "link.json"
    os.symlink(target, link)
    for path in (mine, link, demos):
        before = Path(path).read_bytes()
        r = cdrb("cluster", tmp_path / "absent.h5", "--out", tmp_path / "c.h5", env={"CDRB_ERROR_FILE": str(path)})
        assert r.returncode == 2 and "not written, it is not an error record" in r.stderr, r.stderr
        assert Path(path).read_bytes() == before and os.path.islink(link) and target.read_text() == "kept\n"
    record = tmp_path / "error.json"
    r = cdrb("cluster", demos, "--no-such-flag", env={"CDRB_ERROR_FILE": str(record)})  # a usage error
    got = json.loads(record.read_text())
    assert r.returncode == 2 and got["exit_code"] == 2 and "--no-such-flag" in got["message"]
    assert "--help" in got["hint"]
    # an earlier record is written over by the next failure
    r = cdrb("cluster", tmp_path / "absent.h5", "--out", tmp_path / "c.h5", env={"CDRB_ERROR_FILE": str(record)})
    assert r.returncode == 2 and "absent.h5" in json.loads(record.read_text())["message"], r.stderr


def test_a_huge_columns_is_bounded(tmp_path):
    """COLUMNS=20000000 once made a help page take half a minute and gigabytes: it is read as at most 1000."""
    from tests.conftest import run_cdrb

    r = run_cdrb("train", "--help", env={"COLUMNS": "20000000"})
    assert r.returncode == 0 and "--config" in r.stdout, r.stderr
    assert max(len(line) for line in r.stdout.splitlines()) <= 1000


def test_check_can_make_finds_the_nearest_existing_folder(tmp_path):
    from cdrb_cli.artifacts.outputs import check_can_make

    assert check_can_make(tmp_path / "a" / "b" / "c", "--x") == tmp_path
    (tmp_path / "a").mkdir()
    assert check_can_make(tmp_path / "a" / "b", "--x") == tmp_path / "a"
    assert check_can_make(tmp_path / "a", "--x") == tmp_path / "a"
    (tmp_path / "f").write_text("x")
    with pytest.raises(BadInput, match=r"--x shown: .*/f is not a folder"):
        check_can_make(tmp_path / "f" / "sub", "--x", shown="shown")
    assert (tmp_path / "f").read_text() == "x" and sorted(p.name for p in tmp_path.iterdir()) == ["a", "f"]


def test_writes_inside_together_land_at_its_end_or_not_at_all(tmp_path):
    from cdrb_cli.files import atomic_path, together

    a, b = tmp_path / "a.txt", tmp_path / "b.txt"
    a.write_text("old")
    with together():
        with atomic_path(a) as tmp:
            tmp.write_text("new")
        with together(), atomic_path(b) as tmp:  # a nested block is the outer one
            tmp.write_text("b")
        assert a.read_text() == "old" and not b.exists()
    assert a.read_text() == "new" and b.read_text() == "b"
    with pytest.raises(RuntimeError), together():
        with atomic_path(a) as tmp:
            tmp.write_text("newer")
        raise RuntimeError("a later output failed")
    assert a.read_text() == "new" and sorted(p.name for p in tmp_path.iterdir()) == ["a.txt", "b.txt"]
    with atomic_path(a) as tmp:  # outside a block: at once
        tmp.write_text("now")
    assert a.read_text() == "now"
