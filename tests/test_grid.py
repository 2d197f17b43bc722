"""`cdrb grid`: the grid file, its stage graph, execution on a local pool and on a local Ray instance,
a worker killed mid-task, a failing task, and re-running a finished grid."""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
import re
import shutil
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

import cdrb_cli.cli  # noqa: F401  (installs the description of the commands a grid composes)
from cdrb_cli import artifacts
from cdrb_cli.envs.pointmaze import PointMazeFamily
from cdrb_cli.errors import BadInput
from cdrb_cli.orchestration.grid import PoolBackend, cluster_flags_for, expand, grid, load_grid, run_grid
from tests.conftest import ROOT, call_cdrb

TINY = """
out = "runs"
envs = ["maze-tight"]
methods = ["mlp", "cdrb"]
seeds = [0, 1]
demos = 40
k = 50
steps = 20
eval_episodes = 3

[[settings]]
train = ["--set", "horizon=16", "--set", "stride=10", "--set", "batch_size=8"]

[[settings]]
method = "cdrb"
train = ["--set", "net.dim=8", "--set", "net.dim_mults=1,2", "--set", "method.diffusion_steps=8"]
"""


def _grid(tmp_path: Path, text: str = TINY, name: str = "grid.toml") -> Path:
    path = tmp_path / name
    path.write_text(text)
    return path


def _buffer_name(flags: list[str]) -> str:
    """The buffer file name a grid gives a clustering's flags: a hash of them."""
    return f"buffer-{hashlib.sha256(json.dumps(flags).encode()).hexdigest()[:8]}.h5"


def _cli(*args: str, cwd: Path | None = None, env: dict | None = None) -> subprocess.CompletedProcess:
    return call_cdrb(*args, cwd=cwd, env={"OMP_NUM_THREADS": "1", **(env or {})})


# ------------------------------------------------------------------------------------------------ file and graph
def test_expand_builds_the_stage_graph_with_settings_and_variants(tmp_path):
    text = (
        TINY
        + """
[[settings]]
env = "maze-tight"
method = "mlp"
eval = ["--max-lag", "0"]

[[variants]]
name = "T4"
methods = ["cdrb"]
train = ["--set", "method.diffusion_steps=4"]
"""
    )
    spec = load_grid(_grid(tmp_path, text))
    assert spec.out == (tmp_path / "runs").resolve()
    tasks = expand(spec)
    ids = [t.id for t in tasks]
    # every task after the tasks it reads from, and every dependency exists
    for i, t in enumerate(tasks):
        for d in t.deps:
            assert d in ids[:i], (t.id, d)
    kinds = [t.kind for t in tasks]
    assert kinds.count("collect") == 1 and kinds.count("cluster") == 1
    # the variant applies to cdrb only: 2 seeds; no variant given besides -> only the variant's runs
    trains = [t for t in tasks if t.kind == "train"]
    assert sorted(t.id for t in trains) == ["train maze-tight/T4/cdrb-s0", "train maze-tight/T4/cdrb-s1"]
    cdrb = trains[0].argv
    assert cdrb[cdrb.index("--buffer") + 1].endswith("buffer-k50.h5")
    # later flags override earlier ones: the variant's T comes after the settings' T
    sets = [cdrb[i + 1] for i, a in enumerate(cdrb) if a == "--set" and cdrb[i + 1].startswith("method.diffusion")]
    assert sets == ["method.diffusion_steps=8", "method.diffusion_steps=4"]
    reports = [t for t in tasks if t.kind == "report"]
    assert [t.id for t in reports] == ["report T4"] and len(reports[0].deps) == 2


def test_settings_select_by_env_and_method(tmp_path):
    text = (
        TINY.replace('envs = ["maze-tight"]', 'envs = ["maze-tight", "maze"]')
        + """
[[settings]]
env = "maze"
method = "mlp"
eval = ["--max-lag", "0"]
"""
    )
    tasks = expand(load_grid(_grid(tmp_path, text)))
    evals = {t.id: t.argv for t in tasks if t.kind == "eval"}
    assert "--max-lag" in evals["eval maze/mlp-s0"]
    assert "--max-lag" not in evals["eval maze-tight/mlp-s0"] and "--max-lag" not in evals["eval maze/cdrb-s0"]
    # MLP needs no buffer: its training does not wait for the clustering
    train = next(t for t in tasks if t.id == "train maze/mlp-s0")
    assert train.deps == ["collect maze"] and "--buffer" not in train.argv


def test_collect_settings_reach_only_their_envs_demos(tmp_path):
    text = (
        TINY.replace('envs = ["maze-tight"]', 'envs = ["maze-tight", "fetch-reach-obstacle"]')
        + """
[[settings]]
env = "fetch-reach-obstacle"
collect = ["--set", 'expert.routes=["over"]']
"""
    )
    tasks = expand(load_grid(_grid(tmp_path, text)))
    argv = {t.id: t.argv for t in tasks}
    assert argv["collect fetch-reach-obstacle"][-4:-2] == ["--set", 'expert.routes=["over"]']
    assert "--set" not in argv["collect maze-tight"]
    assert all("expert.routes" not in " ".join(a) for i, a in argv.items() if not i.startswith("collect"))


@pytest.mark.parametrize(
    "text, words",
    [
        ("not toml = = 1", "not valid TOML"),
        (TINY + "\nbogus = 1\n", "bogus"),
        (TINY.replace('"maze-tight"]', '"maze-tighter"]'), "maze-tighter"),
        (TINY.replace('"mlp", "cdrb"', '"mlp", "cdrbb"'), "cdrbb"),
        (TINY.replace("seeds = [0, 1]", "seeds = []"), "seeds"),
        (TINY.replace("seeds = [0, 1]", "seeds = [0, 0]"), "once"),
        (TINY + '\n[[settings]]\nmethod = "diffuserr"\n', "settings[2].method"),
        (TINY + "\n[demos_for]\nmazee = 5\n", "demos_for: unknown environment 'mazee' (choose one of maze,"),
        (TINY + '\n[[settings]]\nenv = "mazee"\n', "settings[2].env"),
        (TINY + '\n[[settings]]\nmethod = "mlp"\ncollect = ["--workers", "1"]\n', "every method shares"),
        (TINY + "\n[resources.training]\ncpus = 2\n", "training"),
        (TINY + "\n[resources.collect]\ncpus = inf\n", "resources.collect.cpus"),
        (TINY + "\n[resources.eval]\ngpus = nan\n", "resources.eval.gpus"),
        (TINY + "\n[resources.train]\ncpus = true\n", "resources.train.cpus"),  # not read as 1
        (TINY + '\n[[settings]]\ncluster = ["--seed", "7"]\n', "the grid sets this `cdrb cluster` option itself"),
        (TINY + f'\n[[variants]]\nname = "{"a" * 300}"\n', "at most 64 characters"),  # a file name too long later
        (TINY + '\n[[settings]]\neval = ["--config", "."]\n', ": not a regular file"),
        (  # a settings entry and a variant reach one field: every eval would refuse it
            TINY + '\n[[settings]]\neval = { replan = "every:20" }\n[[variants]]\nname = "e40"\n'
            'eval = ["--replan", "every:40"]\n',
            "in variant e40: eval flags: --replan every:40 with --set replan=",
        ),
        (TINY + '\n[[settings]]\ntrain = ["--set", "steps=5", "--steps", "6"]\n', "train flags: --steps 6 with"),
        (TINY + '\n[resources.train]\ncpus = "2"\n', "resources.train.cpus"),
        (TINY + "\n[resources.train]\ncpus = 1e300\n", "resources.train.cpus"),
        (TINY + "\n[resources.eval]\ngpus = true\n", "resources.eval.gpus"),
        (TINY + '\n[[variants]]\nname = "a/b"\n', "variants.0.name"),
        (TINY + '\n[[settings]]\ntrain = ["--stepz", "5"]\n', "'--stepz' is not a `cdrb train` option"),
        (TINY + '\n[[variants]]\nname = "v"\neval = ["--max-lagg=0.6"]\n', "is not a `cdrb eval` option"),
        # options the grid sets from its own keys: a repeat's last value would win and mislabel the artifact
        (TINY + '\n[[settings]]\ntrain = ["--method", "diffuser"]\n', "the grid sets this `cdrb train` option"),
        (TINY + '\n[[settings]]\ntrain = ["--seed=9"]\n', "the grid sets this `cdrb train` option"),
        (TINY + '\n[[settings]]\ncollect = ["-n", "5"]\n', "the grid sets this `cdrb collect` option"),
        (TINY + '\n[[variants]]\nname = "v"\neval = ["--seeds", "7"]\n', "the grid sets this `cdrb eval` option"),
        (TINY + '\n[[variants]]\nname = "v"\neval = ["-o", "x.h5"]\n', "the grid sets this `cdrb eval` option"),
        # values: a missing one, a number that does not parse, an unknown controller, a missing file, a stray word
        (TINY + '\n[[settings]]\ntrain = ["--steps", "many"]\n', "'many': not an integer"),
        (TINY + '\n[[settings]]\ntrain = ["--steps"]\n', "'--steps' has no value"),
        (TINY + '\n[[settings]]\ntrain = ["--steps", "--set", "lr=1"]\n', "'--steps' has no value"),
        (TINY + '\n[[settings]]\neval = ["--max-lag=far"]\n', "'far': not a number"),
        (TINY + '\n[[settings]]\neval = ["--controller", "nope"]\n', "unknown controller"),
        (TINY + '\n[[settings]]\ntrain = ["--config", "missing.toml"]\n', "missing.toml: no such file"),
        (TINY + '\n[[settings]]\ntrain = ["4000"]\n', "'4000' is not the value of an option"),
        # values the option's own parser refuses (its range, its choices), for every command
        (TINY + '\n[[settings]]\ncollect = ["--valid-fraction", "-1"]\n', "'-1': -1 is not a share in [0, 1)"),
        (TINY + '\n[[settings]]\ncollect = ["--valid-fraction", "1"]\n', "'1': 1 is not a share in [0, 1)"),
        (TINY + '\n[[settings]]\ncollect = ["--starts", "nowhere"]\n', "--starts 'nowhere': not a start distribution"),
        (TINY + '\n[[settings]]\ncluster = ["--k=-1"]\n', "--k '-1': Input should be greater than"),
        (TINY + '\n[[settings]]\ncluster = ["--features", "pixels"]\n', "not a known feature space"),
        (TINY + '\n[[settings]]\ntrain = ["--net", "resnet"]\n', "not a known network"),
        # how each task runs is the grid's: a dry run would be recorded done without its model, a resume fails fresh
        (TINY + '\n[[settings]]\ntrain = ["--dry-run"]\n', "the grid decides this for each task itself"),
        (TINY + '\n[[settings]]\ntrain = ["--resume"]\n', "the grid decides this for each task itself"),
        (TINY + '\n[[variants]]\nname = "v"\neval = ["--force"]\n', "the grid decides this for each task itself"),
        # train settings resolved as `cdrb train` resolves them: a key, a value, a net, a buffer's features, a horizon
        (
            TINY + '\n[[settings]]\nmethod = "cdrb"\ntrain = ["--set", "net.dimm=8"]\n',
            "cdrb on maze-tight: train flags: --set net.dimm=8: unknown setting",
        ),
        (TINY + '\n[[settings]]\ntrain = ["--set", "lr=fast"]\n', "mlp on maze-tight: train flags: --set lr=fast"),
        (TINY + '\n[[settings]]\nmethod = "cdrb"\ntrain = ["--net", "mlp"]\n', "the cdrb method uses --net"),
        (
            TINY + '\n[[settings]]\nmethod = "cdrb"\ntrain = ["--set", "features=state-action"]\n',
            "clustered on 'state'",
        ),
        (
            TINY + '\n[[variants]]\nname = "v"\nmethods = ["cdrb"]\ntrain = ["--set", "horizon=15"]\n',
            "in variant v: train flags: --set horizon=15",
        ),
        # out: a file, under a file, a control character
        (TINY.replace('out = "runs"', 'out = "grid.toml"'), "is not a folder"),
        (TINY.replace('out = "runs"', 'out = "grid.toml/sub"'), "is not a folder"),
        (TINY.replace('out = "runs"', 'out = "ru\\nns"'), "has a control character"),
        (TINY.replace('out = "runs"', 'out = "/proc/cdrb-grid"'), "out = /proc/cdrb-grid: cannot write in /proc"),
        # a collection on a map file: the command refuses an env and --maze-map both given, so every one would fail
        (TINY + '\n[[settings]]\ncollect = ["--maze-map", "grid.toml"]\n', "a grid collects on its `envs` only"),
        # variants and extensions that would collide or apply to nothing; seeds given two ways
        (TINY + '\n[[variants]]\nname = "demos.h5"\n', "cannot end in .h5"),
        (TINY + '\n[[variants]]\nname = "A"\n[[variants]]\nname = "a"\n', "also in case"),
        (TINY + '\n[[variants]]\nname = "v"\nmethods = []\n', "methods = []: applies to nothing"),
        (TINY + "\n[[extend]]\nenvs = []\nsteps = 40\n", "envs = []: applies to nothing"),
        (
            TINY.replace("seeds = [0, 1]", "seeds = [0, 1]\neval_seeds = [3]\neval_seed_offset = 10"),
            "offset applies only",
        ),
    ],
)
def test_bad_grid_files_are_one_line_errors_naming_the_file(tmp_path, text, words):
    path = _grid(tmp_path, text)
    with pytest.raises(BadInput) as err:
        load_grid(path)
    assert str(path) in str(err.value) and words in str(err.value)
    proc = _cli("grid", str(path), "--backend", "pool")
    assert proc.returncode == 2 and proc.stdout == ""
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error:") and words in lines[0]
    assert not (tmp_path / "runs").exists(), "a refused grid writes nothing"


