"""CLI conventions: help, version, inspect, exit codes, one-line errors, stdout hygiene."""

from __future__ import annotations

import json

import h5py
import numpy as np
import pytest

from cdrb_cli import __version__
from cdrb_cli.cli import main
from tests.factories import KINDS, tampered, write

COMMANDS = [
    "collect",
    "cluster",
    "train",
    "plan",
    "eval",
    "report",
    "quickstart",
    "grid",
    "import",
    "export",
    "inspect",
    "schema",
    "envs",
    "methods",
    "config",
]


def test_help_lists_every_command(cdrb):
    r = cdrb("--help")
    assert r.returncode == 0
    for name in COMMANDS:
        assert name in r.stdout


def test_the_max_lag_default_is_declared_once_and_shown(cdrb):
    from cdrb_cli.envs.pointmaze.controllers import DEFAULT_MAX_LAG, InverseDynamicsConfig, PDConfig

    assert PDConfig().max_lag == InverseDynamicsConfig().max_lag == DEFAULT_MAX_LAG
    r = cdrb("config", "eval", "--controller", "pd")
    row = next(line for line in r.stdout.splitlines() if "controller.max_lag" in line)
    assert f" {DEFAULT_MAX_LAG:g} " in row
    assert "0.6" not in cdrb("eval", "--help").stdout  # the help points to it instead of repeating it


def test_version(cdrb):
    r = cdrb("--version")
    assert r.returncode == 0 and r.stdout.strip() == f"cdrb {__version__}"


@pytest.mark.parametrize("kind", KINDS)
def test_inspect_every_kind(tmp_path, cdrb, kind):
    p = write(tmp_path / f"{kind}.h5", kind)
    r = cdrb("inspect", p)
    assert r.returncode == 0, r.stderr
    assert f"valid cdrb {kind} artifact" in r.stdout
    j = cdrb("inspect", p, "--json")
    info = json.loads(j.stdout)
    assert info["kind"] == kind and info["valid"] and info["sha256"] and info["datasets"]


def test_inspect_bad_files_exit_2_with_one_line(tmp_path, cdrb):
    junk = tmp_path / "junk.h5"
    junk.write_bytes(b"\x00" * 100)
    plain = tmp_path / "plain.h5"
    with h5py.File(plain, "w") as f:
        f["x"] = np.ones(2)
    newer = write(tmp_path / "newer.h5", "demos")
    with tampered(newer) as f:
        f.attrs["cdrb_schema_version"] = "9.0"
    for path, needle in [
        (junk, "not an HDF5"),
        (plain, "not a cdrb artifact"),
        (newer, "upgrade cdrb"),
        (tmp_path / "absent.h5", "no such file"),
    ]:
        before = sorted(x.name for x in tmp_path.iterdir())
        r = cdrb("inspect", path)
        assert r.returncode == 2, r.stderr
        assert needle in r.stderr and r.stderr.count("\n") == 1 and "Traceback" not in r.stderr
        assert r.stdout == ""
        assert sorted(x.name for x in tmp_path.iterdir()) == before


def test_usage_errors_exit_2(cdrb):
    r = cdrb("inspect", "--no-such-flag")
    assert r.returncode == 2 and r.stderr.startswith("error:") and r.stderr.count("\n") == 1
    r = cdrb("no-such-command")
    assert r.returncode == 2


def test_debug_shows_traceback(tmp_path, cdrb):
    r = cdrb("--debug", "inspect", tmp_path / "absent.h5")
    assert r.returncode != 0 and "Traceback" in r.stderr


def test_main_returns_exit_codes(tmp_path, capsys):
    assert main(["--version"]) == 0
    assert main(["inspect", str(tmp_path / "nope.h5")]) == 2
    assert "no such file" in capsys.readouterr().err


