"""Degenerate covariances (issue 20 item 1): what a float32 rasterizer cannot handle, and ours bounded.

A near-singular deformation gradient F makes Sigma = F Sigma0 F^T rank-deficient; seen edge on and
large, its 2D covariance is rank one, and the float32 determinant (a0 + eps)(c0 + eps) - b0^2 loses the
blur's share to cancellation (gsplat computes exactly that, and culls at det <= 0). The reproducing
case is a rank-one footprint of L px^2: at L >= 1e7 the naive float32 determinant is off by > 2x or
negative. ``covariance_health`` flags it; our projection floors the un-blurred determinant at 0 (its
exact-arithmetic range), so the conic stays below ~1/eps2d and its gradient finite.
"""

from __future__ import annotations

import math
import sys
from pathlib import Path

import pytest
import torch

from gca.render import RasterConfig, render, render_ref
from gca.render.follow import follow, Binding
from gca.render.project import covariance_health, project_gaussians

sys.path.insert(0, str(Path(__file__).parent))
from test_render_raster import BG, KEYS, _camera, _scene  # noqa: E402

K = torch.tensor([[300.0, 0, 128], [0, 300.0, 128], [0, 0, 1]])
W2C = torch.eye(4)
EPS2D = 0.3


def _rank_one(L: float, dtype=torch.float32, angle: float = 0.5):
    """One Gaussian 1 m in front of the camera whose 2D covariance is L px^2 along ``angle``, rank one."""
    u = torch.tensor([math.cos(angle), math.sin(angle), 0.0], dtype=torch.float64)
    cov = (L / 300.0**2) * torch.outer(u, u) + 1e-12 * torch.eye(3, dtype=torch.float64)
    return torch.tensor([[0.0, 0.0, 1.0]], dtype=dtype), cov[None].to(dtype)


def _naive_det(cov: torch.Tensor) -> torch.Tensor:
    """gsplat's (a0 + eps)(c0 + eps) - b0^2 in the input's precision (camera = identity, J = f/z)."""
    c2 = cov[0, :2, :2] * 300.0**2
    return (c2[0, 0] + EPS2D) * (c2[1, 1] + EPS2D) - c2[0, 1] * c2[1, 0]


@pytest.mark.parametrize("L", [1e7, 1e8, 1e9])
def test_large_thin_footprint_is_flagged_and_stays_bounded(L):
    m, c = _rank_one(L)
    exact = EPS2D * 2 * L * 1.0 + EPS2D**2  # det of the blurred rank-one 2D covariance (a0 + c0 = L)
    naive = float(_naive_det(c))
    assert naive <= 0 or abs(naive - exact) > 0.5 * exact  # the negative control: float32 cancellation
    health = covariance_health(m, c, K, W2C, 256, 256, eps2d=EPS2D)
    assert health["det_unreliable"].all() and health["singular"].all() and health["any"].all()
    assert not health["not_spd"].any()
    c = c.clone().requires_grad_(True)
    proj = project_gaussians(m, c, K, W2C, 256, 256, eps2d=EPS2D)
    assert proj.valid.all() and torch.isfinite(proj.conics).all()
    assert proj.conics.abs().max() <= 1.0 / EPS2D  # bounded whatever the rounding
    (g,) = torch.autograd.grad(proj.conics.sum(), c)
    assert torch.isfinite(g).all()


def test_healthy_gaussians_are_not_flagged_and_match_float64():
    m, c = _rank_one(1e2)
    health = covariance_health(m, c, K, W2C, 256, 256)
    assert not health["any"].any()
    p32 = project_gaussians(m, c, K, W2C, 256, 256)
    p64 = project_gaussians(m.double(), c.double(), K.double(), W2C.double(), 256, 256)
    torch.testing.assert_close(p32.conics.double(), p64.conics, rtol=1e-5, atol=0)
    means, covs, *_ = _scene(50, seed=3, dtype=torch.float32)
    camera = _camera(64, 48)
    Kc, w2c = camera.tensors(torch.float32)
    assert not covariance_health(means, covs, Kc, w2c, 64, 48)["any"].any()


def test_not_spd_is_flagged():
    m = torch.tensor([[0.0, 0.0, 1.0]] * 3)
    good = 1e-4 * torch.eye(3)
    bad = torch.diag(torch.tensor([1e-4, 1e-4, -1e-5]))
    nan = good.clone()
    nan[0, 0] = float("nan")
    h = covariance_health(m, torch.stack([good, bad, nan]), K, W2C, 256, 256)
    assert h["not_spd"].tolist() == [False, True, True]