def test_grid_eval_settings_take_dashes_as_the_command_does(tmp_path):
    """`cdrb eval --set avoid.best-of=2` is avoid.best_of; the grid's check reads the key the same way."""
    path = _grid(
        tmp_path, TINY + '\n[[variants]]\nname = "v"\nmethods = ["cdrb"]\neval = ["--set", "avoid.best-of=2"]\n'
    )
    assert load_grid(path).variants[0].eval == ["--set", "avoid.best-of=2"]
    bad = _grid(
        tmp_path, TINY + '\n[[variants]]\nname = "v"\nmethods = ["cdrb"]\neval = ["--set", "avoid.best-of=0"]\n'
    )
    with pytest.raises(BadInput, match="avoid.best-of=0"):
        load_grid(bad)


def test_an_entry_that_applies_to_none_of_the_grids_runs_is_said_unless_the_grid_was_narrowed(tmp_path):
    path = _grid(tmp_path, TINY + '\n[[variants]]\nname = "v"\nmethods = ["diffuser"]\n')
    proc = _cli("grid", str(path), "--dry-run")
    assert proc.returncode == 0 and "variants[0] (v): applies to none of the grid's" in proc.stderr, proc.stderr
    proc = _cli("grid", str(path), "--dry-run", "--set", 'methods=["mlp"]')
    assert proc.returncode == 0 and "applies to none" not in proc.stderr, proc.stderr


def test_missing_grid_file_and_ray_flags(tmp_path):
    proc = _cli("grid", str(tmp_path / "nope.toml"))
    assert proc.returncode == 2 and "no such grid file" in proc.stderr
    proc = _cli("grid", str(_grid(tmp_path)), "--backend", "pool", "--address", "ray://x:1")
    assert proc.returncode == 2 and "--address" in proc.stderr and len(proc.stderr.strip().splitlines()) == 1
    t = time.time()
    proc = _cli("grid", str(_grid(tmp_path)), "--backend", "ray", "--address", "127.0.0.1:1")  # nobody listens: no hang
    assert proc.returncode == 2 and "no Ray cluster answers" in proc.stderr and time.time() - t < 120, proc.stderr
    assert len(proc.stderr.strip().splitlines()) == 1
    proc = _cli("grid", str(_grid(tmp_path)), "--address", "garbage")
    assert proc.returncode == 2 and "--address 'garbage': not a Ray address" in proc.stderr
    proc = _cli("grid", "/dev/zero")
    assert proc.returncode == 2 and "/dev/zero: not a grid file" in proc.stderr
    (tmp_path / "afile").write_text("x")
    proc = _cli("grid", str(_grid(tmp_path)), "--set", f"out={tmp_path / 'afile'}", "--backend", "pool")
    assert proc.returncode == 2 and "is not a folder" in proc.stderr
    assert (tmp_path / "afile").read_text() == "x"


# ------------------------------------------------------------------------------------------------ execution
def _outputs(run) -> dict[str, float]:
    return {p: os.stat(p).st_mtime_ns for r in run.results for p in r.outputs}


def test_local_pool_runs_the_grid_and_a_rerun_does_no_work(tmp_path, monkeypatch):
    from cdrb_cli.orchestration.grid import run as grid_run

    # tasks print progress lines often and the grid reads them often; FORCE_COLOR must not turn a task's log into a
    # terminal's redraws
    monkeypatch.setenv("CDRB_PROGRESS_SECONDS", "0.05")
    monkeypatch.setenv("FORCE_COLOR", "1")
    monkeypatch.setattr(grid_run, "PROGRESS_POLL", 0.2)
    path = _grid(tmp_path)
    spec = load_grid(path)
    fresh = _cli("grid", str(path), "--dry-run")  # nothing made yet: every task to run, none commented out
    assert fresh.returncode == 0 and "# up to date" not in fresh.stdout
    assert f"{len(expand(spec))} tasks: 0 up to date, {len(expand(spec))} to run" in fresh.stderr
    backend = PoolBackend(2)
    infos: list[str] = []  # what the grid's bar shows after it: the running tasks' last progress lines
    try:
        run = run_grid(spec, backend, on_progress=infos.append)
    finally:
        backend.close()
    assert [r.status for r in run.results] == ["done"] * len(run.results)
    # each task's stderr stays in the grid's folder, and the bar showed the trainings' own progress lines
    logs = spec.out / ".grid" / "logs"
    assert len(list(logs.glob("*.log"))) == len(run.results)
    assert "train cdrb: " in (logs / "train_maze-tight_cdrb-s0.log").read_text()
    assert not any("\x1b" in log.read_text() for log in logs.glob("*.log"))
    assert any(re.search(r"train maze-tight/\w+-s\d: train \w+: \d+/\d+", i) for i in infos), infos
    for r in run.results:
        if r.kind == "eval":
            ev = artifacts.load(Path(r.outputs[0]), "eval")
            assert ev.manifest.config.seeds == [int(r.id[-1])]  # each model on its own seed
    report = (spec.out / "report.md").read_text()
    assert "mlp" in report and "cdrb" in report
    summary = json.loads(run.summary.read_text())
    assert summary["counts"]["done"] == len(run.results)
    before = _outputs(run)

    # the same grid again: every task's memo matches, nothing is started, no file is touched
    class Refuse:
        name = "refuse"

        def submit(self, payload):
            raise AssertionError(f"re-ran {payload['argv'][:2]}")

    again = run_grid(spec, Refuse())
    assert {r.status for r in again.results} == {"up to date"}
    assert _outputs(again) == before
    # and a dry run says so: every command a shell comment
    listing = _cli("grid", str(path), "--dry-run").stdout.splitlines()
    assert len(listing) == len(run.results) and all(line.startswith("# up to date: cdrb ") for line in listing)

    # one output removed: that task and only what depends on it run again (the CLI decides for the others), which
    # is what a dry run lists to run, as commands, and in --json
    Path(run.results[[r.id for r in run.results].index("eval maze-tight/cdrb-s1")].outputs[0]).unlink()
    dry = grid(path, dry_run=True)
    assert sorted(t.id for t in dry.pending()) == ["eval maze-tight/cdrb-s1", "report"]
    listed = _cli("grid", str(path), "--dry-run", "--json")
    rows = json.loads(listed.stdout)
    assert sorted(r["id"] for r in rows if not r["up_to_date"]) == ["eval maze-tight/cdrb-s1", "report"]
    assert f"{len(rows)} tasks: {len(rows) - 2} up to date, 2 to run: 1 eval, 1 report" in listed.stderr
    backend = PoolBackend(1)
    try:
        third = run_grid(spec, backend)
    finally:
        backend.close()
    ran = sorted(r.id for r in third.results if r.status == "done")
    assert ran == ["eval maze-tight/cdrb-s1", "report"]

    # a report the grid did not write (the user's own notes under its name) is refused, never written over
    (spec.out / "report.md").write_text("my notes\n")
    Path(run.results[[r.id for r in run.results].index("eval maze-tight/cdrb-s1")].outputs[0]).unlink()
    backend = PoolBackend(1)
    try:
        fourth = run_grid(spec, backend)
    finally:
        backend.close()
    status = {r.id: r for r in fourth.results}
    assert status["eval maze-tight/cdrb-s1"].status == "done" and status["report"].status == "failed"
    said = status["report"].stderr[-1]
    assert "file exists" in said and "--force" not in said, said  # grid takes no --force: what to do instead
    assert "move or remove that one" in said and status["report"].attempts == 1  # a refusal is not retried
    assert (spec.out / "report.md").read_text() == "my notes\n"


def test_a_task_log_gives_its_last_progress_line_and_is_never_written_through_a_link(tmp_path):
    from cdrb_cli.orchestration.grid.memo import fresh_log, last_line, open_log, read_log

    log = tmp_path / ".grid" / "logs" / "t.log"
    assert last_line(log) == ""  # not made yet
    fresh_log(log)
    assert log.read_bytes() == b"" and last_line(log) == ""
    # a live bar redraws with carriage returns, plain progress lines end with newlines; blank tails are skipped;
    # terminal control sequences (a bar drawn under FORCE_COLOR) never reach the grid's own bar
    log.write_text(
        "loading\ntrain cdrb: 1/10 (10%)\rtrain cdrb: 2/10 (20%)\r" + "x" * 5000 + "\rtrain cdrb: 3/10\n\n  \n"
    )
    assert last_line(log) == "train cdrb: 3/10"
    log.write_text("\x1b[2K\x1b[1mtrain cdrb\x1b[0m \x1b[91m━━\x1b[0m 4/10\x1b]8;;http://x\x07 \x07\x08done\r")
    assert last_line(log) == "train cdrb ━━ 4/10 done"
    # the next attempt starts an empty log and keeps the last one beside it
    fresh_log(log)
    assert log.read_bytes() == b"" and "4/10" in (log.parent / "t.log.1").read_text()

    # a link planted at the name is removed, never followed; one planted after the grid made the log is refused
    target = tmp_path / "precious.txt"
    target.write_text("keep")
    log.unlink()
    log.symlink_to(target)
    fresh_log(log)
    assert target.read_text() == "keep" and not log.is_symlink() and log.read_bytes() == b""
    log.unlink()
    log.symlink_to(target)
    with pytest.raises(OSError):
        os.close(open_log(log))
    assert read_log(log) == "" and last_line(log) == "" and target.read_text() == "keep"
    # a FIFO at the name: neither the writer's open nor the grid's poll blocks on it
    log.unlink()
    os.mkfifo(log)
    with pytest.raises(OSError):
        os.close(open_log(log))
    assert last_line(log) == ""
    # a linked log folder is refused with one line, nothing made through it
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    linked = tmp_path / "out2" / ".grid"
    linked.parent.mkdir()
    linked.symlink_to(elsewhere)
    with pytest.raises(BadInput, match="a link, not a folder of the grid's own"):
        fresh_log(linked / "logs" / "t.log")
    assert list(elsewhere.iterdir()) == []


@pytest.mark.parametrize("warm", [False, True])
def test_a_task_never_writes_its_stderr_through_a_link_at_its_log(tmp_path, warm):
    """The log the grid made, swapped for a link before the task opens it (fresh process or warm fork): the task
    fails, and the link's target is untouched."""
    from cdrb_cli.orchestration.grid.run import execute
    from cdrb_cli.orchestration.grid.warm import WarmServer

    target, log = tmp_path / "precious.txt", tmp_path / "t.log"
    target.write_text("keep")
    log.symlink_to(target)
    payload = {"argv": ["grid", "/dev/zero"], "kind": "eval", "outputs": [], "cpus": 1, "log": str(log)}
    server = WarmServer() if warm else None
    try:
        if warm:
            assert execute({**payload, "log": None}, server)["rc"] == 2  # the server answers, the command fails
        with pytest.raises(OSError) if not warm else contextlib.nullcontext():
            out = execute(payload, server)
            assert out["rc"] != 0
    finally:
        if server is not None:
            server.close()
    assert target.read_text() == "keep"


def test_the_grids_bar_shows_only_running_tasks_and_their_latest_lines(tmp_path, monkeypatch):
    """What the bar shows after the grid's progress while tasks run: each running task's last log line, read as the
    task writes it, and never a task that has finished."""
    import concurrent.futures as cf

    from cdrb_cli.orchestration.grid import run as grid_run

    monkeypatch.setattr(grid_run, "PROGRESS_POLL", 0.01)
    spec = load_grid(_grid(tmp_path, TINY.replace('envs = ["maze-tight"]', 'envs = ["maze", "maze-tight"]')))
    tasks = [t for t in expand(spec) if t.kind == "collect"]
    assert [t.id for t in tasks] == ["collect maze", "collect maze-tight"]

    class Held:
        """Two slots; the test finishes the tasks one at a time from the progress callback."""

        name, logs, capacity = "held", True, 2

        def __init__(self):
            self.futures: list[tuple[cf.Future, dict]] = []

        def submit(self, payload):
            assert Path(payload["log"]).read_bytes() == b""  # made anew before the task is handed over
            fut = cf.Future()
            self.futures.append((fut, payload))
            return fut

    backend, shown = Held(), []

    def on_progress(info: str) -> None:
        shown.append(info)
        first, second = backend.futures
        if len(shown) == 1:  # both running, nothing written yet
            Path(first[1]["log"]).write_text("collect maze: 3/40\r")
            Path(second[1]["log"]).write_text("collect maze-tight: 7/40\n")
        elif len(shown) == 2:
            first[0].set_result({"rc": 1, "seconds": 0.0, "stderr": ["boom"]})
        elif len(shown) == 3:
            second[0].set_result({"rc": 1, "seconds": 0.0, "stderr": ["boom"]})

    run = grid_run.run_grid(spec, backend, retries=0, tasks=tasks, on_progress=on_progress)
    assert [r.status for r in run.results] == ["failed", "failed"]
    a, b = tasks[0].id, tasks[1].id
    assert shown[0] == f"{a}; {b}"
    assert shown[1] == f"{a}: collect maze: 3/40; {b}: collect maze-tight: 7/40"
    assert shown[2] == f"{b}: collect maze-tight: 7/40"  # the finished task is gone at once
    assert shown[3:] == [""]  # and nothing is left once no task runs