def test_help_text_is_reflowed_not_hard_wrapped(cdrb):
    import typer.main

    from cdrb_cli.cli import app, reflow

    assert reflow("One\n    two three.\n\n* a\n  b\n* c\n1. d") == "One two three.\n\n* a b\n* c\n1. d"
    command = typer.main.get_command(app)
    for name, cmd in command.commands.items():
        subs = getattr(cmd, "commands", {name: cmd})
        for sub in subs.values():
            for para in (sub.help or "").split("\n\n"):
                for line in para.splitlines()[1:]:
                    assert line.lstrip().startswith(("*", "-")) or line.lstrip()[:1].isdigit(), (name, line)
    for columns in ("80", "120"):
        r = cdrb("collect", "--help", env={"COLUMNS": columns})
        text = " ".join(line.strip(" │") for line in r.stdout.splitlines())
        assert "smooths it and comes to rest at the goal" in text


def test_shell_completion_script(cdrb, monkeypatch):
    """`cdrb --show-completion` prints the script of the shell it runs in (detected from the parent processes, so
    the detection is fixed here: the suite may run under no shell at all)."""
    import shellingham

    monkeypatch.setattr(shellingham, "detect_shell", lambda *a, **k: ("bash", "/bin/bash"))
    r = cdrb("--show-completion")
    assert r.returncode == 0 and "_cdrb_completion" in r.stdout and "complete -o default -F" in r.stdout


def _commands(group, prefix=()):
    """Every command path of the typer app's click group (sub-groups included)."""
    import typer.main

    cmd = typer.main.get_command(group) if not hasattr(group, "commands") else group
    for name, sub in sorted(getattr(cmd, "commands", {}).items()):
        yield (*prefix, name)
        if hasattr(sub, "commands"):
            yield from _commands(sub, (*prefix, name))


def test_help_names_values_as_a_person_reads_them():
    """No Python type names in any command's help (<bool>, <int range>, <list[str]>, {demos}): values read N, X,
    FILE, TEXT or the option's own metavar, and required arguments are upper case in the usage line."""
    import re

    from typer.testing import CliRunner

    from cdrb_cli.cli import app

    runner = CliRunner()
    paths = list(_commands(app))
    assert len(paths) >= 15
    for path in paths:
        out = runner.invoke(app, [*path, "--help"], env={"COLUMNS": "200"}).output
        found = re.findall(r"<(?:bool|int|float|str|path|file|list\[\w+\])[^>]*>|\{[a-z_]+\}", out)
        assert not found, (path, found)
    train = runner.invoke(app, ["train", "--help"], env={"COLUMNS": "200"}).output
    assert "Usage: cdrb train [OPTIONS] DEMOS" in train and re.search(r"--steps\s+N\s", train)


def test_help_labels_fall_back_to_typers_own_on_another_typer_layout(monkeypatch):
    """The label wrapper reaches into typer internals that other typer releases (within the supported range) name
    differently; there it leaves typer's own labels in place instead of failing every command at import."""
    from typer import core

    from cdrb_cli import cli

    monkeypatch.delattr(core, "_TyperParameter")
    before = core.TyperArgument._usage_display_name
    cli.readable_help()  # raises AttributeError without the fallback
    assert core.TyperArgument._usage_display_name is before


def test_a_task_added_without_eta_shows_no_time_left_on_a_terminal_either():
    """The live bar's time-left column: ``eta`` and a time for a task of alike items, nothing for one added with
    ``eta=False`` (as a grid's count of tasks is)."""
    from rich.progress import Progress

    from cdrb_cli import ui

    with Progress(disable=True) as bar:
        alike, unlike = bar.add_task("train", total=10), bar.add_task("grid", total=10, eta=False)
        for _ in range(3):
            bar.advance(alike)
            bar.advance(unlike)
        column = ui.EtaColumn()
        assert column.render(bar.tasks[alike]).plain.startswith("eta ")
        assert column.render(bar.tasks[unlike]).plain == ""


