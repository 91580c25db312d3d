"""The reference models' Mish against torch's own kernel and a float64 evaluation: values, gradients, extreme
inputs, and the module as a drop-in for ``torch.nn.Mish`` in saved state dicts."""

from __future__ import annotations

import torch
import torch.nn.functional as F
from hypothesis import given, settings
from hypothesis import strategies as st

from reference_common.layers import Mish, mish, mlp


def _reference(x: torch.Tensor) -> torch.Tensor:
    """x * tanh(softplus(x)) in float64 with torch's own kernel."""
    return F.mish(x.double())


def test_values_match_torch_in_float64_and_float32() -> None:
    x = torch.linspace(-60.0, 60.0, 240_001, dtype=torch.float64)
    assert torch.allclose(mish(x), _reference(x), rtol=1e-14, atol=1e-14)
    xf = x.float()
    ours = (mish(xf).double() - _reference(xf)).abs()
    torch_own = (F.mish(xf).double() - _reference(xf)).abs()
    # as close to the float64 value as torch's float32 kernel, anywhere in the range
    assert float(ours.max()) <= float(torch_own.max()) * 1.01 + 1e-12
    assert mish(xf).dtype == torch.float32


def test_gradient_matches_torch_and_passes_gradcheck() -> None:
    x = torch.linspace(-30.0, 30.0, 6001, dtype=torch.float64, requires_grad=True)
    mish(x).sum().backward()
    ours = x.grad.clone()
    x.grad = None
    F.mish(x).sum().backward()
    assert torch.allclose(ours, x.grad, rtol=1e-12, atol=1e-12)
    probe = (torch.randn(64, dtype=torch.float64, generator=torch.Generator().manual_seed(0)) * 6).requires_grad_()
    assert torch.autograd.gradcheck(mish, (probe,))


def test_input_is_not_modified_and_other_dtypes_use_torch() -> None:
    x = torch.randn(5, 7)
    before = x.clone()
    mish(x)
    assert torch.equal(x, before)
    h = torch.randn(16).to(torch.bfloat16)
    assert torch.equal(mish(h), F.mish(h))


@settings(max_examples=200, deadline=None)
@given(st.floats(allow_nan=False, allow_infinity=False, width=32))
def test_finite_inputs_give_finite_outputs_close_to_torch(value: float) -> None:
    x = torch.tensor([value], dtype=torch.float32)
    out = mish(x)
    assert torch.isfinite(out).all()
    expected = _reference(x)
    assert abs(float(out) - float(expected)) <= 1e-6 * max(1.0, abs(float(expected)))


def test_module_is_a_drop_in_for_torch_mish() -> None:
    torch.manual_seed(0)
    ours = torch.nn.Sequential(torch.nn.Linear(4, 8), Mish(), torch.nn.Linear(8, 2))
    theirs = torch.nn.Sequential(torch.nn.Linear(4, 8), torch.nn.Mish(), torch.nn.Linear(8, 2))
    theirs.load_state_dict(ours.state_dict())  # same keys: Mish holds no parameters
    x = torch.randn(32, 4)
    assert torch.allclose(ours(x), theirs(x), atol=1e-6)
    assert isinstance(mlp([4, 8, 2])[2], torch.nn.Mish)  # the shared MLP keeps torch's kernel