def test_the_pool_is_handed_ready_tasks_in_the_grids_order(tmp_path):
    """With one worker the grid hands over one task at a time, the first ready one in its own order: a model's evals
    run before the next model trains, a variant's evals too, which the grid lists after all the trainings
    (everything submitted at once would train every model first, so a grid stopped part-way would leave no finished
    row)."""
    text = TINY.replace('methods = ["mlp", "cdrb"]', 'methods = ["mlp"]')
    text += '\n[[variants]]\nname = "base"\n\n[[variants]]\nname = "lag"\neval = ["--max-lag", "0.6"]\n'
    spec = load_grid(_grid(tmp_path, text))
    listed = [t.id for t in expand(spec)]
    assert listed.index("eval maze-tight/lag/mlp-s0") > listed.index("train maze-tight/mlp-s1")  # moved up below
    submitted: list[str] = []
    in_flight: list[int] = []

    class Recording(PoolBackend):
        def submit(self, payload):
            out = Path(payload["outputs"][0])
            submitted.append(f"{payload['argv'][0]} {out.parent.name}/{out.name}")
            future = super().submit(payload)
            in_flight.append(sum(not f.done() for f in futures) + 1)
            futures.append(future)
            return future

    futures: list = []
    backend = Recording(1)
    try:
        run = run_grid(spec, backend)
    finally:
        backend.close()
    assert all(r.status == "done" for r in run.results)
    assert submitted == [
        "collect maze-tight/demos.h5",
        "train maze-tight/mlp-s0.h5",
        "eval base/eval-mlp-s0.h5",
        "eval lag/eval-mlp-s0.h5",
        "train maze-tight/mlp-s1.h5",
        "eval base/eval-mlp-s1.h5",
        "eval lag/eval-mlp-s1.h5",
        "report runs/report-base.md",
        "report runs/report-lag.md",
    ]
    assert max(in_flight) == 1


def _kill_when_running(held: Path, after: float, killed: list, stop: threading.Event) -> None:
    """SIGKILL the first process that holds the file ``held`` open (a task's output lock: a fresh process or a fork
    of the warm server alike) once it has held it ``after`` seconds."""
    seen: dict[int, float] = {}
    while not stop.is_set() and not killed:
        for pid in filter(str.isdigit, os.listdir("/proc")):
            try:
                fds = os.listdir(f"/proc/{pid}/fd")
                holds = any(os.readlink(f"/proc/{pid}/fd/{fd}") == str(held) for fd in fds)
            except OSError:
                continue
            if holds:
                first = seen.setdefault(int(pid), time.time())
                if time.time() - first >= after:
                    os.kill(int(pid), signal.SIGKILL)
                    killed.append(int(pid))
                    return
        time.sleep(0.05)


def test_a_worker_killed_mid_task_is_retried_and_the_grid_finishes(tmp_path):
    text = TINY.replace('methods = ["mlp", "cdrb"]', 'methods = ["mlp"]').replace("seeds = [0, 1]", "seeds = [0]")
    text = text.replace("steps = 20", "steps = 3000")  # long enough to be killed while training
    spec = load_grid(_grid(tmp_path, text))
    killed: list[int] = []
    stop = threading.Event()
    watcher = threading.Thread(
        target=_kill_when_running, args=(spec.out / "maze-tight" / ".mlp-s0.h5.lock", 4.0, killed, stop)
    )
    watcher.start()
    backend = PoolBackend(1)
    try:
        run = run_grid(spec, backend)
    finally:
        stop.set()
        watcher.join()
        backend.close()
    assert killed, "test set-up: the training was not caught running"
    by_id = {r.id: r for r in run.results}
    assert by_id["train maze-tight/mlp-s0"].attempts == 2
    assert all(r.status == "done" for r in run.results), [(r.id, r.status, r.stderr) for r in run.results]
    model = artifacts.load(Path(by_id["train maze-tight/mlp-s0"].outputs[0]), "model")
    assert model.manifest.state.finished and model.manifest.state.step == 3000
    assert artifacts.load(Path(by_id["eval maze-tight/mlp-s0"].outputs[0]), "eval").manifest.summary is not None


def test_a_failing_task_is_reported_and_the_others_go_on(tmp_path):
    # a setting that is valid but makes training diverge: a failure only the run itself can find
    text = TINY + '\n[[settings]]\nmethod = "mlp"\ntrain = ["--set", "lr=1e30"]\n'
    grid = _grid(tmp_path, text)
    # progress as plain lines at every change (stderr is not a terminal here)
    proc = _cli("grid", str(grid), "--backend", "pool", "-j", "2", env={"CDRB_PROGRESS_SECONDS": "0"})
    assert proc.returncode == 1 and proc.stdout == ""
    assert proc.stderr.strip().splitlines()[-1].startswith("error: 2 of 11 grid tasks failed")
    # the grid's bar counts unlike tasks (evals of seconds, trainings of hours): it shows no time left
    bars = [line for line in proc.stderr.splitlines() if line.startswith("grid: ")]
    # (a running task's own line, shown after the grid's, may have its eta)
    own_eta = [line for line in bars if re.match(r"grid: [^,]*, [\d:]+ elapsed, eta ", line)]
    assert len(bars) >= 5 and not own_eta, own_eta
    summary = json.loads((tmp_path / "runs" / "grid.json").read_text())
    status = {t["id"]: t for t in summary["tasks"]}
    for seed in (0, 1):
        failed = status[f"train maze-tight/mlp-s{seed}"]
        assert failed["status"] == "failed" and failed["attempts"] == 2
        assert any("training diverged" in line for line in failed["stderr"])  # the command's own one-line error
        assert status[f"eval maze-tight/mlp-s{seed}"]["status"] == "skipped"
        assert status[f"eval maze-tight/cdrb-s{seed}"]["status"] == "done"
    assert status["report"]["status"] == "skipped"
    assert not (tmp_path / "runs" / "maze-tight" / "mlp-s0.h5").exists()


def test_ray_runs_the_same_grid(tmp_path):
    """... and its workers import nothing from the folder the grid was started in (a planted `numpy.py`)."""
    pytest.importorskip("ray")
    text = TINY.replace('methods = ["mlp", "cdrb"]', 'methods = ["mlp"]')
    grid = _grid(tmp_path, text)
    start = tmp_path / "start"
    start.mkdir()
    marker = tmp_path / "hijacked"
    (start / "numpy.py").write_text(f"open({str(marker)!r}, 'w').close()\nraise ImportError('planted')\n")
    proc = _cli("grid", str(grid), "--backend", "ray", "-j", "2", cwd=start)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert not marker.exists()
    summary_path = Path(proc.stdout.strip())
    assert summary_path == (tmp_path / "runs" / "grid.json").resolve()
    summary = json.loads(summary_path.read_text())
    assert summary["backend"] == "ray" and summary["counts"]["done"] == 6
    assert "mlp" in (tmp_path / "runs" / "report.md").read_text()
    # a finished grid run again on the pool: nothing to do
    proc = _cli("grid", str(grid), "--backend", "pool", "--json")
    assert proc.returncode == 0 and json.loads(proc.stdout)["counts"]["up to date"] == 6


def test_the_shipped_experiment_files_load_and_expand():
    root = Path(__file__).resolve().parent.parent / "experiments"
    files = sorted(p for p in root.glob("*/*.toml") if p.parent.name not in ("tuned", "data", "scenes"))
    assert len(files) >= 10
    for path in files:
        spec = load_grid(path)
        spec.reuse = []  # the counts below are of a clean checkout, with nothing finished to reuse
        tasks = expand(spec)
        evals = [t for t in tasks if t.kind == "eval"]
        assert evals and all(t.meta["stream"] in t.argv for t in evals)
        tuning = path.parent.name == "tune"
        # tuning files evaluate on the tuning stream only and leave the comparison to `cdrb select`; the others on
        # the test stream only
        assert {t.meta["stream"] for t in evals} == {"tune" if tuning else "test"}, path
        assert (not spec.report) == tuning, path
        # the comment states the --dry-run count of every kind of task
        head = path.read_text().split("\nout =")[0]
        counts = {k: sum(t.kind == k for t in tasks) for k in ("train", "eval")}
        for kind, n in counts.items():
            word = {"train": "training", "eval": "eval"}[kind] + ("" if n == 1 else "s")
            assert f" {n} {word}" in head, (path, kind)
    # the included settings files of the test grids hold exactly one entry per env x method they choose for
    for path in sorted((root / "tuned").glob("*.toml")):
        from cdrb_cli.orchestration.grid import SettingsFile, read_toml

        sfile = SettingsFile.model_validate(read_toml(path, "settings file"))
        keys = [(s.env, s.method) for s in sfile.settings]
        assert keys and len(keys) == len(set(keys)) and all(s.chosen for s in sfile.settings), path


# ------------------------------------------------------------------------------------------------ experiments as data
def test_includes_apply_in_order_and_a_loop_is_an_error(tmp_path):
    (tmp_path / "shared.toml").write_text('[[settings]]\nmethod = "cdrb"\ntrain = ["--set", "net.dim=16"]\n')
    (tmp_path / "tuned.toml").write_text(
        'include = ["shared.toml"]\n[meta]\nrule = "x"\n'
        '[[settings]]\nenv = "maze-tight"\nmethod = "cdrb"\nchosen = "dim32"\ntrain = ["--set", "net.dim=32"]\n'
    )
    (tmp_path / "late.toml").write_text('[[settings]]\nmethod = "cdrb"\ntrain = ["--set", "net.dim=64"]\n')
    grid = _grid(tmp_path, 'include = ["tuned.toml"]\n' + TINY)
    train = next(t for t in expand(load_grid(grid)) if t.id == "train maze-tight/cdrb-s0").argv
    dims = [a for a in train if a.startswith("net.dim=")]
    # the included file's own include, then the included file, then the grid's own settings
    assert dims == ["net.dim=16", "net.dim=32", "net.dim=8"]
    train = next(
        t
        for t in expand(load_grid(grid, extra_includes=[tmp_path / "late.toml"]))
        if t.id == "train maze-tight/cdrb-s0"
    ).argv
    assert [a for a in train if a.startswith("net.dim=")][-1] == "net.dim=64"  # --include comes last
    (tmp_path / "shared.toml").write_text('include = ["tuned.toml"]\n')
    with pytest.raises(BadInput, match="includes itself"):
        load_grid(grid)
    (tmp_path / "shared.toml").write_text('[[settings]]\nmethod = "cdrb"\nbogus = 1\n')
    with pytest.raises(BadInput, match=r"shared.toml: settings.0.bogus"):
        load_grid(grid)


def test_a_selection_that_misses_a_run_its_tuning_grid_tunes_is_refused(tmp_path):
    """A test grid including a `cdrb select` file runs nothing unchosen: an env x method the selection's tuning grid
    tunes but the selection holds no choice for (written before that run was tuned) is one line naming both files;
    a run the tuning grid never tuned, or a grid narrowed to the chosen runs, goes."""
    (tmp_path / "tune").mkdir()
    (tmp_path / "tune" / "t.toml").write_text(TINY)  # tunes mlp and cdrb on maze-tight
    (tmp_path / "tuned.toml").write_text(
        '[meta]\nrule = "x"\ntuning_grid = "tune/t.toml"\n'
        '[[settings]]\nenv = "maze-tight"\nmethod = "cdrb"\nchosen = "c"\ntrain = ["--steps", "30"]\n'
    )
    grid = _grid(
        tmp_path, 'include = ["tuned.toml"]\n' + TINY.replace('["mlp", "cdrb"]', '["mlp", "cdrb", "straight"]')
    )
    with pytest.raises(BadInput, match=r"mlp on maze-tight: tuned.toml holds no choice for it, though tune/t.toml"):
        load_grid(grid)
    assert {t.id for t in expand(load_grid(grid, overrides=['methods=["cdrb", "straight"]']))} >= {
        "train maze-tight/cdrb-s0",
        "train maze-tight/straight-s0",
    }
    # a tuning grid that names no runs, or a name no file can have: provenance only, never a crash
    for text in ["envs = 5\nmethods = 3\n", 'envs = ["maze-tight"]\nmethods = "mlp"\n']:
        (tmp_path / "tune" / "t.toml").write_text(text)
        load_grid(grid)
    for name in ["tune/t\\u0000.toml", "x" * 5000]:
        (tmp_path / "tuned.toml").write_text(
            f'[meta]\nrule = "x"\ntuning_grid = "{name}"\n[[settings]]\nenv = "maze-tight"\nmethod = "cdrb"\n'
        )
        load_grid(grid)
    (tmp_path / "tune" / "t.toml").unlink()  # the tuning grid gone: the selection is provenance only
    load_grid(grid)


