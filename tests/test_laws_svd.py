"""gca.laws.svd: rotation-valued SVD, clamped backward, exact spectral-map gradients at repeated values."""

import sys
from pathlib import Path

import pytest
import torch
from torch.autograd import gradcheck
from torch.autograd.gradcheck import GradcheckError

from gca.laws.svd import det3, polar_rotation, svd, svd_map, torch_svd_rotations
from gca.laws.svd_kernel import svd3

sys.path.insert(0, str(Path(__file__).parent))
from fixtures3x3 import random_F, random_rotations  # noqa: E402

f64 = torch.float64


def eye(n, dtype=f64):
    return torch.eye(3, dtype=dtype).repeat(n, 1, 1)


@pytest.mark.parametrize("dtype", [torch.float32, f64])
def test_reconstruction_and_proper_rotations(dtype):
    F = random_F(64, 0, spread=0.8, dtype=dtype)
    F[:8, :, 0] *= -1  # flips det for some: both signs occur
    U, sigma, Vh = svd(F)
    tol = 1e-5 if dtype == torch.float32 else 1e-12
    torch.testing.assert_close(U @ torch.diag_embed(sigma) @ Vh, F, atol=tol, rtol=tol)
    torch.testing.assert_close(det3(U), torch.ones(64, dtype=dtype), atol=tol, rtol=0)
    torch.testing.assert_close(det3(Vh), torch.ones(64, dtype=dtype), atol=tol, rtol=0)
    inverted = det3(F) < 0
    assert 0 < int(inverted.sum()) < 64 and bool((sigma[inverted, 2] < 0).all()) and bool((sigma[~inverted] > 0).all())
    assert bool((sigma[:, 0] >= sigma[:, 1]).all()) and bool((sigma[:, 1] >= sigma[:, 2].abs()).all())


def _kernel_cases(dtype=torch.float32) -> torch.Tensor:
    """Batch: generic, identity, two/three repeated values, inverted, rotated, near-singular."""
    g = torch.Generator().manual_seed(7)
    F = [torch.eye(3, dtype=f64) + 0.4 * torch.randn(400, 3, 3, generator=g, dtype=f64), eye(4),
         torch.diag(torch.tensor([1.2, 1.2, 0.9], dtype=f64))[None], torch.diag(torch.tensor([0.7, 1.0, 1.0], dtype=f64))[None],
         torch.diag(torch.tensor([1.1, 0.9, -0.8], dtype=f64))[None], 1e-3 * torch.randn(4, 3, 3, generator=g, dtype=f64)]
    R = random_rotations(8, 8)
    F.append(R @ torch.diag(torch.tensor([1.3, 1.3, 0.6], dtype=f64)))
    return torch.cat(F).to(dtype)


@pytest.mark.parametrize("dtype, tol", [(torch.float32, 5e-6), (f64, 1e-14)])
def test_warp_kernel_matches_torch_reference(dtype, tol):
    """Fast path (one warp kernel) vs torch.linalg.svd with the same sign conventions."""
    F = _kernel_cases(dtype)
    U, sigma, Vh = svd3(F)
    U_ref, s_ref, Vh_ref = torch_svd_rotations(F)
    scale = F.flatten(1).abs().max(1).values.clamp(min=1.0)[:, None, None]
    torch.testing.assert_close(U @ torch.diag_embed(sigma) @ Vh / scale, F / scale, atol=tol, rtol=0)
    torch.testing.assert_close(sigma, s_ref, atol=tol / 2, rtol=tol / 5)
    eye3 = torch.eye(3, dtype=dtype).expand_as(U)
    torch.testing.assert_close(U @ U.transpose(1, 2), eye3, atol=tol / 2, rtol=0)
    torch.testing.assert_close(Vh @ Vh.transpose(1, 2), eye3, atol=tol / 2, rtol=0)
    assert bool((det3(U) > 0).all()) and bool((det3(Vh) > 0).all())
    assert torch.equal(sigma[:, 2] < 0, det3(F) < 0)
    well_posed = det3(F).abs() > 1e-2  # the polar rotation is unique and well conditioned there
    torch.testing.assert_close((U @ Vh)[well_posed], (U_ref @ Vh_ref)[well_posed], atol=2 * tol, rtol=0)
    at_rest = svd3(eye(3, dtype))  # exact at F = I: no rotation is taken
    assert torch.equal(at_rest[0], eye(3, dtype)) and torch.equal(at_rest[1], torch.ones(3, 3, dtype=dtype))


def test_warp_kernel_refuses_other_types():
    with pytest.raises(ValueError, match="float32/float64"):
        svd3(torch.eye(3, dtype=torch.float16)[None])


def test_hand_values_diagonal():
    F = torch.diag(torch.tensor([0.5, 2.0, -1.5], dtype=f64))[None]
    _, sigma, _ = svd(F)
    torch.testing.assert_close(sigma[0], torch.tensor([2.0, 1.5, -0.5], dtype=f64))  # det F = -1.5 < 0


@pytest.mark.grad
def test_gradcheck_generic_F():
    F = random_F(3, 1).requires_grad_(True)
    assert gradcheck(lambda F: svd(F), (F,))