@pytest.mark.grad
def test_projection_gradient_float64_gradcheck_with_floor():
    """The floored determinant is differentiable where det0 > 0 (float64 gradcheck) and its gradient
    differs from the naive one only where det0 < 0 (negative control: a rank-deficient 2D covariance)."""
    means, covs, *_ = _scene(6, seed=4)
    camera = _camera(32, 24)
    Kc, w2c = camera.tensors(torch.float64)
    covs = covs.clone().requires_grad_(True)
    fn = lambda cv: project_gaussians(means, cv, Kc, w2c, 32, 24).conics  # noqa: E731
    assert torch.autograd.gradcheck(fn, (covs,), eps=1e-9, atol=1e-6)


def _degenerate_scene(n: int = 200, seed: int = 5):
    """Gaussians following particles whose F is near singular (flattened to 1e-3 along a random axis)."""
    means0, covs0, colors, opac = _scene(n, seed=seed, dtype=torch.float64)
    g = torch.Generator().manual_seed(seed)
    Q, _ = torch.linalg.qr(torch.randn(n, 3, 3, generator=g, dtype=torch.float64))
    d = torch.tensor([1.5, 1.0, 1e-3], dtype=torch.float64)
    F = Q @ torch.diag_embed(d.expand(n, 3)) @ Q.transpose(-1, -2)
    idx = torch.arange(n)
    binding = Binding(rows=idx, cols=idx, weights=torch.ones(n, dtype=torch.float64), n_gaussians=n, n_particles=n)
    return binding, means0, covs0, colors, opac, F


def test_degenerate_F_cpu_twin_agrees_with_reference_under_gsplat_rules():
    """CPU twin of the CUDA agreement test on a degenerate-F scene: tiled torch = dense reference
    (gsplat's alpha clamp and extent), gradients finite."""
    binding, means0, covs0, colors, opac, F = _degenerate_scene(60)
    F = F.requires_grad_(True)
    means, covs = follow(binding, means0, covs0, means0, means0, F)
    camera, cfg = _camera(32, 24), RasterConfig(alpha_max=0.999, sigma_cutoff=3.5)
    a, b = render(means, covs, colors, opac, camera, BG, cfg=cfg), render_ref(means, covs, colors, opac, camera, BG, cfg)
    for k in KEYS:
        torch.testing.assert_close(a[k], b[k], atol=1e-10, rtol=0)
    (gF,) = torch.autograd.grad(sum(a[k].sum() for k in KEYS), F)
    assert torch.isfinite(gF).all() and gF.abs().sum() > 0


@pytest.mark.gpu
def test_degenerate_F_gsplat_matches_torch_on_cuda():
    """The reproducing case on CUDA: flattened Gaussians from a near-singular F, float32, gsplat vs
    torch: images agree and both backends' gradients w.r.t. F are finite and close."""
    pytest.importorskip("gsplat")
    binding, means0, covs0, colors, opac, F = _degenerate_scene(2000)
    binding = Binding(rows=binding.rows.cuda(), cols=binding.cols.cuda(), weights=binding.weights.float().cuda(),
                      n_gaussians=binding.n_gaussians, n_particles=binding.n_particles)
    means0, covs0, colors, opac = (t.float().cuda() for t in (means0, covs0, colors, opac))
    F = F.float().cuda().requires_grad_(True)
    means, covs = follow(binding, means0, covs0, means0, means0, F)
    camera, cfg, bg = _camera(128, 96), RasterConfig(alpha_max=0.999, sigma_cutoff=3.5), BG.float().cuda()
    Kc, w2c = camera.tensors(torch.float32, "cuda")
    health = covariance_health(means, covs, Kc, w2c, 128, 96)
    ours, theirs = render(means, covs, colors, opac, camera, bg, cfg=cfg), \
        render(means, covs, colors, opac, camera, bg, backend="gsplat", cfg=cfg)
    for k in KEYS:
        torch.testing.assert_close(ours[k], theirs[k], atol=1e-3, rtol=0, msg=k)
    (g_ours,) = torch.autograd.grad(sum(ours[k].sum() for k in KEYS), F, retain_graph=True)
    (g_theirs,) = torch.autograd.grad(sum(theirs[k].sum() for k in KEYS), F)
    assert torch.isfinite(g_ours).all() and torch.isfinite(g_theirs).all(), health["any"].sum()
    assert ((g_ours - g_theirs).abs().max() / g_theirs.abs().max()).item() < 1e-2
