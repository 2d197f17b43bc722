"""`cdrb grid` (issue 19): the grid file, its stage graph, execution on a local pool and on a local Ray instance,
a worker killed mid-task, a failing task, and re-running a finished grid."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from cdrb_cli import artifacts
from cdrb_cli.errors import BadInput
from cdrb_cli.stages.grid import PoolBackend, expand, load_grid, run_grid

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


def _cli(*args: str, cwd: Path | None = None) -> subprocess.CompletedProcess:
    env = dict(os.environ, OMP_NUM_THREADS="1")
    return subprocess.run(
        [sys.executable, "-m", "cdrb_cli", *args], capture_output=True, text=True, cwd=cwd, env=env, timeout=600
    )


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
        (TINY + '\n[[settings]]\nenv = "mazee"\n', "settings[2].env"),
        (TINY + '\n[[settings]]\nmethod = "mlp"\ncollect = ["--workers", "1"]\n', "every method shares"),
        (TINY + "\n[resources.training]\ncpus = 2\n", "training"),
        (TINY + '\n[[variants]]\nname = "a/b"\n', "variants.0.name"),
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


def test_missing_grid_file_and_ray_flags(tmp_path):
    proc = _cli("grid", str(tmp_path / "nope.toml"))
    assert proc.returncode == 2 and "no such grid file" in proc.stderr
    proc = _cli("grid", str(_grid(tmp_path)), "--backend", "pool", "--address", "ray://x:1")
    assert proc.returncode == 2 and "--address" in proc.stderr and len(proc.stderr.strip().splitlines()) == 1


# ------------------------------------------------------------------------------------------------ execution
def _outputs(run) -> dict[str, float]:
    return {p: os.stat(p).st_mtime_ns for r in run.results for p in r.outputs}


def test_local_pool_runs_the_grid_and_a_rerun_does_no_work(tmp_path):
    spec = load_grid(_grid(tmp_path))
    backend = PoolBackend(2)
    try:
        run = run_grid(spec, backend)
    finally:
        backend.close()
    assert [r.status for r in run.results] == ["done"] * len(run.results)
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

    # one output removed: that task and only what depends on it run again (the CLI decides for the others)
    Path(run.results[[r.id for r in run.results].index("eval maze-tight/cdrb-s1")].outputs[0]).unlink()
    backend = PoolBackend(1)
    try:
        third = run_grid(spec, backend)
    finally:
        backend.close()
    ran = sorted(r.id for r in third.results if r.status == "done")
    assert ran == ["eval maze-tight/cdrb-s1", "report"]


def _kill_when_running(pattern: str, after: float, killed: list, stop: threading.Event) -> None:
    """SIGKILL the first process whose command line contains ``pattern`` once it has run ``after`` seconds."""
    seen: dict[int, float] = {}
    while not stop.is_set() and not killed:
        for pid in os.listdir("/proc"):
            if not pid.isdigit():
                continue
            try:
                cmd = Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ").decode()
            except OSError:
                continue
            if "cdrb_cli" in cmd and pattern in cmd:
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
        target=_kill_when_running, args=(f"{spec.out}/maze-tight/mlp-s0.h5 --device", 4.0, killed, stop)
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
    text = TINY + '\n[[settings]]\nmethod = "mlp"\ntrain = ["--set", "net.hidden=lots"]\n'
    grid = _grid(tmp_path, text)
    proc = _cli("grid", str(grid), "--backend", "pool", "-j", "2")
    assert proc.returncode == 1 and proc.stdout == ""
    assert proc.stderr.strip().splitlines()[-1].startswith("error: 2 of 11 grid tasks failed")
    summary = json.loads((tmp_path / "runs" / "grid.json").read_text())
    status = {t["id"]: t for t in summary["tasks"]}
    for seed in (0, 1):
        failed = status[f"train maze-tight/mlp-s{seed}"]
        assert failed["status"] == "failed" and failed["attempts"] == 2
        assert any("net.hidden" in line for line in failed["stderr"])  # the command's own one-line error
        assert status[f"eval maze-tight/mlp-s{seed}"]["status"] == "skipped"
        assert status[f"eval maze-tight/cdrb-s{seed}"]["status"] == "done"
    assert status["report"]["status"] == "skipped"
    assert not (tmp_path / "runs" / "maze-tight" / "mlp-s0.h5").exists()


def test_ray_runs_the_same_grid(tmp_path):
    pytest.importorskip("ray")
    text = TINY.replace('methods = ["mlp", "cdrb"]', 'methods = ["mlp"]')
    grid = _grid(tmp_path, text)
    proc = _cli("grid", str(grid), "--backend", "ray", "-j", "2")
    assert proc.returncode == 0, proc.stderr[-2000:]
    summary_path = Path(proc.stdout.strip())
    assert summary_path == (tmp_path / "runs" / "grid.json").resolve()
    summary = json.loads(summary_path.read_text())
    assert summary["backend"] == "ray" and summary["counts"]["done"] == 6
    assert "mlp" in (tmp_path / "runs" / "report.md").read_text()
    # a finished grid run again on the pool: nothing to do
    proc = _cli("grid", str(grid), "--backend", "pool", "--json")
    assert proc.returncode == 0 and json.loads(proc.stdout)["counts"]["up to date"] == 6


def test_the_shipped_grid_files_load_and_expand():
    root = Path(__file__).resolve().parent.parent / "grids"
    files = sorted(root.glob("*.toml"))
    assert files
    for path in files:
        spec = load_grid(path)
        tasks = expand(spec)
        trains = [t for t in tasks if t.kind == "train"]
        assert len(trains) == len(spec.envs) * len(spec.methods) * len(spec.seeds)
        assert all("--stream" in t.argv and "test" in t.argv for t in tasks if t.kind == "eval")
