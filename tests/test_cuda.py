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
