"""gca.laws.fused: the neural laws' features and heads in warp kernels with hand-written adjoints
(fast path) against the torch reference path, float64 gradient checks of each warp <-> torch boundary."""

import pytest
import torch
from torch.autograd import gradcheck

from gca.laws import fused
from gca.laws.lora import apply_lora
from gca.laws.neural import NeuralElasticity, NeuralLawConfig, NeuralPlasticity, invariant_features
from gca.laws.svd import bmm3, svd

from test_laws_neural import eye, random_F, random_rotations, scramble

f64 = torch.float64


def hard_F(n=40, seed=0, dtype=f64) -> torch.Tensor:
    """Generic F plus the cases that break naive code: F = I, repeated values, inversion, rotations."""
    F = random_F(n, seed, dtype=dtype)
    F[:4] = eye(4, dtype)
    F[4] = torch.diag(torch.tensor([1.1, 1.1, 0.9], dtype=dtype))
    F[5:8, :, 0] *= -1  # inverted
    F[8:12] = random_rotations(4, seed + 1, dtype) @ torch.diag(torch.tensor([1.2, 0.95, 0.95], dtype=dtype))
    return F


def simple_rows(F: torch.Tensor) -> torch.Tensor:
    """Rows of F [N,3,3] whose singular values are distinct, or F = I exactly: [N] bool.

    Where sigma ties (rows 4 and 8-11 of ``hard_F``) the law is not differentiable in F: its features
    hold each sigma_i, whose derivative u_i v_i^T depends on the basis picked inside the tied subspace,
    and near a tie the adjoint's 1/(sigma_i - sigma_j) terms amplify rounding differences between two
    implementations. Values and parameter gradients are unique on every row."""
    sigma = torch.linalg.svdvals(F.detach().double().cpu())
    gap = (sigma[:, :-1] - sigma[:, 1:]).min(dim=1).values
    identity = (F.detach().cpu() == torch.eye(3, dtype=F.dtype)).flatten(1).all(dim=1)
    return (gap > 1e-6) | identity


@pytest.mark.grad
def test_features_gradcheck_float64():
    F = random_F(4, 3).requires_grad_(True)
    assert gradcheck(fused.features, (F,))


@pytest.mark.grad
@pytest.mark.parametrize("head", ["elastic", "plastic"])
def test_heads_gradcheck_float64(head):
    g = torch.Generator().manual_seed(5)
    X = torch.randn(5, 9, dtype=f64, generator=g).requires_grad_(True)
    R = random_rotations(5, 2).requires_grad_(True)
    F = random_F(5, 4).requires_grad_(True)
    fn = (lambda X, R, F: fused.elastic_head(X, R, F, 3.0)) if head == "elastic" else \
        (lambda X, R, F: fused.plastic_head(X, R, F, 0.7))
    assert gradcheck(fn, (X, R, F))


def test_features_and_heads_equal_the_torch_formulas():
    F = hard_F()
    R, z = fused.features(F)
    U, sigma, Vh = svd(F)
    torch.testing.assert_close(R, bmm3(U, Vh), rtol=0, atol=1e-14)
    torch.testing.assert_close(z, invariant_features(F, sigma), rtol=0, atol=1e-14)
    assert torch.equal(z[:4], torch.zeros(4, 13, dtype=f64))  # exactly 0 at rest
    X = torch.randn(len(F), 9, dtype=f64)
    S = 0.5 * (X.reshape(-1, 3, 3) + X.reshape(-1, 3, 3).transpose(1, 2))
    torch.testing.assert_close(fused.elastic_head(X, R, F, 2.0), 2.0 * bmm3(bmm3(R, S), F.transpose(1, 2)))
    torch.testing.assert_close(fused.plastic_head(X, R, F, 0.1), F + 0.1 * bmm3(R, S))


@pytest.mark.parametrize("dtype", [f64, torch.float32])
def test_the_svd_and_the_features_in_one_kernel_equal_the_two_kernels(dtype):
    # session 52: _Features runs svd_features (the SVD inlined) instead of the SVD kernel then features: R and z
    # bitwise the two kernels' on the CPU, the SVD stored only where ``keep`` (its NaN-filled buffers untouched
    # otherwise), and a forward with gradients saves the SVD the backward reads
    from gca.laws.svd import _svd_rotations

    F = hard_F(dtype=dtype)
    n, k = F.shape[0], fused.make_law_kernels(dtype)
    U, sigma, Vh = _svd_rotations(F)
    R0, z0 = fused.features_of_svd(F, U, sigma, Vh)
    for keep in (0, 1):
        out = [torch.full_like(t, float("nan")) for t in (U, sigma, Vh, R0, z0)]
        fused._launch(k.svd_features, n, F.device, [fused._m(F, k), keep, fused._m(out[0], k), fused._v(out[1], k),
                                                    fused._m(out[2], k), fused._m(out[3], k), fused._a(out[4])])
        assert torch.equal(out[3], R0) and torch.equal(out[4], z0)
        for a, b in zip(out[:3], (U, sigma, Vh)):
            assert torch.equal(a, b) if keep else torch.isnan(a).all()
    with torch.no_grad():
        R1, z1 = fused.features(F)
    assert torch.equal(R1, R0) and torch.equal(z1, z0)
    Fg = F.clone().requires_grad_(True)
    R2, z2 = fused.features(Fg)
    saved = R2.grad_fn.saved_tensors
    assert torch.equal(saved[1], U) and torch.equal(saved[2], sigma) and torch.equal(saved[3], Vh)


