"""Hostile inputs that reached a traceback, an exit 1, a wrong flag name, a broken file or a silent result: maps
beyond the layout's bounds, TOML nested thousands deep, scene files with odd names, block names that break their
markers, CRLF docs files, guidance that throws plans out of the scene, and SIGTERM to a grid on Ray."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time

import numpy as np
import pytest

from cdrb_cli.errors import BadInput
from tests.factories import write


def _one_line(r: subprocess.CompletedProcess) -> str:
    lines = r.stderr.strip().splitlines()
    assert r.returncode == 2 and len(lines) == 1, (r.returncode, r.stderr[-2000:])
    assert "Traceback" not in r.stderr and "ValidationError" not in r.stderr and "RecursionError" not in r.stderr
    return lines[0]


def _map(rows: int, cols: int) -> str:
    """A map of ``rows`` x ``cols`` cells, walls around, a start and a goal inside."""
    inner = ["#" + "." * (cols - 2) + "#" for _ in range(rows - 2)]
    inner[0] = "#S" + "." * (cols - 4) + "G#"
    return "\n".join(["#" * cols, *inner, "#" * cols]) + "\n"


# ------------------------------------------------------------------------------------------------ maze maps
def test_maps_beyond_the_layout_bounds_are_one_line_naming_the_file(tmp_path, cdrb):
    """More than 100 rows, more than 100 cells per row, or a name (the file's stem) over 200 characters: one line
    naming the file, the limit and the fix, never the layout record's validation error."""
    from cdrb_cli.envs.pointmaze.maze import load_map_file

    tall, wide = tmp_path / "tall.txt", tmp_path / "wide.txt"
    tall.write_text(_map(103, 5))
    wide.write_text(_map(5, 150))
    long = tmp_path / ("a" * 201 + ".txt")
    long.write_text(_map(5, 5))
    cases = {tall: ("too tall", "103 rows, more than 100"), wide: ("too wide", "150 cells per row, more than 100")}
    cases[long] = ("201 characters, more than 200", "rename the file")
    for path, words in cases.items():
        with pytest.raises(BadInput) as err:
            load_map_file(path)
        assert str(path) in str(err.value) and all(w in str(err.value) for w in words), str(err.value)
        assert "same length" not in str(err.value)
        line = _one_line(cdrb("collect", "--maze-map", path, "-n", "2", "--out", tmp_path / "d.h5"))
        assert str(path) in line and all(w in line for w in words), line
    assert not (tmp_path / "d.h5").exists()
    # the bounds themselves are fine
    edge = tmp_path / "edge.txt"
    edge.write_text(_map(100, 100))
    assert load_map_file(edge).n_cols == 100


# ------------------------------------------------------------------------------------------------ deep TOML
def test_a_number_of_thousands_of_digits_is_one_line_in_every_reader(tmp_path, cdrb):
    """Python's int() refuses numbers of more than 4300 digits with a ValueError: each TOML reader (settings, scene,
    grid and figures files, `grid --set`) and each integer-list flag says so in one line naming the flag or file."""
    from cdrb_cli.cli.common import int_values
    from cdrb_cli.envs.fetch.scenes import load_scene_change
    from cdrb_cli.orchestration.grid.load import parse_override
    from cdrb_cli.settings import read_config_file
    from cdrb_cli.stages.report import paper_figures

    big = "9" * 5000
    path = tmp_path / "big.toml"
    path.write_text(f"n = {big}\n")
    for read, flag in [(read_config_file, "--config"), (load_scene_change, "--scene"), (paper_figures, "--paper")]:
        with pytest.raises(BadInput, match=f"{flag}.* {path}: holds an integer of more than 4300 digits"):
            read(path)
    with pytest.raises(BadInput, match="--set n=9+...: .*a number too long"):
        parse_override(f"n={big}")
    with pytest.raises(BadInput, match="a number of more than 20 digits") as info:
        int_values(big, "--seeds", "integers", "0,1")
    assert len(str(info.value)) < 300
    grid = tmp_path / "grid.toml"
    grid.write_text(f'out = "runs"\nenvs = ["maze-tight"]\nmethods = ["mlp"]\nseeds = [0]\nsteps = {big}\n')
    line = _one_line(cdrb("grid", grid, "--dry-run"))
    assert line.startswith(f"error: {grid}: holds an integer of more than")


def test_a_byte_order_mark_does_not_change_a_toml_file(tmp_path):
    """Some editors start a UTF-8 file with a byte-order mark; a map file reads the same with one, and so does
    every TOML file (tomllib itself refuses it)."""
    from cdrb_cli.envs.fetch.scenes import load_scene_change

    text = "[[boxes]]\ncenter = [1.455, 0.749, 0.47]\nhalf = [0.005, 0.125, 0.30]\n"
    plain, marked = tmp_path / "closed.toml", tmp_path / "marked" / "closed.toml"
    marked.parent.mkdir()
    plain.write_text(text)
    marked.write_text("\ufeff" + text)
    assert load_scene_change(marked) == load_scene_change(plain)


def test_toml_nested_thousands_deep_is_one_line(tmp_path, cdrb):
    """`report --paper-figures`, `grid --set` and Fetch `--scene` files parse TOML recursively: a value nested
    3000 deep is one line naming the flag, not a RecursionError."""
    from cdrb_cli.orchestration.grid.load import parse_override
    from cdrb_cli.stages.report import paper_figures

    arrays, tables = tmp_path / "deep.toml", tmp_path / "deep2.toml"
    arrays.write_text("x = " + "[" * 3000 + "]" * 3000 + "\n")
    tables.write_text("a = " + "{b = " * 3000 + "1" + "}" * 3000 + "\n")
    for path in (arrays, tables):
        with pytest.raises(BadInput, match="--paper-figures .*nested too deep"):
            paper_figures(path)
    ev = write(tmp_path / "ev.h5", "eval")
    line = _one_line(cdrb("report", ev, "--paper", "--paper-figures", arrays))
    assert line.startswith(f"error: --paper-figures {arrays}")

    from cdrb_cli.envs.fetch.scenes import load_scene_change

    for path in (arrays, tables):  # a Fetch scene file, parsed the same way
        with pytest.raises(BadInput, match="--scene .*nested too deep"):
            load_scene_change(path)

    deep = "seeds=" + "[" * 3000 + "]" * 3000
    with pytest.raises(BadInput, match="--set seeds=.*too deep"):
        parse_override(deep)
    assert parse_override("seeds=[0, 1]") == ("seeds", [0, 1])
    assert parse_override("name=not toml") == ("name", "not toml")
    grid = tmp_path / "grid.toml"
    grid.write_text('out = "runs"\nenvs = ["maze-tight"]\nmethods = ["mlp"]\nseeds = [0]\n')
    line = _one_line(cdrb("grid", grid, "--dry-run", "--set", deep))
    assert line.startswith("error: --set seeds=") and len(line) < 400


# ------------------------------------------------------------------------------------------------ --scene
def test_scene_errors_name_the_flag_as_typed(tiny_models, tmp_path, cdrb):
    """plan and eval take the scene as --scene or --maze-map: an error names the one the user typed."""
    model = tiny_models["cdrb"].path
    fifo = tmp_path / "fifo.txt"
    os.mkfifo(fifo)
    small = tmp_path / "small.txt"
    small.write_text(_map(5, 5))
    for flag in ("--scene", "--maze-map"):
        for path, words in ((fifo, "not a regular file"), (small, "a 5x5 map, but the model was trained in")):
            for command in ("eval", "plan"):
                args = ["-n", "1", "--seeds", "0"] if command == "eval" else ["--pairs", "1"]
                line = _one_line(cdrb(command, model, flag, path, *args, "--out", tmp_path / "o.h5"))
                assert line.startswith(f"error: {flag} {path}:") and words in line, (command, line)
        line = _one_line(cdrb("eval", model, f"{flag}={small}", "-n", "1", "--out", tmp_path / "o.h5"))
        assert line.startswith(f"error: {flag} {small}:"), line
    assert not (tmp_path / "o.h5").exists()


# ------------------------------------------------------------------------------------------------ Fetch scenes
def test_a_scene_file_named_with_a_leading_dot_gets_a_valid_name(tmp_path):
    """A scene without ``name`` is named after its file: characters a name may not start with are dropped; a file
    name with nothing left is one line about the file name, not about a ``name`` the user never wrote."""
    from cdrb_cli.envs.fetch.scenes import load_scene_change

    boxes = "[[boxes]]\ncenter = [1.455, 0.749, 0.47]\nhalf = [0.005, 0.125, 0.30]\n"
    for stem, name in ((".x", "x"), ("_-.closed x", "closed-x"), ("ok", "ok")):
        (tmp_path / f"{stem}.toml").write_text(boxes)
        assert load_scene_change(tmp_path / f"{stem}.toml").name == name
    bad = tmp_path / "._-.toml"
    bad.write_text(boxes)
    with pytest.raises(BadInput) as err:
        load_scene_change(bad)
    assert "._-.toml" in str(err.value) and "rename the file" in str(err.value) and "pattern" not in str(err.value)
    bad.write_text('name = "given"\n' + boxes)  # a name in the file is the fix
    assert load_scene_change(bad).name == "given"


# ------------------------------------------------------------------------------------------------ --docs blocks
def test_block_names_that_break_the_markers_are_refused(tmp_path, cdrb):
    """`report --docs F --block NAME` and `select --docs F --block NAME`: an empty or blank name, or one with
    characters that end or break the HTML comment, is one line naming --block, and the file is untouched."""
    ev = write(tmp_path / "ev.h5", "eval")
    doc = tmp_path / "doc.md"
    doc.write_text("a\n<!-- :begin -->\nold\n<!-- :end -->\n")
    before = doc.read_bytes()
    grid = tmp_path / "grid.toml"
    grid.write_text('out = "runs"\nenvs = ["maze-tight"]\nmethods = ["mlp"]\nseeds = [0]\n')
    names = ("", " ", "\t", "a b", "a-->", "x--y", "a\nb", "<b>", "-a", "a" * 65)
    for name in names:
        line = _one_line(cdrb("report", ev, "--docs", doc, "--block", name))
        assert line.startswith("error: --block "), line
        line = _one_line(cdrb("select", grid, "--out", tmp_path / "s.toml", "--docs", doc, "--block", name))
        assert line.startswith("error: --block "), line
    assert doc.read_bytes() == before

    from cdrb_cli.stages.docs_blocks import check_block_name

    for name in names:
        with pytest.raises(BadInput, match="--block"):
            check_block_name(name)
    for name in ("table1-mazes", "T", "a.b_c-1"):
        check_block_name(name)


def test_a_crlf_docs_file_stays_crlf(tmp_path, cdrb):
    """`report --docs` into a file with CRLF line endings writes the whole file with CRLF, the new block too."""
    ev = write(tmp_path / "ev.h5", "eval")
    doc = tmp_path / "doc.md"
    doc.write_bytes(b"intro\r\n<!-- T:begin -->\r\nold\r\n<!-- T:end -->\r\nend\r\n")
    r = cdrb("report", ev, "--docs", doc, "--block", "T")
    assert r.returncode == 0, r.stderr
    data = doc.read_bytes()
    assert b"old" not in data and b"| cdrb |" in data
    assert data.count(b"\n") == data.count(b"\r\n") > 5 and data.startswith(b"intro\r\n<!-- T:begin -->\r\n")
    # a file with LF endings keeps them
    doc.write_bytes(b"intro\n<!-- T:begin -->\nold\n<!-- T:end -->\n")
    assert cdrb("report", ev, "--docs", doc, "--block", "T").returncode == 0
    assert b"\r" not in doc.read_bytes()
    # mixed endings: the text around the block is kept byte for byte, the block takes the file's main ending
    head, tail = b"a\r\nb\n<!-- T:begin -->\n", b"\n<!-- T:end -->\r\nc\rd\n"
    doc.write_bytes(head + b"old" + tail)
    assert cdrb("report", ev, "--docs", doc, "--block", "T").returncode == 0
    data = doc.read_bytes()
    assert data.startswith(b"a\r\nb\n<!-- T:begin -->") and data.endswith(b"<!-- T:end -->\r\nc\rd\n"), data


def test_a_docs_block_never_deletes_another_blocks_marker(tmp_path, cdrb):
    """Blocks that nest or overlap: replacing one would delete the other's marker, so the file is left as it is."""
    ev = write(tmp_path / "ev.h5", "eval")
    doc = tmp_path / "doc.md"
    for text in (
        "<!-- T:begin -->\nx\n<!-- U:begin -->\ny\n<!-- T:end -->\nz\n<!-- U:end -->\n",  # overlapping
        "<!-- T:begin -->\nx\n<!-- U:begin -->\ny\n<!-- U:end -->\n<!-- T:end -->\n",  # nested
    ):
        doc.write_text(text)
        r = cdrb("report", ev, "--docs", doc, "--block", "T")
        assert r.returncode == 2 and "holds another block's marker (<!-- U:begin -->)" in r.stderr, r.stderr
        assert doc.read_text() == text


# ------------------------------------------------------------------------------------------------ guidance
def test_plans_thrown_out_of_the_scene_are_warned_about(tiny_models, tmp_path, cdrb):
    """avoid.guide_scale near its bound moves plans kilometres away: plan and eval say so in one warning line
    (plans inside the scene, however long their steps, are not warned about)."""
    model = tiny_models["diffuser"].path
    words = "farther in one planned step than the scene is across"
    guided = ["--set", "avoid.guide_scale=1e6"]
    for command, args in (("eval", ["-n", "2", "--seeds", "0"]), ("plan", ["--pairs", "2"])):
        r = cdrb(command, model, *args, *guided, "--out", tmp_path / f"{command}.h5")
        assert r.returncode == 0, r.stderr
        warned = [ln for ln in r.stderr.splitlines() if words in ln]
        assert len(warned) == 1 and warned[0].startswith("warning: ") and "avoid.guide_scale=1e+06" in warned[0]
        assert not any("the first planned step" in ln for ln in r.stderr.splitlines())  # one warning, the cause
        r = cdrb(command, model, *args, "--out", tmp_path / f"{command}-plain.h5")
        assert r.returncode == 0 and words not in r.stderr, r.stderr

    from cdrb_cli.envs.registry import make_spec
    from cdrb_cli.stages.plan_warnings import off_scene_warning

    spec = make_spec("maze-tight")
    assert off_scene_warning(spec, np.array([1.0, 20.0, np.nan]), 2) is None  # the map is 21.2 m across
    line = off_scene_warning(spec, np.array([1.0, 5e4]), 2)
    assert line.startswith("1 of 2 plans jump farther") and "\n" not in line


# ------------------------------------------------------------------------------------------------ Ray
def test_sigterm_stops_a_grid_on_ray_with_exit_130_and_one_line(tmp_path):
    """ray.init puts its own SIGTERM handler in place of cdrb's (exit 15 and a C++ stack dump): the grid puts
    cdrb's back, so SIGTERM stops a grid on Ray as on the pool, exit 130 and one line, its tasks stopped. The
    grid starts a Ray of its own (never one already running on the machine)."""
    pytest.importorskip("ray")
    from tests.test_grid import TINY, _train_pids

    text = TINY.replace('methods = ["mlp", "cdrb"]', 'methods = ["mlp"]').replace("seeds = [0, 1]", "seeds = [0]")
    grid = tmp_path / "grid.toml"
    grid.write_text(text.replace("steps = 20", "steps = 100000"))
    env = {k: v for k, v in os.environ.items() if k != "RAY_ADDRESS"}
    proc = subprocess.Popen(
        [sys.executable, "-m", "cdrb_cli", "grid", str(grid), "--backend", "ray", "-j", "1"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=dict(env, OMP_NUM_THREADS="1"),
    )  # fmt: skip
    out = tmp_path / "runs"
    try:
        deadline = time.time() + 300
        while not _train_pids(out) and time.time() < deadline and proc.poll() is None:
            time.sleep(0.2)
        assert _train_pids(out), "the training never started"
        time.sleep(3)
        proc.send_signal(signal.SIGTERM)
        t = time.time()
        _, stderr = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    assert proc.returncode == 130, stderr[-3000:]
    assert time.time() - t < 30
    assert "Traceback" not in stderr and "SIGTERM" not in stderr and "*** " not in stderr, stderr[-3000:]
    assert "Started a local Ray instance" not in stderr, stderr[-3000:]  # Ray's notices stay off the progress
    errors = [ln for ln in stderr.splitlines() if ln.startswith("error:")]
    assert errors == [stderr.strip().splitlines()[-1]] and errors[0].startswith("error: interrupted"), stderr
    while _train_pids(out) and time.time() - t < 30:
        time.sleep(0.2)
    assert not _train_pids(out)


@pytest.mark.parametrize(
    "name, value",
    [
        ("OMP_NUM_THREADS", "99999"),  # OpenMP itself crashes (SIGSEGV) on such a count in scikit-learn's k-means
        ("OMP_NUM_THREADS", "abc"),
        ("OMP_NUM_THREADS", "0"),
        ("CDRB_PROGRESS_SECONDS", "abc"),
        ("CDRB_PROGRESS_SECONDS", "-1"),
        ("CDRB_MAX_ARTIFACT_BYTES", "-1"),
        ("CDRB_MAX_ARTIFACT_BYTES", "1e9"),
        ("CDRB_READ_TIMEOUT", "inf"),
        ("CDRB_MAX_ARTIFACT_BYTES", "9" * 30),  # beyond any C library's integer
        ("MUJOCO_GL", "bogus"),  # MuJoCo's import raises a bare RuntimeError on it
    ],
)
def test_bad_numbers_in_the_environment_are_one_line_before_any_work(small_data, tmp_path, cdrb, name, value):
    demos, _ = small_data
    out = tmp_path / "b.h5"
    r = cdrb("cluster", demos.path, "--k", "5", "--out", out, env={name: value})
    assert r.returncode == 2 and r.stderr.startswith(f"error: {name}={value!r}"[:30]), r.stderr
    assert r.stderr.count("\n") == 1 and not list(tmp_path.iterdir())


def test_good_numbers_in_the_environment_are_taken(small_data, tmp_path, cdrb):
    demos, _ = small_data
    env = {"OMP_NUM_THREADS": "1", "CDRB_PROGRESS_SECONDS": "0", "CDRB_READ_TIMEOUT": "5"}
    r = cdrb("cluster", demos.path, "--k", "5", "--out", tmp_path / "b.h5", env=env)
    assert r.returncode == 0, r.stderr
    r = cdrb("inspect", tmp_path / "b.h5", env={"CDRB_MAX_ARTIFACT_BYTES": "64"})  # its arrays declare more
    assert r.returncode == 2 and "more than CDRB_MAX_ARTIFACT_BYTES=64" in r.stderr, r.stderr
    assert "corrupt" not in r.stderr, r.stderr  # the file is sound; the variable is what refuses it


def test_a_rendering_backend_whose_library_is_absent_is_one_line(monkeypatch):
    """MUJOCO_GL=osmesa without libOSMesa makes MuJoCo's import fail (an AttributeError from PyOpenGL): refused,
    naming the variable and the library; MuJoCo's own spellings are taken as it takes them."""
    import ctypes.util

    from cdrb_cli import envvars

    monkeypatch.setattr(ctypes.util, "find_library", lambda name: None)
    monkeypatch.setenv("MUJOCO_GL", "osmesa")
    with pytest.raises(BadInput, match="MUJOCO_GL=osmesa: the OSMesa library is not installed"):
        envvars.mujoco_gl()
    for value in ("EGL ", "disable", "glfw", ""):
        monkeypatch.setattr(ctypes.util, "find_library", lambda name: f"lib{name}.so")
        monkeypatch.setenv("MUJOCO_GL", value)
        assert envvars.mujoco_gl() == value.lower().strip()
    monkeypatch.delenv("MUJOCO_GL")
    assert envvars.mujoco_gl() is None


@pytest.mark.parametrize("methods", ["", ",", " , "])
def test_quickstart_refuses_an_empty_method_list(tmp_path, cdrb, methods):
    """An empty --methods is a mistake (a shell variable that was never set), not a request for the default
    methods' several-minute run."""
    r = cdrb("quickstart", "--methods", methods, "--out", tmp_path / "qs")
    assert r.returncode == 2 and "--methods" in r.stderr and not (tmp_path / "qs").exists(), r.stderr


def test_an_eval_of_a_hundred_million_episodes_is_refused(tiny_models, tmp_path, cdrb):
    seeds = ",".join(map(str, range(1000)))
    r = cdrb("eval", tiny_models["mlp"].path, "-n", "100000", "--seeds", seeds, "--out", tmp_path / "e.h5")
    assert r.returncode == 2 and "100,000,000 episodes: more than the 1,000,000 one eval runs" in r.stderr, r.stderr
    assert not (tmp_path / "e.h5").exists()


def test_videos_without_video_is_refused_not_ignored(tiny_models, tmp_path, cdrb):
    for args in (["collect", "maze-tight", "-n", "3", "--videos", "2"],
                 ["eval", tiny_models["mlp"].path, "-n", "1", "--seeds", "0", "--videos", "5"]):  # fmt: skip
        r = cdrb(*args, "--out", tmp_path / "x.h5")
        assert r.returncode == 2 and "goes with --video DIR" in r.stderr and not (tmp_path / "x.h5").exists()


def test_quickstart_refuses_a_bad_env_or_k_before_writing_anything(tmp_path, cdrb):
    for args, needle in ((["--env", "nope"], "--env nope: unknown environment"),
                         (["--k", "100000000", "--episodes", "2"], "--k 100000000: more than the")):  # fmt: skip
        r = cdrb("quickstart", *args, "--out", tmp_path / "qs")
        assert r.returncode == 2 and needle in r.stderr and "--maze-map" not in r.stderr, r.stderr
        assert not (tmp_path / "qs").exists()


@pytest.mark.skipif(not os.path.exists("/dev/full"), reason="needs /dev/full")
def test_stdout_that_cannot_be_written_is_one_line(small_data):
    """Output sent to a full device: the error says stdout is what failed, not a bare OSError."""
    demos, _ = small_data
    for args in (["inspect", str(demos.path)], ["inspect", str(demos.path), "--json"], ["config", "train"]):
        with open("/dev/full", "w") as full:
            r = subprocess.run(
                [sys.executable, "-m", "cdrb_cli", *args], stdout=full, stderr=subprocess.PIPE, text=True, timeout=120
            )
        assert r.returncode == 1 and r.stderr.startswith("error: cannot write the output to stdout"), r.stderr
        assert r.stderr.count("\n") == 1, r.stderr


def test_an_empty_path_option_is_refused_not_read_as_the_current_folder(small_data, tmp_path, cdrb):
    """``Path("")`` is ".": an unset shell variable in ``--video "$DIR"`` would write GIFs into the current folder."""
    demos, _ = small_data
    for args in (
        ["cluster", demos.path, "--out", ""],
        ["cluster", demos.path, "-o", ""],
        ["cluster", demos.path, "--out="],
        ["collect", "maze", "-n", "1", "--video", "", "--out", tmp_path / "d.h5"],
        # a repeatable path option, and path arguments (the first, or one of many)
        ["grid", tmp_path / "g.toml", "--include", "", "--dry-run"],
        ["inspect", ""],
        ["report", demos.path, "", "--out", tmp_path / "r.md"],
        ["import", "npz", "", "--out", tmp_path / "d.h5"],
    ):
        r = cdrb(*args, cwd=tmp_path)
        assert r.returncode == 2 and "an empty path" in r.stderr and r.stderr.count("\n") == 1, (args, r.stderr)
    assert not list(tmp_path.iterdir())
    r = cdrb("cluster", demos.path, "--k", "2", "--out", tmp_path / "b.h5", "--plot", tmp_path / "b.png")
    assert r.returncode == 0, r.stderr  # a given path is untouched by the check


def test_a_link_loop_is_one_line_naming_the_path(small_data, tmp_path, cdrb):
    """Links that point at each other, given as an output, a settings file or an experiment file: a one-line bad-input
    error naming the path (Python's path resolution raises a bare RuntimeError on them)."""
    demos, _ = small_data
    os.symlink(tmp_path / "b", tmp_path / "a")
    os.symlink(tmp_path / "a", tmp_path / "b")
    loop = tmp_path / "a"
    for args in (
        ["cluster", demos.path, "--k", "2", "--out", loop / "x.h5"],
        ["select", loop, "--out", tmp_path / "t.toml"],
        ["train", demos.path, "--config", loop, "--out", tmp_path / "m.h5"],
    ):
        r = cdrb(*args)
        assert r.returncode == 2 and "a link loop" in r.stderr and str(loop) in r.stderr, (args, r.stderr)
        assert r.stderr.count("\n") == 1


@pytest.mark.skipif(not os.path.exists("/proc/self/mem"), reason="needs Linux's /proc")
def test_a_file_that_opens_but_cannot_be_read_is_one_line(small_data, tmp_path, cdrb):
    """/proc/self/mem opens and then fails every read (EIO): the error names the file and the flag."""
    demos, _ = small_data
    for args, needle in (
        (["inspect", "/proc/self/mem"], "/proc/self/mem: cannot be read"),
        (["train", demos.path, "--config", "/proc/self/mem", "--out", tmp_path / "m.h5"], "--config /proc/self/mem"),
    ):
        r = cdrb(*args)
        assert r.returncode == 2 and needle in r.stderr and r.stderr.count("\n") == 1, (args, r.stderr)
