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


@pytest.fixture
def cdrb():
    return run_cdrb


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
