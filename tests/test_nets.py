"""Network building blocks checked against their definitions."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from cdrb_cli import torch_utils
from cdrb_cli.nets.activations import Mish, mish


def test_mish_is_x_tanh_softplus_in_value_and_gradient():
    x = torch.cat([torch.linspace(-60, 60, 100_001, dtype=torch.float64), torch.tensor([0.0, -1e-30, 1e-30])])
    want = x * torch.tanh(torch.nn.functional.softplus(x))  # the definition, in float64
    xf = x.float().requires_grad_()
    got = Mish()(xf)
    got.sum().backward()
    assert torch.isfinite(got).all() and torch.isfinite(xf.grad).all()
    np.testing.assert_allclose(got.detach().double(), want, rtol=1e-6, atol=3e-6)
    xd = x.clone().requires_grad_()
    (xd * torch.tanh(torch.nn.functional.softplus(xd))).sum().backward()
    np.testing.assert_allclose(xf.grad.double(), xd.grad, rtol=1e-5, atol=3e-6)
    # small negative inputs keep their relative precision (p = s (2 - s), not 1 - (1 - s)^2)
    neg = torch.tensor([-8.0, -12.0, -16.0, -30.0])
    exact = neg.double() * torch.tanh(torch.nn.functional.softplus(neg.double()))
    np.testing.assert_allclose(mish(neg).double(), exact, rtol=1e-5)


def test_mish_loads_the_weights_of_networks_built_with_torchs_mish():
    ours = torch.nn.Sequential(torch.nn.Linear(3, 8), Mish(), torch.nn.Linear(8, 2))
    theirs = torch.nn.Sequential(torch.nn.Linear(3, 8), torch.nn.Mish(), torch.nn.Linear(8, 2))
    ours.load_state_dict(theirs.state_dict())  # strict: no parameter or buffer of its own
    x = torch.randn(64, 3)
    np.testing.assert_allclose(ours(x).detach(), theirs(x).detach(), atol=2e-6)


@pytest.mark.skipif(not __import__("sys").platform.startswith("linux"), reason="glibc's allocator")
def test_the_allocator_is_left_alone_where_a_user_tuned_it(monkeypatch):
    monkeypatch.setenv("MALLOC_ARENA_MAX", "2")
    assert torch_utils.keep_freed_memory() is False
    monkeypatch.delenv("MALLOC_ARENA_MAX")
    import platform

    assert torch_utils.keep_freed_memory() is (platform.libc_ver()[0] == "glibc")