def test_a_setting_stated_by_two_included_files_is_passed_once_and_an_override_still_holds(tmp_path):
    # a tuned settings file repeats what the data file it was chosen under also says
    (tmp_path / "data.toml").write_text('[[settings]]\nmethod = "cdrb"\ntrain = ["--set", "horizon=16"]\n')
    (tmp_path / "tuned.toml").write_text(
        '[meta]\nrule = "x"\n[[settings]]\nenv = "maze-tight"\nmethod = "cdrb"\nchosen = "c"\n'
        'train = ["--set", "horizon=16", "--steps", "30"]\n'
        'eval = ["--set=controller.kp=2", "--set=controller.kp=2"]\n'
    )
    grid = _grid(tmp_path, 'include = ["data.toml", "tuned.toml"]\n' + TINY.replace('"horizon=16", ', '"horizon=12", '))
    tasks = {t.id: t.argv for t in expand(load_grid(grid))}
    train = tasks["train maze-tight/cdrb-s0"]
    # data's 16, tuned's 16 (dropped: the same value), the grid's own 12: the last one still wins
    assert [a for a in train if a.startswith("horizon=")] == ["horizon=16", "horizon=12"]
    evaluate = next(argv for tid, argv in tasks.items() if tid.startswith("eval maze-tight") and "cdrb-s0" in tid)
    assert evaluate.count("--set=controller.kp=2") == 1


def test_without_repeated_sets_keeps_every_flag_that_changes_the_command():
    from cdrb_cli.orchestration.grid import without_repeated_sets

    flags = ["--set", "a=1", "--steps", "5", "--set", "a=1", "--set", "b=2"]
    assert without_repeated_sets(flags) == ["--set", "a=1", "--steps", "5", "--set", "b=2"]
    # a value overridden in between and then restored is a real change
    assert without_repeated_sets(["--set", "a=1", "--set", "a=2", "--set", "a=1"]) == [
        "--set", "a=1", "--set", "a=2", "--set", "a=1",
    ]  # fmt: skip
    # so is one whose parent (or child) key was set in between
    nested = ["--set", "net.dim=8", "--set", "net=big", "--set", "net.dim=8"]
    assert without_repeated_sets(nested) == nested
    assert without_repeated_sets(["--set", "net=big", "--set", "net.dim=8", "--set", "net=big"]) == [
        "--set", "net=big", "--set", "net.dim=8", "--set", "net=big",
    ]  # fmt: skip
    # a pair without '=' and a trailing --set are left for the command's own error
    assert without_repeated_sets(["--set", "oops", "--set", "oops", "--set"]) == [
        "--set",
        "oops",
        "--set",
        "oops",
        "--set",
    ]


def test_eval_only_variants_share_the_base_model_and_cluster_variants_get_their_own_buffer(tmp_path):
    text = TINY + (
        '\n[[variants]]\nname = "gated"\neval = ["--max-lag", "0.6"]\n'
        '\n[[variants]]\nname = "official"\nmethods = ["cdrb"]\neval = ["--protocol", "official-code"]\n'
        "eval_settings = false\n"
        '\n[[settings]]\nmethod = "cdrb"\neval = ["--max-lag", "0.3"]\n'
        '\n[[variants]]\nname = "k20"\nmethods = ["cdrb"]\ncluster = ["--k", "20"]\nstream = "tune"\n'
    )
    spec = load_grid(_grid(tmp_path, text))
    tasks = {t.id: t for t in expand(spec)}
    out = spec.out / "maze-tight"
    # one base training per method and seed serves both eval-only variants
    trains = sorted(i for i in tasks if i.startswith("train"))
    assert trains == [
        "train maze-tight/cdrb-s0", "train maze-tight/cdrb-s1", "train maze-tight/k20/cdrb-s0",
        "train maze-tight/k20/cdrb-s1", "train maze-tight/mlp-s0", "train maze-tight/mlp-s1",
    ]  # fmt: skip
    gated, official = tasks["eval maze-tight/gated/cdrb-s0"], tasks["eval maze-tight/official/cdrb-s0"]
    assert gated.inputs == official.inputs == [out / "cdrb-s0.h5"] and gated.deps == ["train maze-tight/cdrb-s0"]
    assert gated.argv[gated.argv.index("--max-lag") :][:4] == ["--max-lag", "0.3", "--max-lag", "0.6"]
    assert "--max-lag" not in official.argv and "official-code" in official.argv  # the settings' flags left out
    assert "eval maze-tight/official/mlp-s0" not in tasks
    # a variant with cluster flags: its own buffer, clustered from the same demos, and its own models
    (cluster,) = [t for t in tasks.values() if t.kind == "cluster" and "20" in t.argv]
    assert cluster.argv[2:4] == ["--k", "20"] and cluster.argv.count("--k") == 1  # the variant's k, once
    assert cluster.outputs[0].parent == out
    assert cluster.outputs[0] != out / "buffer-k50.h5"  # not the grid's own buffer
    k20 = tasks["train maze-tight/k20/cdrb-s0"]
    assert str(cluster.outputs[0]) in k20.argv and cluster.id in k20.deps
    # settings may give cluster flags too: runs with the same flags share one buffer, whoever sets them
    shared = text + '\n[[settings]]\nmethod = "mlp"\ncluster = ["--k", "20"]\n'
    spec2 = load_grid(_grid(tmp_path, shared))
    clusters = [t for t in expand(spec2) if t.kind == "cluster"]
    assert len(clusters) == 2  # the grid's buffer and the k = 20 one (mlp needs none: no task for it)
    assert tasks["eval maze-tight/k20/cdrb-s0"].meta["stream"] == "tune"
    assert "--stream" in gated.argv and gated.argv[gated.argv.index("--stream") + 1] == "test"
    assert {t.id for t in expand(spec) if t.kind == "report"} == {"report gated", "report official", "report k20"}


def test_a_cluster_option_named_twice_is_passed_once_with_its_last_value(tmp_path):
    """Two settings files both naming `--features` (an included data file and a tuned file) make the same buffer
    as one naming it once: one clustering, one flag, the last value (as `cdrb cluster` itself would read it)."""
    once = TINY + '\n[[settings]]\nmethod = "cdrb"\ncluster = ["--features", "state-action"]\n'
    twice = once + '\n[[settings]]\nmethod = "cdrb"\ncluster = ["--k", "20", "--features", "state-action"]\n'
    clusters = {}
    for name, text in {"once": once, "twice": twice}.items():
        folder = tmp_path / name
        folder.mkdir()
        (cluster,) = [t for t in expand(load_grid(_grid(folder, text))) if t.kind == "cluster"]
        clusters[name] = cluster
    argv = clusters["twice"].argv
    assert argv.count("--features") == 1 and argv[argv.index("--features") + 1] == "state-action"
    assert argv[argv.index("--k") + 1] == "20" and argv.count("--k") == 1  # the settings' k replaces the grid's
    # the option named twice with one value names the same buffer as the option named once
    assert clusters["once"].argv.count("--features") == 1
    changed = once.replace('cluster = ["--features", "state-action"]', 'cluster = ["--features", "state"]')
    last = changed + '\n[[settings]]\nmethod = "cdrb"\ncluster = ["--features", "state-action"]\n'
    (folder := tmp_path / "last").mkdir()
    (cluster,) = [t for t in expand(load_grid(_grid(folder, last))) if t.kind == "cluster"]
    assert cluster.argv.count("--features") == 1 and "state-action" in cluster.argv
    assert cluster.outputs[0].name == clusters["once"].outputs[0].name
    # a buffer a grid already made under the name the repeated flags gave keeps it (its runs stay done)
    spec = load_grid(_grid(tmp_path / "twice", twice))
    given = cluster_flags_for(spec, "maze-tight", "cdrb")
    old_name = _buffer_name(given)
    (spec.out / "maze-tight").mkdir(parents=True)
    (spec.out / "maze-tight" / old_name).write_bytes(b"")
    (kept,) = [t for t in expand(spec) if t.kind == "cluster"]
    assert kept.outputs[0].name == old_name and kept.argv[2:] == clusters["twice"].argv[2:-1] + [str(kept.outputs[0])]


def test_one_clustering_spelled_two_ways_is_one_buffer(tmp_path):
    """`--features=state-action` and `--features state-action` are one clustering to `cdrb cluster`, so to the grid:
    one cluster task, one buffer name, one spelling on its command line."""
    names = {}
    for form in ('"--features", "state-action"', '"--features=state-action"'):
        text = TINY + f'\n[[settings]]\nmethod = "cdrb"\ncluster = ["--features", "state", {form}]\n'
        (folder := tmp_path / str(len(names))).mkdir()
        (cluster,) = [t for t in expand(load_grid(_grid(folder, text))) if t.kind == "cluster"]
        assert cluster.argv.count("--features") == 1 and "state-action" in cluster.argv, cluster.argv
        names[form] = cluster.outputs[0].name
    assert len(set(names.values())) == 1, names


def test_buffers_named_before_folding_keep_every_run_on_its_buffer(tmp_path):
    """A grid whose base settings cluster with `--features state-action` and whose variant names the option again
    made two buffers before repeated options were folded (named from the flags as given). Both flag lists now fold
    to one line; with both old buffers on disk, each training still reads the one it read, so none is redone."""
    text = TINY + (
        '\n[[settings]]\nmethod = "cdrb"\ncluster = ["--features", "state-action"]\n'
        '\n[[variants]]\nname = "plain"\neval = ["--max-lag", "0.6"]\n'
        '\n[[variants]]\nname = "sa"\ncluster = ["--features", "state-action"]\n'
    )
    spec = load_grid(_grid(tmp_path, text))
    once, twice = ["--features", "state-action"], ["--features", "state-action"] * 2
    (spec.out / "maze-tight").mkdir(parents=True)
    for flags in (once, twice):
        (spec.out / "maze-tight" / _buffer_name(flags)).write_bytes(b"")
    reads = {
        t.id: {p.name for p in t.inputs if p.name.startswith("buffer-")}
        for t in expand(spec)
        if t.kind == "train" and "cdrb" in t.id
    }
    assert reads, "no CDRB trainings"
    for tid, names in reads.items():
        assert names == {_buffer_name(twice if "/sa/" in tid else once)}, (tid, names)


def test_a_planner_without_a_buffer_names_the_grid_buffer_by_placeholder(tmp_path):
    """``{buffer}`` in an eval flag is the environment's buffer (the base clustering): the eval reads it, so it
    depends on the clustering, even for a method that trains without one (no second clustering is made)."""
    text = TINY.replace('methods = ["mlp", "cdrb"]', 'methods = ["mlp"]') + (
        '\n[[variants]]\nname = "routed"\n'
        'eval = { replan = { mode = "every", every = 40, waypoint_reach = 2.0 }, '
        'avoid = { route_buffer = "{buffer}" } }\n'
    )
    spec = load_grid(_grid(tmp_path, text))
    tasks = expand(spec)
    (cluster,) = [t for t in tasks if t.kind == "cluster"]  # made for the placeholder alone: mlp needs no buffer
    ev = next(t for t in tasks if t.id == "eval maze-tight/routed/mlp-s0")
    buffer = cluster.outputs[0]
    assert f'avoid.route_buffer="{buffer}"' in ev.argv and "{buffer}" not in " ".join(ev.argv)
    assert cluster.id in ev.deps and buffer in ev.inputs
    assert not [t for t in tasks if t.kind == "train" and "--buffer" in t.argv]


def test_demos_per_environment_where_datasets_differ_in_size(tmp_path):
    text = TINY.replace('envs = ["maze-tight"]', 'envs = ["maze-tight", "maze"]').replace(
        "eval_episodes = 3", 'eval_episodes = 3\ndemos_for = { "maze" = 12 }'
    )
    tasks = {t.id: t for t in expand(load_grid(_grid(tmp_path, text)))}
    counts = {
        env: tasks[f"collect {env}"].argv[tasks[f"collect {env}"].argv.index("-n") + 1]
        for env in ("maze", "maze-tight")
    }
    assert counts == {"maze": "12", "maze-tight": "40"}
    with pytest.raises(BadInput, match="no-such-env"):
        load_grid(
            _grid(tmp_path, TINY.replace("eval_episodes = 3", 'eval_episodes = 3\ndemos_for = { "no-such-env" = 5 }'))
        )


def test_reuse_rewrites_a_file_a_setting_names(tmp_path):
    """A reused clustering moves its buffer to the other grid's file: an eval that names it in a setting (a route
    buffer) reads that file then, as one naming it in an option does."""
    from cdrb_cli.orchestration.grid.reuse import _replace_files

    here, there = tmp_path / "a" / "buffer.h5", tmp_path / "b" / "buffer.h5"
    for f in (here, there):
        f.parent.mkdir()
        f.write_bytes(b"x")
    argv = ["eval", "m.h5", "--set", f'avoid.route_buffer="{here}"', f"--route-buffer={here}", "--set", "n=3"]
    out = _replace_files(argv, {os.path.realpath(here): str(there)})
    assert out == ["eval", "m.h5", "--set", f'avoid.route_buffer="{there}"', f"--route-buffer={there}", "--set", "n=3"]