def test_progress_prints_plain_lines_while_it_runs_when_stderr_is_not_a_terminal(small_data, tmp_path, cdrb):
    """With stderr piped (nohup, CI, SLURM) training prints a plain progress line every CDRB_PROGRESS_SECONDS while it
    runs, with rising step counts, and one at the end; not the escape codes of a live bar."""
    import re

    demos, buffer = small_data
    r = cdrb(
        "train", demos.path, "--buffer", buffer.path, "--steps", "60", "--set", "net.dim=8",
        "--set", "checkpoint_every=20", "--out", tmp_path / "m.h5",
        env={"CDRB_PROGRESS_SECONDS": "0"},
    )  # fmt: skip
    assert r.returncode == 0, r.stderr
    counts = [int(m) for m in re.findall(r"^train cdrb: (\d+)/60", r.stderr, re.M)]
    assert len(counts) >= 3 and counts == sorted(counts) and counts[-1] == 60 and counts[0] < 60
    assert "\x1b[" not in r.stderr


def _stat(*cpus):
    """A /proc/stat text with one line per CPU: (busy, idle) jiffies each."""
    lines = ["cpu  0 0 0 0 0 0 0 0 0 0"]
    lines += [f"cpu{i} {busy} 0 0 {idle} 0 0 0 0 0 0" for i, (busy, idle) in enumerate(cpus)]
    return "\n".join(lines + ["intr 1 2 3", "ctxt 4"]) + "\n"


@pytest.mark.parametrize(
    "busy_now, expected",
    [((0, 0, 0, 0), 4), ((100, 0, 0, 0), 3), ((100, 100, 60, 0), 1), ((100, 100, 100, 100), 1), ((40, 0, 0, 0), 4)],
)
def test_default_threads_take_the_cores_free_now(monkeypatch, busy_now, expected):
    """Without OMP_NUM_THREADS a run takes the cores other work leaves free *now* (a short sample of the CPU
    accounting, at least one thread), whatever the 1-minute load average says; with it, that."""
    import os

    from cdrb_cli import torch_utils

    before = _stat(*[(0, 0)] * 4)
    after = _stat(*[(b, 100 - b) for b in busy_now])  # each CPU's share of the sample spent busy, in percent
    reads = iter([before, after])
    monkeypatch.delenv("OMP_NUM_THREADS", raising=False)
    monkeypatch.setattr(torch_utils, "usable_cores", lambda: [0, 1, 2, 3])
    monkeypatch.setattr(torch_utils, "_cpu_ticks", lambda cores: torch_utils.parse_cpu_ticks(next(reads), cores))
    monkeypatch.setattr(torch_utils.time, "sleep", lambda s: None)
    monkeypatch.setattr(os, "getloadavg", lambda: (9.0, 9.0, 9.0))  # a busy minute that is over: not counted
    assert torch_utils.cpu_threads() == expected
    monkeypatch.setenv("OMP_NUM_THREADS", "3")
    assert torch_utils.cpu_threads() == 3


def test_busy_cores_count_only_the_cores_this_process_may_use():
    """The sample sums the CPUs of the affinity mask alone: a busy CPU outside it is not this run's concern."""
    from cdrb_cli import torch_utils

    text = _stat((90, 10), (0, 100), (100, 0))
    assert torch_utils.parse_cpu_ticks(text, [1]) == (100, 100)
    assert torch_utils.parse_cpu_ticks(text, [0, 1]) == (110, 200)
    assert torch_utils.parse_cpu_ticks(text, None) == (110, 300)
    assert torch_utils.parse_cpu_ticks(text, [7]) is None
    assert torch_utils.parse_cpu_ticks("cpu0 1 2\n", None) is None


@pytest.mark.parametrize("load, expected", [(0.05, 4), (1.2, 3), (2.6, 1), (9.0, 1)])
def test_default_threads_fall_back_on_the_load_average(monkeypatch, load, expected):
    """Where the platform has no CPU accounting to sample (no /proc/stat), the 1-minute load average stands in."""
    import os

    from cdrb_cli import torch_utils

    monkeypatch.delenv("OMP_NUM_THREADS", raising=False)
    monkeypatch.setattr(torch_utils, "usable_cores", lambda: None)
    monkeypatch.setattr(os, "cpu_count", lambda: 4)
    monkeypatch.setattr(torch_utils, "_cpu_ticks", lambda cores: None)
    monkeypatch.setattr(os, "getloadavg", lambda: (load, load, load))
    assert torch_utils.cpu_threads() == expected


