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
    import os
    import platform

    for k in [k for k in os.environ if k.startswith("MALLOC_") or k == "GLIBC_TUNABLES"]:
        monkeypatch.delenv(k)
    for name, value in (("MALLOC_ARENA_MAX", "2"), ("GLIBC_TUNABLES", "glibc.malloc.trim_threshold=0")):
        monkeypatch.setenv(name, value)
        assert torch_utils.keep_freed_memory() is False
        monkeypatch.delenv(name)

    assert torch_utils.keep_freed_memory() is (platform.libc_ver()[0] == "glibc")


def test_mish_keeps_only_its_input_for_backward_and_its_gradient_is_exact():
    """Training memory as with torch's Mish (one saved tensor, the input), and the closed-form derivative checked
    against finite differences in float64."""
    saved = []
    x = torch.randn(4, 8, requires_grad=True)
    with torch.autograd.graph.saved_tensors_hooks(lambda t: saved.append(t) or t, lambda t: t):
        mish(x).sum().backward()
    assert len(saved) == 1 and saved[0] is x
    xd = (torch.randn(64, dtype=torch.float64) * 6).requires_grad_()
    assert torch.autograd.gradcheck(mish, (xd,))


@pytest.mark.parametrize("dtype", [torch.bfloat16, torch.float16])
def test_mish_rounds_once_in_low_precision(dtype):
    """Half and bfloat16 inputs (what autocast hands a layer) are computed in float32 and rounded once: as close to
    the definition as torch's own kernel."""
    x = torch.linspace(-20, 20, 20_001).to(dtype)
    want = x.double() * torch.tanh(torch.nn.functional.softplus(x.double()))
    got = mish(x)
    assert got.dtype == dtype
    big = want.abs() > 1e-2
    err = ((got.double() - want).abs() / want.abs())[big].max()
    theirs = ((torch.nn.functional.mish(x).double() - want).abs() / want.abs())[big].max()
    assert err <= max(theirs, torch.finfo(dtype).eps)
