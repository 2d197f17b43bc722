"""Every method trains, plans or acts, and is evaluated on a CUDA device, and a CUDA-trained model runs on the CPU.

Skipped where torch sees no GPU (CI); run on a GPU machine with ``pytest tests/test_cuda.py``. The CPU tests cannot
catch a tensor or random generator left on the wrong device, which only fails once a GPU is there.
"""

from __future__ import annotations

import numpy as np
import pytest

torch = pytest.importorskip("torch")
pytestmark = pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")

from cdrb_cli import artifacts  # noqa: E402
from cdrb_cli.methods.config import train_config  # noqa: E402
from cdrb_cli.stages.train import train  # noqa: E402
from tests.test_policies import TINY_BC, TINY_QL  # noqa: E402
from tests.test_train import TINY, TINY_MLP  # noqa: E402

SETTINGS = {"cdrb": TINY, "diffuser": TINY, "mlp": TINY_MLP, "diffusion-bc": TINY_BC, "diffusion-ql": TINY_QL}


@pytest.mark.parametrize("method", sorted(SETTINGS))
def test_method_trains_and_is_evaluated_on_cuda(method, small_data, tmp_path, cdrb):
    demos, buffer = small_data
    b = buffer if method == "cdrb" else None
    cfg = train_config(demos, b, method, {**SETTINGS[method], "steps": 20, "checkpoint_every": 20})
    model = train(demos, b, cfg, tmp_path / "m.h5", device="cuda")
    assert model.manifest.state.finished and np.isfinite(model.arrays["curve/loss"]).all()
    for device in ("cuda", "cpu"):
        out = tmp_path / f"eval-{device}.h5"
        r = cdrb("eval", tmp_path / "m.h5", "--episodes", "3", "--seeds", "0", "--device", device, "--out", out)
        assert r.returncode == 0, r.stderr
        assert r.stdout.strip() == str(out)
        ev = artifacts.load(out, "eval")
        assert len(ev.arrays["episodes/success"]) == 3


def test_cdrb_plans_from_a_cuda_graph_are_the_loop_it_captured(small_data, tmp_path):
    """On a GPU, CDRB's sampler replays a CUDA graph of its whole loop: the plans are exactly what the captured loop
    computes kernel by kernel from the same randomness, the same for the same seed, pinned, at several batch
    sizes; the graph is captured once per batch size and reused."""
    from cdrb_cli.methods.checkpoint import load_method
    from cdrb_cli.stages.plan import sample_plans

    demos, buffer = small_data
    cfg = train_config(demos, buffer, "cdrb", {**TINY, "steps": 20, "checkpoint_every": 20})
    model = train(demos, buffer, cfg, tmp_path / "m.h5", device="cuda")
    method = load_method(model, device="cuda")
    starts, goals = np.array([[0.0, 0.0, 0.0, 0.0]] * 5), np.array([[6.0, 6.0, 0.0, 0.0]] * 5)
    for n in (1, 5):
        a = sample_plans(method, starts[:n], goals[:n], 1, seed=4, batch_size=n, device="cuda").plans
        b = sample_plans(method, starts[:n], goals[:n], 1, seed=4, batch_size=n, device="cuda").plans
        np.testing.assert_array_equal(a, b)
        np.testing.assert_array_equal(a[:, 0], starts[:n])
        np.testing.assert_array_equal(a[:, -1], goals[:n])
    assert len(method._graphs) == 2
    start = torch.zeros((3, method.obs_dim), device="cuda")
    goal = torch.full((3, method.obs_dim), 0.5, device="cuda")
    with torch.no_grad():
        graphed = method._graphed(start, goal, np.random.default_rng(7), None).plans
    ball = method._device_ball(start.device)
    gen = ball.generator(np.random.default_rng(7))  # the same draws, in the same order, as _graphed makes
    ks = method._schedule(method.T - 1, None)
    x = method.pin(ball.random_states((3, method.horizon), gen).float(), start, goal)
    u = torch.rand((len(ks), 3, method.horizon - 2), generator=gen, device="cuda", dtype=torch.float64)
    with torch.no_grad():
        torch.testing.assert_close(graphed, method.graph_loop(x, start, goal, u, ks), rtol=0, atol=0)