def test_learning_curve_snapshots_are_evaluated_and_eval_seeds_are_shared(tmp_path):
    text = TINY.replace("steps = 20", "steps = 100\nsnapshot_at = [50]\neval_seeds = [0, 1]\nreport = false")
    spec = load_grid(_grid(tmp_path, text))
    tasks = {t.id: t for t in expand(spec)}
    train = tasks["train maze-tight/mlp-s1"]
    assert train.argv[train.argv.index("--snapshot-at") + 1] == "50"
    assert train.outputs == [spec.out / "maze-tight" / "mlp-s1.h5", spec.out / "maze-tight" / "mlp-s1.step50.h5"]
    snap = tasks["eval maze-tight/mlp-s1.step50"]
    assert snap.inputs == [spec.out / "maze-tight" / "mlp-s1.step50.h5"] and snap.meta["steps"] == 50
    assert snap.argv[snap.argv.index("--seeds") + 1] == "0,1" and tasks["eval maze-tight/mlp-s1"].meta["steps"] == 100
    assert not [t for t in tasks.values() if t.kind == "report"]
    for bad, words in (
        ("snapshot_at = [100]", "snapshot_at: every snapshot must lie between"),
        ("snapshot_at = [50, 50]", "list each step once"),
    ):
        with pytest.raises(BadInput, match=words):
            load_grid(_grid(tmp_path, text.replace("snapshot_at = [50]", bad)))
    with pytest.raises(BadInput, match="eval_seeds with several training seeds"):
        load_grid(_grid(tmp_path, text.replace("report = false", "report = true")))


def test_an_extension_runs_some_curves_further_and_keeps_the_rest(tmp_path):
    """An [[extend]] entry resumes the matching runs to its steps, with the grid's steps one more snapshot point;
    runs it does not name keep the grid's curve; entries that resume the same runs go in increasing steps."""
    text = TINY.replace("steps = 20", "steps = 100\nsnapshot_at = [50]\nreport = false")
    text += '\n[[extend]]\nmethods = ["cdrb"]\nsteps = 200\n\n[[extend]]\nmethods = ["mlp"]\nsteps = 300\n'
    spec = load_grid(_grid(tmp_path, text))
    tasks = {t.id: t for t in expand(spec)}
    cdrb, mlp = tasks["train maze-tight/cdrb-s0"], tasks["train maze-tight/mlp-s0"]
    assert cdrb.argv[cdrb.argv.index("--steps") + 1] == "200" and "--snapshot-at" in cdrb.argv
    assert cdrb.argv[cdrb.argv.index("--snapshot-at") + 1] == "50,100"
    assert mlp.argv[mlp.argv.index("--steps") + 1] == "300"
    assert cdrb.outputs[1:] == [spec.out / "maze-tight" / f"cdrb-s0.step{s}.h5" for s in (50, 100)]
    # the old final length is now a snapshot, evaluated from its snapshot file; the new one is the final model
    old, new = tasks["eval maze-tight/cdrb-s0.step100"], tasks["eval maze-tight/cdrb-s0"]
    assert old.inputs == [spec.out / "maze-tight" / "cdrb-s0.step100.h5"] and old.meta["steps"] == 100
    assert new.inputs == [spec.out / "maze-tight" / "cdrb-s0.h5"] and new.meta["steps"] == 200
    # one env not named: its curves stay at the grid's steps
    narrow = load_grid(_grid(tmp_path, TINY.replace("steps = 20", "steps = 100\nreport = false")
                             + '\n[[extend]]\nenvs = ["maze"]\nsteps = 200\n'))  # fmt: skip
    train = next(t for t in expand(narrow) if t.id == "train maze-tight/mlp-s0")
    assert train.argv[train.argv.index("--steps") + 1] == "100" and "--snapshot-at" not in train.argv
    for extra, words in (
        ("[[extend]]\nsteps = 100\n", r"extend\[0\]: steps 100 does not extend the curve"),
        ('[[extend]]\nmethods = ["nope"]\nsteps = 200\n', r"extend\[0\]: methods"),
        ('[[extend]]\nenvs = ["nope"]\nsteps = 200\n', r"extend\[0\]: envs"),
        ("[[extend]]\nsteps = 200\nsnapshot = 1\n", "extend.0.snapshot: not a key of this file's format"),
    ):
        with pytest.raises(BadInput, match=words):
            load_grid(_grid(tmp_path, text.split("\n[[extend]]")[0] + "\n" + extra))
    # the grid's steps, now a snapshot, must lie on the loss curve like any snapshot (quick records every 50)
    with pytest.raises(BadInput, match="snapshot_at: 120 is not a multiple of 50"):
        load_grid(
            _grid(tmp_path, TINY.replace("steps = 20", "steps = 120\nreport = false") + "[[extend]]\nsteps = 200\n")
        )
    # given with --set, as TOML inline tables
    spec = load_grid(_grid(tmp_path, TINY.replace("steps = 20", "steps = 100")), ["extend=[{steps=200}]"])
    assert spec.curve("maze-tight", "mlp") == (200, [100])
    # an entry may extend some variants' runs: an eval-only variant's name stands for the base models it evaluates
    scoped = TINY.replace("steps = 20", "steps = 100\nreport = false").replace('["mlp", "cdrb"]', '["mlp"]')
    scoped += '\n[[variants]]\nname = "ref"\neval = []\n\n[[variants]]\nname = "wide"\ntrain = { lr = 0.01 }\n'
    for names, base, wide in ((["wide"], 100, 200), (["ref"], 200, 100), (None, 200, 200)):
        extra = "" if names is None else f"variants = {json.dumps(names)}\n"
        spec = load_grid(_grid(tmp_path, scoped + f"\n[[extend]]\n{extra}steps = 200\n"))
        assert spec.curve("maze-tight", "mlp", "")[0] == base and spec.curve("maze-tight", "mlp", "wide")[0] == wide
        tasks = {t.id: t for t in expand(spec)}
        argv = tasks["train maze-tight/wide/mlp-s0"].argv
        assert argv[argv.index("--steps") + 1] == str(wide)
        assert ("eval maze-tight/ref/mlp-s0.step100" in tasks) == (base == 200)
    for names, words in ((["nope"], "variants: nope: no such variant in grid.toml"), ([], "applies to nothing")):
        with pytest.raises(BadInput, match=re.escape(words)):
            load_grid(_grid(tmp_path, scoped + f"\n[[extend]]\nvariants = {json.dumps(names)}\nsteps = 200\n"))
    # the entry's names mean the file's variants, whichever arms --set variants=[...] runs: narrowed to the
    # eval-only arm, the base models still train to the entry's steps (not back to the grid's), and a typo is a typo
    spec = load_grid(_grid(tmp_path, scoped + '\n[[extend]]\nvariants = ["ref"]\nsteps = 200\n'), ['variants=["ref"]'])
    assert [v.name for v in spec.variants] == ["ref"] and spec.curve("maze-tight", "mlp", "") == (200, [100])
    train = {t.id: t for t in expand(spec)}["train maze-tight/mlp-s0"].argv
    assert train[train.index("--steps") + 1] == "200"
    with pytest.raises(BadInput, match="variants: rfe: no such variant in grid.toml"):
        load_grid(_grid(tmp_path, scoped + '\n[[extend]]\nvariants = ["rfe"]\nsteps = 200\n'), ['variants=["ref"]'])
    # a variant the entry's own scope never reaches would extend nothing
    out_of_scope = scoped.replace('name = "wide"', 'name = "wide"\nenvs = ["maze-tight"]').replace(
        'envs = ["maze-tight"]\nmethods', 'envs = ["maze-tight", "maze"]\nmethods'
    )
    with pytest.raises(BadInput, match="variants: wide has no runs in this entry's envs and methods"):
        load_grid(_grid(tmp_path, out_of_scope + '\n[[extend]]\nenvs = ["maze"]\nvariants = ["wide"]\nsteps = 200\n'))
    # a later entry with fewer steps for the same runs would cut the curve short: refused, naming both
    with pytest.raises(
        BadInput, match=re.escape("extend[1]: steps 200 is fewer than extend[0]'s 300 for maze-tight x cdrb")
    ):
        load_grid(
            _grid(
                tmp_path,
                text.split("\n[[extend]]")[0]
                + '\n[[extend]]\nsteps = 300\n\n[[extend]]\nmethods = ["cdrb"]\nsteps = 200\n',
            )
        )
    # a later stage resumes the runs again: each earlier stage's end stays a point of the curve
    staged = TINY.replace("steps = 20", "steps = 100\nsnapshot_at = [50]\nreport = false")
    staged += "\n[[extend]]\nsteps = 200\n\n[[extend]]\nsteps = 400\n"
    spec = load_grid(_grid(tmp_path, staged))
    assert spec.curve("maze-tight", "mlp") == (400, [50, 100, 200])
    assert "eval maze-tight/mlp-s0.step200" in {t.id for t in expand(spec)}


def test_eval_seed_offset_gives_each_model_fresh_pairs_of_its_own(tmp_path):
    spec = load_grid(_grid(tmp_path, TINY.replace("eval_episodes = 3", "eval_episodes = 3\neval_seed_offset = 10")))
    evals = {t.meta["seed"]: t.argv for t in expand(spec) if t.kind == "eval" and t.meta["method"] == "mlp"}
    assert {s: argv[argv.index("--seeds") + 1] for s, argv in evals.items()} == {0: "10", 1: "11"}
    plain = {t.meta["seed"]: t.argv for t in expand(load_grid(_grid(tmp_path))) if t.kind == "eval"}
    assert plain[1][plain[1].index("--seeds") + 1] == "1"


def test_grid_set_overrides_top_level_keys_only(tmp_path, monkeypatch):
    grid = _grid(tmp_path, TINY)
    monkeypatch.chdir(tmp_path)
    spec = load_grid(grid, ["seeds=[3]", "demos=7", "out=elsewhere", "eval_stream=tune"])
    assert spec.seeds == [3] and spec.demos == 7 and spec.out == tmp_path / "elsewhere" and spec.eval_stream == "tune"
    with pytest.raises(BadInput, match="not a top-level grid key"):
        load_grid(grid, ["settings=[]"])
    with pytest.raises(BadInput, match="expected KEY=VALUE"):
        load_grid(grid, ["demos"])
    with pytest.raises(BadInput, match="demos"):
        load_grid(grid, ["demos=1"])  # validated like the file's own value
    # a list given as one bare value is refused with the list it means, written out
    with pytest.raises(
        BadInput,
        match=re.escape('--set envs=maze: envs: Input should be a valid list (a TOML list, e.g. envs=["maze"])'),
    ):
        load_grid(grid, ["envs=maze"])
    # a list whose brackets are wrong is no TOML, so it arrives as text: not wrapped in a list of itself
    with pytest.raises(BadInput, match=re.escape("([0,1 is not a TOML list: write e.g. seeds=[0, 1])")):
        load_grid(grid, ["seeds=[0,1"])
    with pytest.raises(BadInput, match=re.escape('--set out=1: out: a path is written as a string, e.g. "runs/NAME"')):
        load_grid(grid, ["out=1"])


def test_grid_set_variants_runs_the_named_arms_only(tmp_path):
    text = TINY + "".join(
        f'\n[[variants]]\nname = "{n}"\nmethods = ["cdrb"]\ntrain = ["--set", "method.diffusion_steps={t}"]\n'
        for n, t in (("T4", 4), ("T6", 6), ("T2", 2))
    )
    grid = _grid(tmp_path, text)
    trains = lambda spec: sorted(t.id for t in expand(spec) if t.kind == "train")  # noqa: E731
    assert len(trains(load_grid(grid))) == 6
    spec = load_grid(grid, ['variants=["T2", "T4"]'])
    assert [v.name for v in spec.variants] == ["T4", "T2"]  # the file's order
    assert trains(spec) == [f"train maze-tight/{n}/cdrb-s{s}" for n in ("T2", "T4") for s in (0, 1)]
    assert [v.name for v in load_grid(grid, ["variants=T6"]).variants] == ["T6"]
    with pytest.raises(BadInput, match=r"--set variants=\[.T9.\]: variants: T9: no such variant.*T4, T6, T2"):
        load_grid(grid, ['variants=["T9"]'])
    with pytest.raises(BadInput, match="a list of the file's variant names"):
        load_grid(grid, ["variants=[]"])


@pytest.mark.parametrize(
    "line, words",
    [
        ("steps = true", "steps: Input should be a valid integer"),
        ("seeds = [-1]", "seeds.0: Input should be greater than or equal to 0"),
        ("seeds = [1.5]", "seeds.0: Input should be a valid integer"),
        ('preset = "bogus"', "preset: Input should be 'quick' or 'paper'"),
        ('device = "tpu"', "device: String should match"),
        ("demos = 1000000000", "demos: Input should be less than or equal to 1000000"),
        ('methods = ["mlp", "mlp"]', "envs, methods and seeds must each be listed once"),
        ("report = 1", "report: Input should be a valid boolean"),
        ("eval_seeds = [0, 0]", "eval_seeds: list each evaluation seed once"),
        ("eval_seeds = []", "eval_seeds: List should have at least 1 item"),
        ("eval_episodes = 200000", "eval_episodes: Input should be less than or equal to 100000"),  # eval's cap
        ("snapshot_at = [10]", "snapshot_at: 10 is not a multiple of 50"),  # where a quick training records
    ],
)
def test_grid_values_are_checked_strictly_at_load_time(tmp_path, line, words):
    key = line.split(" = ")[0]
    text = "\n".join(ln for ln in TINY.splitlines() if not ln.startswith(f"{key} ="))
    with pytest.raises(BadInput, match=words.replace("(", r"\(").replace("[", r"\[")) as err:
        load_grid(_grid(tmp_path, f"{line}\n{text}"))
    assert "grid.toml" in err.value.message
    if "listed once" not in words:  # a value's own error, given with --set, names the flag
        with pytest.raises(BadInput, match=rf"--set {key}="):
            load_grid(_grid(tmp_path, text), [line.replace(" = ", "=")])