@pytest.mark.parametrize("law_cls", [NeuralElasticity, NeuralPlasticity])
@pytest.mark.parametrize("dtype, tol", [(f64, 1e-12), (torch.float32, 2e-5)])
def test_fast_path_equals_reference_values_and_gradients(law_cls, dtype, tol):
    """Whole law with LoRA: outputs, the gradient to F and to every trainable parameter."""
    law = scramble(apply_lora(law_cls(NeuralLawConfig(widths=(32, 32))).double(), rank=4, alpha=4.0), seed=1).to(dtype)
    F = hard_F(dtype=dtype).requires_grad_(True)
    params = [F] + [p for p in law.parameters() if p.requires_grad]
    out = {}
    for fast in (True, False):
        law.fast_path = fast
        y = law(F)
        w = torch.randn(y.shape, dtype=dtype, generator=torch.Generator().manual_seed(9))
        out[fast] = (y, torch.autograd.grad((y * w).sum(), params))
    (y_fast, g_fast), (y_ref, g_ref) = out[True], out[False]
    scale = y_ref.abs().max()
    torch.testing.assert_close(y_fast / scale, y_ref / scale, rtol=0, atol=tol)
    simple = simple_rows(F)
    (gF_fast, *g_fast), (gF_ref, *g_ref) = g_fast, g_ref
    for a, b in zip([gF_fast[simple], *g_fast], [gF_ref[simple], *g_ref]):
        torch.testing.assert_close(a / b.abs().max(), b / b.abs().max(), rtol=0, atol=tol)
    torch.testing.assert_close(gF_fast / gF_ref.abs().max(), gF_ref / gF_ref.abs().max(), rtol=0,
                               atol=max(tol, 1e-8))  # near ties: same basis, amplified rounding
    law.fast_path = True
    at_rest = law(eye(3, dtype))
    expected = torch.zeros(3, 3, 3, dtype=dtype) if law_cls is NeuralElasticity else eye(3, dtype)
    assert torch.equal(at_rest, expected)  # zero stress / identity return map at rest, exactly


def test_fast_path_objectivity():
    law = scramble(NeuralElasticity().double(), seed=2)
    F, Q = random_F(16, 6), random_rotations(16, 7)
    torch.testing.assert_close(law(bmm3(Q, F)), bmm3(bmm3(Q, law(F)), Q.transpose(1, 2)), rtol=1e-10, atol=1e-8)


def test_wrong_dtype_is_refused():
    with pytest.raises(TypeError, match="float32 or float64"):
        fused.features(torch.eye(3, dtype=torch.float16)[None])


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
@pytest.mark.parametrize("law_cls", [NeuralElasticity, NeuralPlasticity])
def test_fast_path_on_cuda_equals_the_cpu(law_cls):
    """The CUDA build of the kernels against the CPU one (float64: values and gradients; dL/dF on the
    rows where it is unique, see ``simple_rows``: the builds round differently, FMA, and so may pick
    different bases where sigma ties)."""
    law = scramble(apply_lora(law_cls(NeuralLawConfig(widths=(32, 32))).double(), rank=4, alpha=4.0), seed=3)
    F0 = hard_F()
    simple = simple_rows(F0)
    assert 0 < int(simple.sum()) < len(F0)
    out = {}
    for device in ("cpu", "cuda"):
        law.to(device)
        F = F0.to(device).requires_grad_(True)
        y = law(F)
        params = [F] + [p for p in law.parameters() if p.requires_grad]
        y_, g_F, *g_params = (t.detach().cpu() for t in (y, *torch.autograd.grad(y.square().sum(), params)))
        out[device] = [y_, g_F[simple], *g_params]
    for a, b in zip(out["cuda"], out["cpu"]):
        torch.testing.assert_close(a, b, rtol=1e-10, atol=1e-10 * float(b.abs().max()))


@pytest.mark.parametrize("law_cls", [NeuralElasticity, NeuralPlasticity])
def test_fast_path_handles_an_empty_batch(law_cls):
    F = torch.zeros(0, 3, 3, requires_grad=True)
    y = law_cls()(F)
    y.sum().backward()
    assert y.shape == (0, 3, 3) and F.grad.shape == (0, 3, 3)