def _documented_commands():
    """Every `cdrb ...` command a user is shown: the fenced shell blocks of README.md and docs/, and the header of
    every shipped experiment file (continuation lines joined; what follows a pipe, redirect or comment dropped)."""
    import re
    from pathlib import Path

    root = Path(__file__).resolve().parent.parent
    for path in [root / "README.md", *sorted((root / "docs").glob("*.md"))]:
        fenced = False
        for line in path.read_text().replace("\\\n", " ").splitlines():
            if line.startswith("```"):
                fenced = not fenced
            elif fenced and line.strip().removeprefix("$ ").startswith("cdrb "):
                yield path.name, line.strip().removeprefix("$ ")
    for path in sorted((root / "experiments").glob("*/*.toml")):
        for line in path.read_text().replace("\\\n#", " ").splitlines():
            found = re.match(r"#\s+(cdrb .*)", line)
            if found:
                yield path.name, found.group(1)


def test_every_documented_command_parses():
    """A command copied from the docs or an experiment file's header names a real command, real options and
    values each option accepts (parsed by the CLI itself, not run)."""
    import re
    import shlex

    import typer.main

    from cdrb_cli.cli import app

    cli = typer.main.get_command(app)
    seen = 0
    for where, text in _documented_commands():
        text = re.split(r" #|\s\(| \| | > | 2> | && ", text)[0]
        args = shlex.split(text)[1:]
        while args and args[0].startswith("-"):  # cdrb's own options (-q, --debug)
            args.pop(0)
        cmd, name = cli, "cdrb"
        while args and hasattr(cmd, "commands"):
            assert args[0] in cmd.commands, (where, text)
            cmd, name = cmd.commands[args[0]], args[0]
            args = args[1:]
        try:
            cmd.make_context(name, args)
        except Exception as e:  # typer's own click: its usage errors are not the `click` package's classes
            raise AssertionError(f"{where}: `{text}`: {e}") from None
        seen += 1
    assert seen >= 50


@pytest.mark.parametrize(
    "text, expected",
    [("0,1", [0, 1]), (" 3 ", [3]), ("0,1,", [0, 1]), ("-2", [-2]), ("0,,1", None), ("1_0", None), ("٣", None)],
)
def test_integer_lists_take_ascii_digits_and_no_empty_items(text, expected):
    """An empty item or Python int()'s extras (underscores, other scripts' digits) are typos in a seed list, not
    seeds to drop or read; one trailing comma is how lists are often written."""
    from cdrb_cli.cli.common import int_values
    from cdrb_cli.errors import BadInput

    if expected is None:
        with pytest.raises(BadInput, match="not a comma-separated list"):
            int_values(text, "--seeds", "integers", "0,1")
    else:
        assert int_values(text, "--seeds", "integers", "0,1") == expected


def test_cluster_keeps_every_state_of_a_small_buffer_by_default_and_refuses_a_larger_k(tmp_path, cdrb):
    """Demos with fewer states than the default number of clusters make a buffer of all of them (nothing to
    reduce) without a flag; a --k given above the states is still a one-line error."""
    from cdrb_cli import artifacts

    demos = write(tmp_path / "d.h5", "demos", n=12)
    states = int(artifacts.load(demos, "demos").arrays["episodes/length"].sum())
    r = cdrb("cluster", demos, "--seed", "0", "--out", tmp_path / "b.h5")
    buf = artifacts.load(tmp_path / "b.h5", "buffer")
    assert r.returncode == 0 and buf.manifest.config.k == 0 and buf.manifest.summary.points == states, r.stderr
    assert "keeping them all" in r.stderr
    r = cdrb("cluster", demos, "--k", str(states + 1), "--out", tmp_path / "c.h5")
    assert (
        r.returncode == 2 and f"larger than the {states} buffer states" in r.stderr and not (tmp_path / "c.h5").exists()
    )
    r = cdrb("cluster", demos, "--k", "3", "--seed", "0", "--out", tmp_path / "e.h5")
    assert r.returncode == 0 and artifacts.load(tmp_path / "e.h5", "buffer").manifest.summary.points == 3