def test_load_errors_name_the_set_that_gave_the_value_and_reuse_must_be_folders(tmp_path, capsys):
    grid = _grid(tmp_path, TINY)
    with pytest.raises(BadInput, match=r'^--set envs=\["nope"\]: envs: '):
        load_grid(grid, ['envs=["nope"]'])
    with pytest.raises(BadInput, match=r'^--set methods=\["nope"\]: methods'):
        load_grid(grid, ['methods=["nope"]'])
    # a variant may name methods and envs the grid does not run, but not ones that do not exist
    assert load_grid(_grid(tmp_path, TINY + '[[variants]]\nname = "v"\nenvs = ["maze"]\nmethods = ["diffuser"]\n'))
    for key in ("methods", "envs"):
        bad = _grid(tmp_path, TINY + f'[[variants]]\nname = "v"\n{key} = ["nope"]\n', "bad.toml")
        with pytest.raises(BadInput, match=rf"bad.toml: variant v: {key}"):
            load_grid(bad)
    with pytest.raises(BadInput, match=r"^--set eval_seed_offset=1: .*past the largest seed"):
        load_grid(grid, ["seeds=[4294967295]", "eval_seed_offset=1"])
    # a snapshot that checkpoint_every, set in the methods' train flags, puts on their loss curves passes
    every10 = _grid(tmp_path, TINY + '\n[[settings]]\ntrain = ["--set", "checkpoint_every=10"]\n', "every10.toml")
    assert load_grid(every10, ["snapshot_at=[10]"]).snapshot_at == [10]
    (tmp_path / "afile").write_text("x")
    with pytest.raises(BadInput, match=r"reuse: .*afile is a file, not a grid's `out` folder"):
        load_grid(grid, [f'reuse=["{tmp_path / "afile"}"]'])
    capsys.readouterr()
    spec = load_grid(grid, [f'reuse=["{tmp_path / "typo"}"]'])
    assert spec.reuse == [tmp_path / "typo"] and "typo: no such folder yet" in capsys.readouterr().err


def test_a_grid_never_writes_over_its_own_files_or_a_users_summary(tmp_path):
    from cdrb_cli.orchestration.grid import grid

    own = _grid(tmp_path, TINY.replace('out = "runs"', 'out = "."'), name="grid.json")  # a TOML file named grid.json
    before = own.read_text()
    with pytest.raises(BadInput, match="the grid file's or the current folder, not a folder of the grid's own"):
        grid(own, backend="pool", workers=1)
    assert own.read_text() == before
    (tmp_path / "runs").mkdir()
    (tmp_path / "runs" / "maze-tight").write_text("my notes\n")  # where the environment's folder goes
    with pytest.raises(BadInput, match="maze-tight: is a file where the grid keeps a folder of artifacts"):
        grid(_grid(tmp_path, TINY), dry_run=True)
    (tmp_path / "runs" / "maze-tight").unlink()
    for empty in ("", " "):  # "" would be "." to a path, " " a folder named so
        with pytest.raises(BadInput, match=f"out = {empty!r}: an empty path"):
            load_grid(_grid(tmp_path, TINY.replace('out = "runs"', f'out = "{empty}"')))
    mine = tmp_path / "runs" / "grid.json"
    mine.write_text("my notes\n")
    with pytest.raises(BadInput, match="exists and is not a grid summary"):
        grid(_grid(tmp_path, TINY), backend="pool", workers=1)
    assert mine.read_text() == "my notes\n"


