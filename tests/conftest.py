import os
import subprocess
import sys
from pathlib import Path

import pytest

os.environ.setdefault("MPLBACKEND", "Agg")
# the test artifacts are small: a read that takes longer than this is a hang (see artifacts._guarded_probe)
os.environ.setdefault("CDRB_READ_TIMEOUT", "10")
# Under pytest-xdist (`./dev.sh test` runs one worker per core) each worker and the CLI subprocesses it starts get
# one torch/OpenMP thread: two workers with a thread per core each spin against each other and run slower than
# one worker alone. Set before anything imports torch; cdrb's own set-up reads OMP_NUM_THREADS.
if os.environ.get("PYTEST_XDIST_WORKER"):
    os.environ["OMP_NUM_THREADS"] = "1"
    os.environ["MKL_NUM_THREADS"] = "1"

ROOT = Path(__file__).resolve().parent.parent


def run_cdrb(*args, cwd=None, env=None, timeout=600):
    """Run the real CLI in a subprocess; returns CompletedProcess with text stdout/stderr."""
    full_env = dict(os.environ)
    full_env.update(env or {})
    return subprocess.run(
        [sys.executable, "-m", "cdrb_cli", *map(str, args)],
        cwd=cwd,
        env=full_env,
        capture_output=True,
        text=True,
        timeout=timeout,
    )


def call_cdrb(*args, cwd=None, env=None, timeout=None):
    """Run the CLI's entry point (`cdrb_cli.cli.main`) in this process, as `python -m cdrb_cli` would in a fresh
    one: the same argument parsing, exit codes and output, with stdout and stderr captured, the environment
    variables ``env`` set and the working folder ``cwd`` for the call, and this process's state (environment,
    folder, torch threads, quiet flag) restored after it. It saves a fresh interpreter's imports per command
    (torch alone is ~2 s). Tests of what only a real process shows (signals, kills, import-time settings) start
    one themselves (``run_cdrb``). ``timeout`` is accepted for the same signature and not enforced."""
    import contextlib
    import io
    import traceback

    import torch

    from cdrb_cli import cli, ui

    out, err = io.StringIO(), io.StringIO()
    saved_env, saved_cwd, threads, quiet = dict(os.environ), os.getcwd(), torch.get_num_threads(), ui._quiet
    try:
        os.environ.update({k: str(v) for k, v in (env or {}).items()})
        if cwd is not None:
            os.chdir(cwd)
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
            try:
                code = cli.main([str(a) for a in args])
            except SystemExit as exc:  # as the interpreter would exit
                code = exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 1)
            except BaseException:  # what an uncaught exception does to a process: a traceback and exit 1
                traceback.print_exc()
                code = 1
    finally:
        os.chdir(saved_cwd)
        os.environ.clear()
        os.environ.update(saved_env)
        torch.set_num_threads(threads)
        ui.set_quiet(quiet)
    return subprocess.CompletedProcess(["cdrb", *map(str, args)], code, out.getvalue(), err.getvalue())


@pytest.fixture
def cdrb():
    return call_cdrb


@pytest.fixture(scope="session")
def small_data(tmp_path_factory):
    """A small Maze Tight dataset shared by the training tests: 40 demos and a 100-point buffer."""
    from cdrb_cli.configs import ClusterConfig
    from cdrb_cli.envs.registry import make_spec
    from cdrb_cli.stages.cluster import cluster
    from cdrb_cli.stages.collect import collect, collect_config

    root = tmp_path_factory.mktemp("data")
    spec = make_spec("maze-tight")
    demos = collect(spec, collect_config(spec, episodes=40, seed=0, valid_fraction=0.1), root / "demos.h5")
    buffer = cluster(demos, ClusterConfig(k=100, seed=0), root / "buffer.h5")
    return demos, buffer


@pytest.fixture(scope="session")
def tiny_models(small_data, tmp_path_factory):
    """CDRB, Diffuser and the MLP trained 30 steps at the tiny settings on ``small_data``, shared by the planning
    tests (untrained in effect: what they test holds for any weights)."""
    from cdrb_cli.methods.config import train_config
    from cdrb_cli.stages.train import train
    from tests.test_train import tiny

    demos, buffer = small_data
    root = tmp_path_factory.mktemp("models")
    out = {}
    for method in ("cdrb", "diffuser", "mlp"):
        b = buffer if method == "cdrb" else None
        cfg = train_config(demos, b, method, tiny(method, steps=30, checkpoint_every=30))
        out[method] = train(demos, b, cfg, root / f"{method}.h5")
    return out


class _SharedWarmServer:
    """The test worker's one warm grid server as a grid's backend sees it: every grid this process runs forks its
    tasks from it (each request carries its task's argv, folder and environment), and a backend's ``close`` or
    ``retire`` leaves it running for the next test; it is closed when the session ends."""

    def __init__(self, server):
        self.server = server

    def __getattr__(self, name):
        return getattr(self.server, name)

    def close(self) -> None:
        pass

    def retire(self) -> None:
        pass


@pytest.fixture(scope="session", autouse=True)
def _one_warm_server():
    """One warm grid server per test worker instead of one per grid: the server imports torch, MuJoCo and the rest
    (~5 s of CPU here) before its first fork, which dozens of tests' grids would each pay. It is started here, in
    the main thread, because the kernel ends it (PR_SET_PDEATHSIG) when the thread that started it ends, and a
    grid's pool thread ends with its grid. A test of the server's own life (``own_warm_servers``) gets fresh ones;
    a server made stale by an edit of the package's code is replaced as a grid would replace it.
    CDRB_TEST_SHARED_WARM=0 turns the sharing off."""
    if not sys.platform.startswith("linux") or os.environ.get("CDRB_TEST_SHARED_WARM") == "0":
        yield
        return
    from cdrb_cli.orchestration.grid import warm

    real = warm.WarmServer
    shared = _SharedWarmServer(real())

    def server():
        if shared.server.proc.poll() is not None or shared.server.stale():
            return real()  # a server of its own, which the backend closes as usual
        return shared

    server.__wrapped__ = real
    warm.WarmServer = server
    try:
        yield
    finally:
        warm.WarmServer = real
        shared.server.close()


@pytest.fixture
def own_warm_servers(monkeypatch):
    """Grids in this test start servers of their own (a test of a server's start, retirement or end)."""
    from cdrb_cli.orchestration.grid import warm

    monkeypatch.setattr(warm, "WarmServer", getattr(warm.WarmServer, "__wrapped__", warm.WarmServer))