@pytest.mark.grad
def test_gradient_matches_torch_on_generic_F():
    """Fast path vs torch.linalg.svd autograd (reference) for a gauge-invariant loss."""
    F = random_F(16, 2).requires_grad_(True)
    W = torch.randn(16, 3, 3, generator=torch.Generator().manual_seed(3), dtype=f64)
    U, sigma, Vh = svd(F)
    (v_F,) = torch.autograd.grad(((U @ Vh) * W).sum() + (sigma ** 3).sum(), F)
    U_ref, s_ref, Vh_ref = torch.linalg.svd(F)
    (v_F_ref,) = torch.autograd.grad(((U_ref @ Vh_ref) * W).sum() + (s_ref ** 3).sum(), F)
    torch.testing.assert_close(v_F, v_F_ref, atol=1e-10, rtol=1e-10)


@pytest.mark.parametrize("F", [eye(2), torch.diag(torch.tensor([1.2, 1.0, 1.0], dtype=f64))[None]])
def test_finite_gradients_at_repeated_values(F):
    F = F.clone().requires_grad_(True)
    U, sigma, Vh = svd(F)
    W = torch.randn(3, 3, 3, generator=torch.Generator().manual_seed(4), dtype=f64)
    loss = (U * W[0]).sum() + (Vh * W[1]).sum() + (sigma * W[2, 0]).sum()
    (v_F,) = torch.autograd.grad(loss, F)
    assert torch.isfinite(v_F).all()


@pytest.mark.grad
@pytest.mark.parametrize("F", [eye(2), torch.diag(torch.tensor([1.2, 1.0, 1.0], dtype=f64))[None],
                               torch.diag(torch.tensor([1.1, 1.1, -0.9], dtype=f64))[None]])
def test_polar_rotation_exact_gradient_at_repeated_values(F):
    F = F.clone().requires_grad_(True)
    assert gradcheck(polar_rotation, (F,))
    if torch.det(F[0]) > 0:
        torch.testing.assert_close(polar_rotation(F.detach()) @ polar_rotation(F.detach()).transpose(1, 2),
                                   eye(F.shape[0]), atol=1e-12, rtol=0)


def _cube_plus_trace(sigma, k):
    return sigma ** 3 + k * sigma.sum(-1, keepdim=True)


@pytest.mark.grad
@pytest.mark.parametrize("left", [False, True])
@pytest.mark.parametrize("which", ["generic", "identity", "uniaxial"])
def test_svd_map_gradcheck_including_repeated_values(left, which):
    F = {"generic": random_F(3, 5), "identity": eye(2),
         "uniaxial": torch.diag(torch.tensor([0.7, 1.3, 1.3], dtype=f64))[None]}[which]
    F = F.clone().requires_grad_(True)
    k = torch.tensor(0.4, dtype=f64, requires_grad=True)
    assert gradcheck(lambda F, k: svd_map(F, _cube_plus_trace, k, left=left)[0], (F, k))


@pytest.mark.grad
def test_negative_control_generic_svd_loses_shear_at_identity():
    """U diag(sigma^3) Vh through the generic SVD backward is wrong at F = I (the divided difference
    (y_i - y_j)/(s_i - s_j) is 0/0 there); gradcheck must catch it, while svd_map is exact."""
    F = eye(1).requires_grad_(True)

    def through_generic_svd(F):
        U, sigma, Vh = svd(F)
        return U @ torch.diag_embed(sigma ** 3) @ Vh

    with pytest.raises(GradcheckError, match="Jacobian mismatch"):
        gradcheck(through_generic_svd, (F,))
    assert gradcheck(lambda F: svd_map(F, lambda s: s ** 3)[0], (F,))


def test_bad_input_raises_clear_error():
    with pytest.raises(ValueError, match=r"svd: F must be a \[N, 3, 3\]"):
        svd(torch.eye(3))
    with pytest.raises(TypeError, match="floating point"):
        svd(torch.eye(3, dtype=torch.int64)[None])


@pytest.mark.gpu
def test_cuda_matches_cpu():
    F = random_F(32, 6, dtype=torch.float32)
    R_cpu = polar_rotation(F)
    R_gpu = polar_rotation(F.cuda()).cpu()
    torch.testing.assert_close(R_gpu, R_cpu, atol=1e-5, rtol=1e-5)


@pytest.mark.grad
def test_bmm3_equals_matmul_with_broadcasting_and_gradients():
    g = torch.Generator().manual_seed(11)
    A = torch.randn(7, 3, 3, generator=g, dtype=f64, requires_grad=True)
    B = torch.randn(7, 3, 3, generator=g, dtype=f64, requires_grad=True)
    M = torch.randn(3, 3, generator=g, dtype=f64)
    from gca.laws.svd import bmm3
    torch.testing.assert_close(bmm3(A, B), A @ B, atol=1e-14, rtol=1e-14)
    torch.testing.assert_close(bmm3(M, B), M @ B, atol=1e-14, rtol=1e-14)
    torch.testing.assert_close(bmm3(A[None], B[:, None]), A[None] @ B[:, None], atol=1e-14, rtol=1e-14)
    assert gradcheck(bmm3, (A, B))