def test_grid_tasks_do_not_import_modules_from_the_current_folder(tmp_path):
    marker = tmp_path / "imported"
    (tmp_path / "typer.py").write_text(f"open({str(marker)!r}, 'w').write('x')\nraise SystemExit(3)\n")
    text = TINY.replace('methods = ["mlp", "cdrb"]', 'methods = ["mlp"]').replace("seeds = [0, 1]", "seeds = [0]")
    grid = _grid(tmp_path, text)
    cdrb = Path(sys.executable).parent / "cdrb"  # the entry point: its own folder, not the current one, on sys.path
    env = dict(os.environ, OMP_NUM_THREADS="1")
    proc = subprocess.run(
        [str(cdrb), "grid", str(grid), "--backend", "pool", "-j", "1"],
        capture_output=True, text=True, cwd=tmp_path, env=env, timeout=600,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert not marker.exists()


def test_hostile_grid_files_and_memos_are_refused_or_redone_without_hanging(tmp_path):
    from cdrb_cli.orchestration.grid import MAX_TASKS, is_done, memo_path

    fifo = tmp_path / "fifo.toml"
    os.mkfifo(fifo)
    (tmp_path / "zero.toml").symlink_to("/dev/zero")
    big = tmp_path / "big.toml"
    big.write_text(TINY + "# " + "x" * (1 << 20) + "\n")
    for path in (fifo, tmp_path / "zero.toml", big):
        with pytest.raises(BadInput, match="not a grid file"):
            load_grid(path)
    deep = tmp_path / "deep.toml"
    deep.write_text("a" + ".a" * 5000 + " = 1\n" + TINY)
    with pytest.raises(BadInput, match="deep.toml"):
        load_grid(deep)
    seeds = ", ".join(str(i) for i in range(1000))
    with pytest.raises(BadInput, match=f"at most {MAX_TASKS:,}"):
        load_grid(_grid(tmp_path, TINY.replace("seeds = [0, 1]", f"seeds = [{seeds}]") + "".join(
            f'[[variants]]\nname = "v{i}"\n' for i in range(60)
        )))  # fmt: skip

    spec = load_grid(_grid(tmp_path, TINY))
    task = expand(spec)[0]
    memo = memo_path(spec, task)
    memo.parent.mkdir(parents=True)
    for make in (
        lambda: os.mkfifo(memo),
        lambda: memo.symlink_to("/dev/zero"),
        lambda: memo.write_text("[" * 200_000 + "]" * 200_000),
    ):
        make()
        t = time.time()
        assert not is_done(spec, task, {})  # a stale memo: the task is redone
        assert time.time() - t < 10
        memo.unlink()


def _train_pids(grid_out: Path) -> list[int]:
    """Trainings of ``grid_out`` running as fresh `python -m cdrb_cli train` processes (a Ray worker's tasks)."""
    pids = []
    for pid in os.listdir("/proc"):
        try:
            cmd = Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ").decode()
        except OSError:
            continue
        if pid.isdigit() and "cdrb_cli train" in cmd and str(grid_out) in cmd:
            pids.append(int(pid))
    return pids


def _tree(root: int) -> set[int]:
    """``root`` and every process below it (from /proc's parent ids)."""
    parents = {}
    for pid in filter(str.isdigit, os.listdir("/proc")):
        try:
            parents[int(pid)] = int(Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[1])
        except (OSError, IndexError, ValueError):
            continue
    tree, grew = {root}, True
    while grew:
        below = {p for p, parent in parents.items() if parent in tree} - tree
        tree |= below
        grew = bool(below)
    return tree


def _alive(pids: set[int]) -> set[int]:
    """Those of ``pids`` still running (a zombie has stopped)."""
    out = set()
    for pid in pids:
        try:
            state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
        except (OSError, IndexError):
            continue
        if state != "Z":
            out.add(pid)
    return out


@pytest.mark.parametrize("warm", ["1", "0"])
@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGKILL])
def test_a_stopped_grid_leaves_no_task_running(tmp_path, sig, warm):
    """SIGTERM: the grid stops its running tasks and exits 130 at once (a training keeps its checkpoint); SIGKILL:
    the tasks die with it. Either way no process the grid started (a task, the warm server and its forks, or a
    fresh process per task) outlives it by more than a few seconds, and none leaves a scratch folder behind."""
    text = TINY.replace('methods = ["mlp", "cdrb"]', 'methods = ["mlp"]').replace("seeds = [0, 1]", "seeds = [0]")
    grid = _grid(tmp_path, text.replace("steps = 20", "steps = 100000"))
    scratch = tmp_path / "scratch"  # the grid's temp folder
    scratch.mkdir()
    proc = subprocess.Popen(
        [sys.executable, "-m", "cdrb_cli", "grid", str(grid), "--backend", "pool", "-j", "1"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
        env=dict(os.environ, OMP_NUM_THREADS="1", CDRB_GRID_WARM=warm, TMPDIR=str(scratch)),
    )  # fmt: skip
    lock = tmp_path / "runs" / "maze-tight" / ".mlp-s0.h5.lock"  # held by the training while it runs
    deadline = time.time() + 300
    while not lock.exists() and time.time() < deadline:
        time.sleep(0.2)
    assert lock.exists(), "the training never started"
    time.sleep(3)
    started = _tree(proc.pid) - {proc.pid}
    assert started, "the grid runs its training in a process of its own"
    made = [p.name for p in scratch.iterdir()]
    proc.send_signal(sig)
    t = time.time()
    rc = proc.wait(timeout=30)
    assert rc == (130 if sig == signal.SIGTERM else -9)
    assert time.time() - t < 15
    while _alive(started) and time.time() - t < 10:
        time.sleep(0.2)
    assert not _alive(started)
    if warm == "1":
        assert any(name.startswith("cdrb-warm-") for name in made), made
    # torchinductor_<user>: torch's cache, one per user and reused, not a run's scratch
    assert [p.name for p in scratch.iterdir() if not p.name.startswith("torchinductor_")] == []


def test_warm_tasks_write_what_fresh_processes_write(tmp_path):
    """The pool's warm server forks each task from a process that imported cdrb once; the artifacts are those of a
    fresh `python -m cdrb_cli` per task, bit for bit (timings aside), and a task's failure reads the same."""
    import h5py
    import numpy as np

    text = TINY.replace("seeds = [0, 1]", "seeds = [0]") + '\n[[variants]]\nname = "v"\n'
    text += '\n[[variants]]\nname = "bad"\nmethods = ["mlp"]\ntrain = ["--set", "lr=1e30"]\n'  # diverges
    arrays, failures = {}, {}
    for warm in (False, True):
        spec = load_grid(_grid(tmp_path, text.replace('out = "runs"', f'out = "runs-{warm}"'), f"g{warm}.toml"))
        backend = PoolBackend(2, warm=warm)
        try:
            run = run_grid(spec, backend)
        finally:
            backend.close()
        failures[warm] = {r.id: r.stderr[-1].replace(str(spec.out), "OUT") for r in run.results if r.status == "failed"}
        found = {}
        for path in sorted(spec.out.rglob("*.h5")):
            with h5py.File(path) as f:
                names = []
                f.visit(names.append)
                for name in names:
                    obj = f[name]
                    if isinstance(obj, h5py.Dataset) and "seconds" not in name and obj.dtype.kind in "fiub":
                        found[(str(path.relative_to(spec.out)), name)] = obj[()]
        arrays[warm] = found
    assert failures[True] == failures[False] and len(failures[True]) == 1, failures
    assert arrays[True].keys() == arrays[False].keys() and len(arrays[True]) > 20
    for key, value in arrays[False].items():
        assert np.array_equal(value, arrays[True][key]), key


def test_a_warm_server_of_older_code_is_replaced_and_finishes_its_tasks(tmp_path, own_warm_servers):
    """Code edited while a grid runs: the server that imported the old code takes no new task (a fork would mix old
    modules with new ones it imports later); the next task gets a new server."""
    import cdrb_cli.errors as module

    backend = PoolBackend(1, warm=True)
    payload = {"argv": ["envs"], "kind": "report", "outputs": [str(tmp_path / "x")], "cpus": 1}
    path = Path(module.__file__)
    before = path.stat()
    try:
        assert backend.submit(payload).result()["rc"] == 0
        first = backend._server
        assert not first.stale()
        os.utime(path)  # the package's code is newer than the server
        assert first.stale()
        assert backend.submit(payload).result()["rc"] == 0
        assert backend._server is not first and backend._retired == [first]
        first.proc.wait(timeout=30)  # it ends by itself, its tasks done
    finally:
        os.utime(path, ns=(before.st_atime_ns, before.st_mtime_ns))
        backend.close()


def test_file_flags_in_a_grid_are_relative_to_the_file_that_declares_them(tmp_path):
    """`--config tiny.toml` in a grid's settings (or in an included file, or a variant) means the file beside
    that grid or settings file, as `out` does, from whatever folder the grid is run; absolute paths stay."""
    sub = tmp_path / "exp"
    (sub / "shared").mkdir(parents=True)
    (sub / "shared" / "common.toml").write_text('[[settings]]\nmethod = "mlp"\ntrain = ["--config", "mlp.toml"]\n')
    text = (
        'include = ["shared/common.toml"]\n'
        + TINY
        + (
            '[[settings]]\nmethod = "cdrb"\ntrain = ["--config=cdrb.toml"]\n'
            f'[[variants]]\nname = "abs"\ntrain = ["--config", "{tmp_path / "abs.toml"}"]\n'
        )
    )
    grid = _grid(sub, text)
    for f in (sub / "shared" / "mlp.toml", sub / "cdrb.toml", tmp_path / "abs.toml"):  # a named file must exist
        f.write_text("")
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    proc = _cli("grid", str(grid), "--dry-run", cwd=elsewhere)
    assert proc.returncode == 0, proc.stderr
    lines = proc.stdout.splitlines()
    assert any(f"--config {sub / 'shared' / 'mlp.toml'}" in ln for ln in lines if "--method mlp" in ln)
    assert any(f"--config={sub / 'cdrb.toml'}" in ln for ln in lines if "--method cdrb" in ln)
    assert any(f"--config {tmp_path / 'abs.toml'}" in ln for ln in lines)
    proc = _cli("grid", str(grid), "--dry-run", "--json", cwd=elsewhere)
    tasks = json.loads(proc.stdout)  # the same tasks as a list, for scripts
    assert [" ".join(["cdrb", *t["argv"]]) for t in tasks] == [" ".join(ln.split()) for ln in lines]
    assert {t["kind"] for t in tasks} == {"collect", "cluster", "train", "eval", "report"}


def test_a_second_grid_on_the_same_out_names_the_grid_file_not_a_flag(tmp_path):
    """While another run holds OUT/grid.json, the grid stops in one line naming its file and `out` (the user
    passed no --out)."""
    from cdrb_cli import artifacts

    grid = _grid(tmp_path)
    (tmp_path / "runs").mkdir()
    with artifacts.claim_output(tmp_path / "runs" / "grid.json", force=True):
        proc = _cli("grid", str(grid), "--backend", "pool")
    lines = proc.stderr.strip().splitlines()
    assert proc.returncode == 2 and len(lines) == 1 and "another cdrb run" in lines[0], proc.stderr
    assert f"{grid}: out =" in lines[0] and "--out" not in lines[0]


def test_files_named_by_eval_flags_are_inputs_and_their_writers_come_first(tmp_path):
    """An eval that reads a map file hashes it in its memo (editing the map re-runs it); one that reads a buffer
    the grid writes runs after the clustering that writes it."""
    text = (
        TINY
        + """
[[variants]]
name = "plain"

[[variants]]
name = "routed"
methods = ["cdrb"]
eval = ["--maze-map", "maps/closed.txt", "--route-buffer", "runs/maze-tight/buffer-k50.h5", "--set", "avoid.route_k=2"]
"""
    )
    (tmp_path / "maps").mkdir()
    shutil.copy(ROOT / "experiments" / "maps" / "maze-tight-closed-north.txt", tmp_path / "maps" / "closed.txt")
    tasks = {t.id: t for t in expand(load_grid(_grid(tmp_path, text)))}
    ev = tasks["eval maze-tight/routed/cdrb-s0"]
    buffer = (tmp_path / "runs" / "maze-tight" / "buffer-k50.h5").resolve()
    inputs = {p.resolve() for p in ev.inputs}
    assert (tmp_path / "maps" / "closed.txt").resolve() in inputs and buffer in inputs
    writer = next(t.id for t in tasks.values() if buffer in [p.resolve() for p in t.outputs])
    assert writer.startswith("cluster") and writer in ev.deps
    assert "train maze-tight/cdrb-s0" in ev.deps


# ------------------------------------------------------------------------------------------------ reuse
def test_a_grid_reuses_the_finished_runs_of_another_down_to_a_snapshot(tmp_path):
    """A test grid with `reuse` reads a tuning grid's demos, buffer and models where it ran the same commands: a
    training of S steps is the curve run's snapshot at S; other seeds, other flags and altered files are run here."""
    curves = TINY.replace('methods = ["mlp", "cdrb"]', 'methods = ["cdrb"]').replace('out = "runs"', 'out = "curves"')
    curves = curves.replace("steps = 20", 'steps = 100\nsnapshot_at = [50]\nreport = false\neval_stream = "tune"')
    curves = curves.replace("seeds = [0, 1]", "seeds = [0]")
    proc = _cli("grid", str(_grid(tmp_path, curves, "curves.toml")), "--backend", "pool", "-j", "2")
    assert proc.returncode == 0, proc.stderr[-2000:]
    table = TINY.replace('methods = ["mlp", "cdrb"]', 'methods = ["cdrb"]').replace("steps = 20\n", "")
    # the flags `cdrb select` writes repeat what the grid's settings already pass: the same command
    chosen = 'train = ["--set", "method.diffusion_steps=8", "--steps", "50"]'
    table = 'reuse = ["curves"]\n' + table + f'\n[[settings]]\nmethod = "cdrb"\n{chosen}\n'
    grid = _grid(tmp_path, table, "table.toml")
    spec = spec_run = load_grid(grid)
    tasks = {t.id: t for t in expand(spec)}
    curve_dir = (tmp_path / "curves" / "maze-tight").resolve()
    # seed 0 is the curve run's snapshot; seed 1 has no curve run and trains here, on the curve grid's demos/buffer
    assert sorted(t for t in tasks if t.split()[0] in ("collect", "cluster", "train")) == ["train maze-tight/cdrb-s1"]
    assert spec._reused["train maze-tight/cdrb-s0"] == str(curve_dir / "cdrb-s0.step50.h5")
    ev = tasks["eval maze-tight/cdrb-s0"]
    assert ev.argv[1] == str(curve_dir / "cdrb-s0.step50.h5") and ev.deps == []
    train1 = tasks["train maze-tight/cdrb-s1"].argv
    assert str(curve_dir / "demos.h5") in train1 and str(curve_dir / "buffer-k50.h5") in train1
    # the length must be one the curve run wrote, the flags the same
    for other in ('train = ["--steps", "60"]', 'train = ["--steps", "50", "--set", "method.diffusion_steps=4"]'):
        spec = load_grid(_grid(tmp_path, table.replace(chosen, other), "other.toml"))
        assert "train maze-tight/cdrb-s0" in {t.id for t in expand(spec)}, other
    # run: the test grid trains seed 1 only, and its seed-0 eval reads the snapshot
    proc = _cli("grid", str(grid), "--backend", "pool", "-j", "2", "--json")
    assert proc.returncode == 0, proc.stderr[-2000:]
    summary = json.loads(proc.stdout)
    assert "train maze-tight/cdrb-s1" in {t["id"] for t in summary["tasks"]}
    assert set(summary["reused"]) == {"collect maze-tight", "cluster maze-tight", "train maze-tight/cdrb-s0"}
    assert "taken from finished runs of" in proc.stderr
    from cdrb_cli import artifacts

    manifest = artifacts.load(tmp_path / "runs" / "maze-tight" / "eval-cdrb-s0.h5").manifest
    snap_sha = artifacts.sha256_file(curve_dir / "cdrb-s0.step50.h5")
    assert any(p.sha256 == snap_sha for p in manifest.parents)
    assert not (tmp_path / "runs" / "maze-tight" / "cdrb-s0.h5").exists()
    # the same reuse through a link to the curves' folder, past memos of any odd shape (never hashing a FIFO)
    from cdrb_cli import __version__

    (tmp_path / "link").symlink_to(tmp_path / "curves")
    memos = tmp_path / "curves" / ".grid"
    os.mkfifo(tmp_path / "fifo")
    odd = {str(tmp_path / "fifo"): "0" * 64, str(tmp_path): "0" * 64}
    for i, memo in enumerate(
        [
            {"argv": ["train"], "inputs": [], "outputs": "x", "cdrb": __version__},
            {"argv": ["collect", "maze"], "inputs": {}, "outputs": odd, "cdrb": __version__},
            {"argv": ["train", "--snapshot-at", "²"], "inputs": {}, "outputs": odd, "cdrb": __version__},
            [1, 2],
        ]
    ):
        (memos / f"odd{i}.json").write_text(json.dumps(memo))
    (memos / "odd9.json").write_text("{not json")
    linked = load_grid(_grid(tmp_path, table.replace('reuse = ["curves"]', 'reuse = ["link"]'), "linked.toml"))
    assert "train maze-tight/cdrb-s0" not in {t.id for t in expand(linked)}
    # --set order does not matter unless one key lies inside another
    moved = chosen.replace('"--set"', '"--set", "net.dim=8", "--set"', 1)
    spec = load_grid(_grid(tmp_path, table.replace(chosen, moved), "o.toml"))
    assert "train maze-tight/cdrb-s0" not in {t.id for t in expand(spec)}
    from cdrb_cli.orchestration.grid import parse_command

    inner, outer = ["--set", "controller.gain=2"], ["--set", "controller={kp = 1}"]
    assert parse_command(["eval", "m.h5", *inner, *outer])[2] != parse_command(["eval", "m.h5", *outer, *inner])[2]
    # a curve file that changes after the grid took it (a curve trained on meanwhile) is never read: the task
    # fails; expanded again, it is not reused: the test grid trains that model itself
    with open(curve_dir / "cdrb-s0.step50.h5", "ab") as fh:
        fh.write(b"\0")
    from cdrb_cli.orchestration.grid import make_backend, run_grid

    backend = make_backend("pool", 1, None)
    try:
        run = run_grid(spec_run, backend, retries=0, tasks=[ev])
    finally:
        backend.close()
    assert [r.status for r in run.results] == ["failed"] and "changed since this grid took it" in run.results[0].stderr[
        0
    ]
    assert "train maze-tight/cdrb-s0" in {t.id for t in expand(load_grid(grid))}
    with pytest.raises(BadInput, match="reuse: names the grid's own"):
        load_grid(_grid(tmp_path, table.replace('reuse = ["curves"]', 'reuse = ["runs"]'), "self.toml"))
    for reuse, needle in (('[""]', "an empty path"), ('["curves", "curves/"]', "names a folder twice")):
        with pytest.raises(BadInput, match=needle):
            load_grid(_grid(tmp_path, table.replace('reuse = ["curves"]', f"reuse = {reuse}"), "bad.toml"))


def test_a_finished_curve_is_extended_by_resuming_its_runs(tmp_path):
    """A curve run to 50 steps, then the same grid with steps = 100 and 50 among the snapshots: each run resumes
    from its finished model (not refused, not retrained), which becomes the snapshot at 50."""
    from cdrb_cli import artifacts

    text = TINY.replace('methods = ["mlp", "cdrb"]', 'methods = ["mlp"]').replace("seeds = [0, 1]", "seeds = [0]")
    grid = _grid(tmp_path, text.replace("steps = 20", "steps = 50\nreport = false"))
    assert _cli("grid", str(grid), "--backend", "pool").returncode == 0
    model = tmp_path / "runs" / "maze-tight" / "mlp-s0.h5"
    short = artifacts.sha256_file(model)
    proc = _cli("grid", str(grid), "--backend", "pool", "--set", "steps=100", "--set", "snapshot_at=[50]")
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert artifacts.sha256_file(model.with_name("mlp-s0.step50.h5")) == short
    assert artifacts.load(model, "model").manifest.state.step == 100


def test_a_method_no_variant_covers_is_warned_of(tmp_path, capsys):
    """With variants, only they run: a method or an environment none of them applies to is left out, and said so."""
    variant = '\n[[variants]]\nname = "b2"\nmethods = ["cdrb"]\neval = { avoid = { best_of = 2 } }\n'
    path = _grid(tmp_path, TINY + variant)
    assert not any("mlp" in t.id for t in expand(load_grid(path)) if t.kind in ("train", "eval"))
    assert "no variant applies to mlp on maze-tight" in capsys.readouterr().err
    load_grid(path, ['methods=["cdrb"]'])  # narrowed on purpose: no word
    assert "no variant applies" not in capsys.readouterr().err


def test_demos_for_an_environment_the_grid_does_not_run_is_warned_of(tmp_path, capsys):
    path = _grid(tmp_path, TINY + "\n[demos_for]\nmaze = 50\n")
    load_grid(path)
    assert "demos_for: maze: not among the grid's environments" in capsys.readouterr().err
    load_grid(path, ['envs=["maze-tight"]'])  # narrowed on purpose: no word
    assert "demos_for" not in capsys.readouterr().err


def test_a_dry_run_counts_the_snapshot_evals_an_extended_curve_keeps(tmp_path):
    """Extending a curve resumes its runs, which leave their earlier snapshots as they are: the dry run counts those
    snapshots' evals as up to date (as the run then finds them), but not where a changed setting starts runs over."""
    text = TINY.replace('methods = ["mlp", "cdrb"]', 'methods = ["mlp"]').replace("seeds = [0, 1]", "seeds = [0]")
    text = text.replace('"--set", "batch_size=8"', '"--set", "batch_size=8", "--set", "checkpoint_every=10"')
    grid = _grid(tmp_path, text.replace("steps = 20", "steps = 50\nsnapshot_at = [20]\nreport = false"))
    r = _cli("grid", str(grid), "--backend", "pool")
    assert r.returncode == 0, r.stderr[-2000:]
    longer = ("--set", "steps=100", "--set", "snapshot_at=[20, 50]")

    def up_to_date(*extra: str) -> list[str]:
        r = _cli("grid", str(grid), "--dry-run", *longer, *extra)
        assert r.returncode == 0, r.stderr
        return [line for line in r.stdout.splitlines() if line.startswith("# up to date:")]

    kept = up_to_date()
    assert any(" eval " in f" {line} " and "mlp-s0.step20.h5" in line for line in kept), kept
    # other data: the runs start over from new demos, so nothing they wrote is kept
    assert not any(" eval " in f" {line} " for line in up_to_date("--set", "demos=41")), "kept across new data"
    assert not any("mlp-s0.step50.h5" in line or "cdrb train" in line for line in kept), kept
    r = _cli("grid", str(grid), "--backend", "pool", *longer)
    assert r.returncode == 0, r.stderr[-2000:]
    summary = json.loads((tmp_path / "runs" / "grid.json").read_text())
    skipped = {t["id"] for t in summary["tasks"] if t["status"] == "up to date"}
    assert "eval maze-tight/mlp-s0.step20" in skipped, skipped  # as the dry run said
    # another learning rate: every run starts over, so no snapshot eval is counted as kept
    grid.write_text(grid.read_text().replace('"--set", "batch_size=8"', '"--set", "batch_size=8", "--set", "lr=0.002"'))
    assert not any(" eval " in f" {line} " for line in up_to_date("--set", "steps=150")), "kept across a restart"


def test_a_variant_may_give_its_settings_as_a_table(tmp_path):
    """A table of settings is the same command as its --set flags (so the same memo key), keys in the table's order;
    a setting the grid sets itself is refused when the file is read."""
    table = (
        TINY
        + '\n[[variants]]\nname = "tab"\nmethods = ["cdrb"]\n'
        + 'eval = { replan = "every:40", avoid = { best_of = 4 }, controller = { max_lag = 0.3 } }\n'
    )
    flags = (
        TINY
        + '\n[[variants]]\nname = "tab"\nmethods = ["cdrb"]\n'
        + 'eval = ["--set", "replan=\\"every:40\\"", "--set", "avoid.best_of=4", "--set", "controller.max_lag=0.3"]\n'
    )
    by_table = {t.id: t.argv for t in expand(load_grid(_grid(tmp_path, table, "a.toml")))}
    by_flags = {t.id: t.argv for t in expand(load_grid(_grid(tmp_path, flags, "b.toml")))}
    assert by_table == by_flags
    argv = by_table["eval maze-tight/tab/cdrb-s0"]
    assert argv[argv.index("--set") : argv.index("--set") + 2] == ["--set", 'replan="every:40"']
    clash = TINY + '\n[[variants]]\nname = "n"\neval = { episodes = 5 }\n'
    with pytest.raises(BadInput, match="the grid sets episodes of `cdrb eval` itself"):
        load_grid(_grid(tmp_path, clash, "c.toml"))


def test_a_memo_keys_what_a_command_asks_for_not_how_its_flags_are_spelled(tmp_path):
    """A finished task is up to date under any spelling of the same settings (a moved flag, its --set, a table; a
    value written another way) and under a memo written before memos had keys; a changed value is not."""
    from cdrb_cli.orchestration.grid.memo import is_done, memo_path

    base = TINY.replace('methods = ["mlp", "cdrb"]', 'methods = ["mlp"]').replace("seeds = [0, 1]", "seeds = [0]")
    variant = '\n[[variants]]\nname = "v"\neval = {}\n'
    path = _grid(tmp_path, base + variant.replace("{}", '["--max-lag", "0.3", "--set", "controller.kp=5"]'))
    backend = PoolBackend(1)
    try:
        run = run_grid(load_grid(path), backend)
    finally:
        backend.close()
    assert {r.status for r in run.results} == {"done"}

    def done(text: str) -> dict[str, bool]:
        path.write_text(base + variant.replace("{}", text))
        spec = load_grid(path)
        return {t.id: is_done(spec, t, {}) for t in expand(spec) if t.kind != "report"}

    spellings = [
        '["--set", "controller.max_lag=0.30", "--set", "controller.kp= 5"]',
        "{ controller = { kp = 5, max_lag = 0.3 } }",
        '["--set", "controller.kp=5", "--max-lag=0.3", "--max-lag", "0.3"]',
    ]
    for text in spellings:
        assert all(done(text).values()), text
    spec = load_grid(path)
    for task in expand(spec):  # memos as they were written before they had keys
        memo = memo_path(spec, task)
        if memo.exists():
            body = json.loads(memo.read_text())
            memo.write_text(json.dumps({k: v for k, v in body.items() if k not in ("key", "asked")}))
    assert all(done(spellings[1]).values())
    changed = done("{ controller = { kp = 5, max_lag = 0.4 } }")
    assert [i for i, ok in changed.items() if not ok] == ["eval maze-tight/v/mlp-s0"]


def test_include_fan_out_and_depth_are_bounded(tmp_path):
    """Four levels of a file that includes the next 40 times would expand to 2.56 M reads: each file is read once,
    the expansion is capped, and the error names the file that fans out; a 40-deep chain is refused too."""
    for level in range(4):
        nxt = f"l{level + 1}.toml"
        body = "[[settings]]\ntrain = []\n" if level == 3 else f"include = {[nxt] * 40!r}\n".replace("'", '"')
        (tmp_path / f"l{level}.toml").write_text(body)
    (tmp_path / "l4.toml").write_text("")
    grid = _grid(tmp_path, 'include = ["l0.toml"]\n' + TINY)
    started = time.time()
    with pytest.raises(BadInput, match=r"l\d.toml: its includes expand to more than 1000 settings files"):
        load_grid(grid)
    assert time.time() - started < 10
    for i in range(40):
        (tmp_path / f"c{i}.toml").write_text(f'include = ["c{i + 1}.toml"]\n')
    (tmp_path / "c40.toml").write_text("")
    with pytest.raises(BadInput, match="includes nest more than 32 files deep"):
        load_grid(_grid(tmp_path, 'include = ["c0.toml"]\n' + TINY, "deep.toml"))


@pytest.mark.parametrize(
    "methods, scoped, eval_, words",
    [
        ('["mlp"]', "", "{ controller = { look_ahead = -1 } }", "look_ahead"),
        ('["mlp"]', "", "{ controller = { look_ahead = true } }", "look_ahead"),
        ('["cdrb"]', "", "{ avoid = { best_of = 65 } }", "best_of"),
        ('["cdrb"]', "", '["--set", "avoid.guide_scale=nan"]', "guide_scale"),
        ('["cdrb"]', "", '{ protocol = "nosuch" }', "not a protocol"),
        ('["cdrb"]', "", '{ protocol = "detour" }', "detour"),
        ('["mlp", "diffuser"]', 'methods = ["diffuser"]', "{ avoid = { mask_buffer = true } }", "no replay buffer"),
        ('["mlp", "diffuser"]', 'methods = ["diffuser"]', "{ avoid = { route_k = 2 } }", "route"),
        ('["cdrb"]', "", '["--scene", "fifo.txt"]', "not a regular file"),
    ],
)
def test_a_variant_whose_evals_would_all_fail_is_refused_when_the_grid_is_read(tmp_path, methods, scoped, eval_, words):
    """Each variant's eval settings resolve as `cdrb eval` resolves them on the model its training will write, so a
    setting the eval refuses is one line at load (`--dry-run` too), naming the file, method and variant."""
    if "fifo" in eval_:
        os.mkfifo(tmp_path / "fifo.txt")
    text = TINY.replace('methods = ["mlp", "cdrb"]', f"methods = {methods}")
    text += f'\n[[variants]]\nname = "bad"\n{scoped}\neval = {eval_}\n'
    proc = _cli("grid", str(_grid(tmp_path, text)), "--dry-run")
    lines = proc.stderr.strip().splitlines()
    named = ("in variant bad: eval flags", "variants[0].eval")  # the variant, as the check that caught it names it
    assert proc.returncode == 2 and len(lines) == 1 and any(n in lines[0] for n in named), proc.stderr
    assert words in lines[0] and "grid.toml" in lines[0], lines[0]


def test_the_replanning_defaults_leave_a_time_indexed_clock_alone(tmp_path):
    """Re-planning adds the tuned look-ahead of the gated clock unless the eval asks for the time-indexed clock
    (controller.max_lag null), where a look-ahead means nothing: the grid and the eval accept the pair."""
    text = TINY.replace('methods = ["mlp", "cdrb"]', 'methods = ["mlp"]')
    text += '\n[[variants]]\nname = "r"\neval = { replan = "every:20", null = ["controller.max_lag"] }\n'
    tasks = expand(load_grid(_grid(tmp_path, text)))
    assert any(t.kind == "eval" and "every:20" in " ".join(t.argv) for t in tasks)


_START = {"pointmaze": PointMazeFamily.start_tuned}


@pytest.mark.parametrize(
    "flags, meant",
    [
        (["--set", 'protocol="anywhere"'], {"start_tuned": _START}),
        (["--protocol", "anywhere"], {"start_tuned": _START}),
        (
            ["--set", 'protocol="anywhere"', "--set", 'replan="every:40"'],
            {"start_tuned": _START, "replan_tuned": "by default"},
        ),
        ([], {}),
        (["--set", 'protocol="official-code"'], {}),
    ],
)
def test_a_memo_records_the_defaults_an_eval_takes_from_its_protocol(flags, meant, monkeypatch):
    """An eval from anywhere takes the family's choice for plans from anywhere: a memo written before that default
    (or before it changed) meant something else, and is out of date."""
    from cdrb_cli.orchestration.grid.memo import _meaning
    from cdrb_cli.orchestration.grid.spec import Task

    task = Task("eval x", "eval", ["eval", "model.h5", *flags, "--out", "e.h5"], [Path("e.h5")])
    assert _meaning(task) == meant
    if meant:
        monkeypatch.setattr(PointMazeFamily, "start_tuned", {"cdrb": {"avoid.best_of": 2}})
        assert _meaning(task) != meant


def test_a_grid_trains_over_its_own_models_when_a_setting_or_the_data_change(tmp_path):
    """A model the grid wrote is its own: after a training setting (or the data) changes it is trained again with
    the new one, where resuming would refuse a file of other settings; a model the memo does not vouch for is
    still never trained over."""
    text = TINY.replace('methods = ["mlp", "cdrb"]', 'methods = ["mlp"]').replace("seeds = [0, 1]", "seeds = [0]")
    text = text.replace("steps = 20\n", "steps = 20\nsnapshot_at = [10]\n")
    path = _grid(tmp_path, text.replace('"batch_size=8"]', '"batch_size=8", "--set", "checkpoint_every=10"]'))
    assert _cli("grid", str(path), "-j", "1").returncode == 0
    model = tmp_path / "runs" / "maze-tight" / "mlp-s0.h5"
    assert artifacts.load(model, "model").manifest.config.lr != 0.01
    path.write_text(path.read_text() + '[[settings]]\ntrain = ["--set", "lr=0.01"]\n')
    for change, check in (
        ([], lambda m: m.manifest.config.lr == 0.01),
        (["--set", "demos=41"], lambda m: m.manifest.parents[0].data_sha256
         == artifacts.load(tmp_path / "runs" / "maze-tight" / "demos.h5", "demos").data_sha256),
    ):  # fmt: skip
        r = _cli("grid", str(path), "-j", "1", *change)
        assert r.returncode == 0, r.stderr[-2000:]
        assert check(artifacts.load(model, "model"))
        snap = artifacts.load(model.with_name("mlp-s0.step10.h5"), "model")
        assert snap.manifest.parents == artifacts.load(model, "model").manifest.parents
    # the data and the list of snapshots changed together: still its own model, trained over
    r = _cli("grid", str(path), "-j", "1", "--set", "demos=42", "--set", "snapshot_at=[]")
    assert r.returncode == 0, r.stderr[-2000:]
    demos = artifacts.load(tmp_path / "runs" / "maze-tight" / "demos.h5", "demos")
    assert artifacts.load(model, "model").manifest.parents[0].data_sha256 == demos.data_sha256
    # a file of the same name the grid did not write is refused, not trained over
    shutil.copy(model.with_name("mlp-s0.step10.h5"), model)  # another file: not the memo's
    r = _cli("grid", str(path), "-j", "1", "--set", "steps=30")
    assert r.returncode != 0 and "train maze-tight/mlp-s0" in r.stderr
    assert "move or remove that one" in r.stderr and "--force" not in r.stderr, r.stderr[-2000:]
    assert artifacts.load(model, "model").manifest.state.step == 10


def test_the_grid_rewrites_a_fix_by_what_a_task_left_as_data_not_by_its_words():
    """A task's hint to pass --force becomes the grid's own advice only where the task's error record says an output
    blocked it (the grid takes no --force); a hint that merely mentions --force is left as the command gave it."""
    from cdrb_cli.orchestration.grid.run import _grid_hint
    from cdrb_cli.orchestration.grid.spec import Task

    task = Task(id="report", kind="report", argv=["report", "a.h5", "--out", "r.md"], inputs=[], outputs=[Path("r.md")])
    said = ["loading a.h5", "error: --out r.md: file exists (pass --force to overwrite it, or choose another path)"]
    blocked = {"message": "--out r.md: file exists", "hint": "pass --force to overwrite it, or choose another path"}
    got = _grid_hint(task, {"stderr": said, "error": {**blocked, "output_exists": "r.md"}})
    assert got[0] == "loading a.h5" and got[1].startswith("error: --out r.md: file exists (")
    assert "--force" not in got[1] and "move or remove that one" in got[1]
    for error in ({**blocked, "output_exists": None}, None, {}):
        assert _grid_hint(task, {"stderr": said, "error": error}) == said  # no output named: the words stand
    own = Task(id="report", kind="report", argv=[*task.argv, "--force"], inputs=[], outputs=[Path("r.md")])
    assert _grid_hint(own, {"stderr": said, "error": {**blocked, "output_exists": "r.md"}}) == said
