"""Soft/exact ranks and the Spearman gamma of RDGA (gca/align/softrank.py)."""

import numpy as np
import pytest
import scipy.stats
import torch
from torch.autograd.gradcheck import GradcheckError

from gca.align.softrank import exact_rank, soft_rank, spearman_exact, spearman_soft


def _patches(m=16, n=49, seed=0):
    g = torch.Generator().manual_seed(seed)
    return torch.randn(m, n, generator=g, dtype=torch.float64), torch.randn(m, n, generator=g, dtype=torch.float64)


def test_exact_rank_matches_scipy_average_ranks_with_ties():
    x = torch.tensor([[3.0, 1.0, 3.0, 2.0, 1.0, 5.0]], dtype=torch.float64)
    np.testing.assert_allclose(exact_rank(x)[0].numpy(), scipy.stats.rankdata(x[0].numpy()))


def test_spearman_exact_matches_scipy_without_ties():
    x, y = _patches()
    ref = [scipy.stats.spearmanr(a, b).statistic for a, b in zip(x.numpy(), y.numpy())]
    np.testing.assert_allclose(spearman_exact(x, y).numpy(), ref, atol=1e-12)


def test_soft_spearman_tends_to_exact_as_temperature_vanishes():
    x, y = _patches()
    exact = spearman_exact(x, y)
    errors = [float((spearman_soft(x, y, T) - exact).abs().max()) for T in (1.0, 1e-1, 1e-2, 1e-5)]
    assert errors[0] > 1e-2  # a large temperature really is soft
    assert all(a > b for a, b in zip(errors, errors[1:])), errors
    assert errors[-1] < 1e-6, errors
    torch.testing.assert_close(soft_rank(x, 1e-5), exact_rank(x), atol=1e-4, rtol=0)


def test_soft_rank_rows_sum_to_triangular_number_and_ties_average():
    x, _ = _patches(n=25)
    n = x.shape[1]
    torch.testing.assert_close(soft_rank(x, 0.3).sum(-1), torch.full((len(x),), n * (n + 1) / 2, dtype=x.dtype))
    tied = torch.tensor([[1.0, 2.0, 2.0, 4.0]], dtype=torch.float64)
    torch.testing.assert_close(soft_rank(tied, 1e-6), torch.tensor([[1.0, 2.5, 2.5, 4.0]], dtype=torch.float64))


def test_gamma_invariant_to_scale_shift_and_monotone_warp_of_target():
    x, y = _patches()
    y = y - y.min() + 0.1  # positive, so powers are monotone
    base_exact, base_soft = spearman_exact(x, y), spearman_soft(x, y, 0.05)
    for warped in (3.7 * y + 11.0, y ** 2.5, torch.log(y) * 0.2 - 4.0):
        torch.testing.assert_close(spearman_exact(x, warped), base_exact, atol=0, rtol=0)
        torch.testing.assert_close(spearman_soft(x, warped, 0.05), base_soft, atol=0, rtol=0)
    # the soft gamma is also invariant to positive scale/shift of the rendered side (standardised)
    torch.testing.assert_close(spearman_soft(5.0 * x + 2.0, y, 0.05), base_soft, atol=1e-12, rtol=0)
    # and it is not invariant to a reversal: a sanity negative control
    torch.testing.assert_close(spearman_exact(x, -y), -base_exact)


@pytest.mark.grad
def test_soft_gamma_gradient_is_finite_nonzero_and_passes_gradcheck():
    x, y = _patches(m=3, n=9)
    x.requires_grad_(True)
    (-spearman_soft(x, y, 0.2)).sum().backward()
    assert torch.isfinite(x.grad).all() and x.grad.abs().sum() > 0
    assert torch.autograd.gradcheck(lambda a: spearman_soft(a, y, 0.2), (x.detach().requires_grad_(),))


class _WrongGrad(torch.autograd.Function):
    """spearman_soft with a deliberately wrong (scaled) backward: the negative control."""

    @staticmethod
    def forward(ctx, x, y):
        ctx.save_for_backward(x, y)
        return spearman_soft(x, y, 0.2)

    @staticmethod
    def backward(ctx, v_gamma):
        x, y = ctx.saved_tensors
        with torch.enable_grad():
            x = x.detach().requires_grad_()
            (v_x,) = torch.autograd.grad(spearman_soft(x, y, 0.2), x, v_gamma)
        return 1.1 * v_x, None


@pytest.mark.grad
def test_gradcheck_catches_a_wrong_gradient():
    x, y = _patches(m=3, n=9)
    with pytest.raises(GradcheckError):
        torch.autograd.gradcheck(lambda a: _WrongGrad.apply(a, y), (x.requires_grad_(),))


def test_bad_input_raises():
    with pytest.raises(ValueError, match="softrank.py"):
        soft_rank(torch.zeros(5), 0.1)
    with pytest.raises(ValueError, match="temperature"):
        soft_rank(torch.zeros(2, 5), 0.0)
