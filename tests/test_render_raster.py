"""Rasterizer: float64 gradchecks (+ negative control), tiled == dense reference, image-formation facts."""


import pytest
import torch

from gca.render import RasterConfig, RenderError, follow, look_at, render, render_ref
from gca.render.follow import Binding

F64 = torch.float64


def _scene(n: int, seed: int, dtype=F64, spread: float = 0.4, scale: float = 0.03):
    """Random Gaussians around (0.5, 0.5, 0.5): means, SPD covs, colours, opacities."""
    g = torch.Generator().manual_seed(seed)
    means = 0.5 + spread * (torch.rand(n, 3, generator=g, dtype=dtype) - 0.5)
    A = scale * torch.randn(n, 3, 3, generator=g, dtype=dtype)
    covs = A @ A.transpose(1, 2) + (0.2 * scale) ** 2 * torch.eye(3, dtype=dtype)
    colors = torch.rand(n, 3, generator=g, dtype=dtype)
    opacities = 0.2 + 0.75 * torch.rand(n, generator=g, dtype=dtype)
    return means, covs, colors, opacities


def _camera(width: int, height: int, fov: float = 40.0, dist: float = 1.5):
    return look_at([0.5, 0.5, 0.5 - dist], [0.5, 0.5, 0.5], [0, 1, 0], fov, width, height)


BG = torch.tensor([0.1, 0.2, 0.3], dtype=F64)
KEYS = ("rgb", "alpha", "depth")


# ---------------------------------------------------------------- gradient checks (float64)


class _ScaleGrad(torch.autograd.Function):
    """Identity forward, backward scaled by 1.01: a deliberately wrong gradient."""

    @staticmethod
    def forward(ctx, x):
        return x.clone()

    @staticmethod
    def backward(ctx, g):
        return 1.01 * g


def _render_fn(which: int, inputs, camera, cfg, corrupt=False):
    """x -> a random linear functional of every output (full-mode gradcheck checks each input entry)."""
    g = torch.Generator().manual_seed(11)
    H, W = camera.height, camera.width
    weights = {"rgb": torch.randn(H, W, 3, generator=g, dtype=F64), "alpha": torch.randn(H, W, generator=g, dtype=F64),
               "depth": torch.randn(H, W, generator=g, dtype=F64),
               "depth_expected": torch.randn(H, W, generator=g, dtype=F64)}

    def fn(x):
        args = list(inputs)
        args[which] = _ScaleGrad.apply(x) if corrupt else x
        out = render(*args, camera, BG, cfg=cfg)
        covered = out["alpha"].detach() > 1e-3      # depth_expected is ill-conditioned where empty
        expected = (out["depth_expected"] * weights["depth_expected"])[covered].sum()
        return sum((out[k] * weights[k]).sum() for k in KEYS) + expected
    return fn


GRAD_CFG = RasterConfig(tile_size=4, slab=2)   # several tiles and slabs on a 12 x 12 image


@pytest.mark.grad
@pytest.mark.parametrize("which, name", [(0, "means"), (1, "covs"), (2, "colors"), (3, "opacities")])
def test_gradcheck_each_input(which, name):
    inputs = _scene(4, seed=3, scale=0.05)
    camera = _camera(12, 12)
    x = inputs[which].clone().requires_grad_()
    assert torch.autograd.gradcheck(_render_fn(which, inputs, camera, GRAD_CFG), (x,), eps=1e-6,
                                    atol=1e-6, rtol=1e-4), name


@pytest.mark.grad
def test_gradcheck_negative_control_catches_a_1_percent_error():
    inputs = _scene(4, seed=3, scale=0.05)
    x = inputs[0].clone().requires_grad_()
    ok = torch.autograd.gradcheck(_render_fn(0, inputs, _camera(12, 12), GRAD_CFG, corrupt=True), (x,),
                                  eps=1e-6, atol=1e-6, rtol=1e-4, raise_exception=False)
    assert not ok


def test_gradient_scene_is_not_trivial():
    """The gradcheck scene must cover pixels, overlap, and exercise the tile/slab machinery."""
    means, covs, colors, opacities = _scene(4, seed=3, scale=0.05)
    out = render(means, covs, colors, opacities, _camera(12, 12), BG, cfg=GRAD_CFG)
    assert (out["alpha"] > 0.05).sum() > 20
    assert out["alpha"].max() > 0.5


# ---------------------------------------------------------------- fast path == dense reference


@pytest.mark.parametrize("dtype, cfg, atol", [
    (F64, RasterConfig(tile_size=8, slab=3, max_elems=5000), 1e-11),   # many batches/slabs, partial tiles
    (F64, RasterConfig(), 1e-11),
    (torch.float32, RasterConfig(), 2e-5),                              # float32 cumsum-in-log vs product
])
def test_tiled_matches_reference_forward_and_vjp(dtype, cfg, atol):
    inputs = [t.to(dtype).requires_grad_() for t in _scene(60, seed=1)]
    camera, bg = _camera(37, 29), BG.to(dtype)
    fast = render(*inputs, camera, bg, cfg=cfg)
    ref = render_ref(*inputs, camera, bg, cfg=cfg)
    assert fast["alpha"].max() > 0.9 and (fast["alpha"] > 0.01).float().mean() > 0.2
    g = torch.Generator().manual_seed(7)
    cot = {k: torch.randn(fast[k].shape, generator=g, dtype=dtype) for k in KEYS}
    for k in ("rgb", "alpha", "depth", "depth_expected"):
        torch.testing.assert_close(fast[k], ref[k], atol=atol, rtol=0, msg=k)
    v_fast = torch.autograd.grad(sum((fast[k] * cot[k]).sum() for k in KEYS), inputs)
    v_ref = torch.autograd.grad(sum((ref[k] * cot[k]).sum() for k in KEYS), inputs)
    for name, a, b in zip(("means", "covs", "colors", "opacities"), v_fast, v_ref):
        scale = b.abs().max().item()
        assert scale > 0, name
        torch.testing.assert_close(a, b, atol=50 * atol * max(scale, 1.0), rtol=0, msg=name)


def test_per_tile_cap_warns_and_keeps_the_front():
    inputs = _scene(60, seed=1)
    with pytest.warns(UserWarning, match="max_per_tile"):
        out = render(*inputs, _camera(32, 32), BG, cfg=RasterConfig(max_per_tile=4))
    assert torch.isfinite(out["rgb"]).all()


# ---------------------------------------------------------------- image formation facts


def _single(mean, sigma: float, opacity: float = 0.9):
    means = torch.tensor([mean], dtype=F64)
    covs = (sigma**2 * torch.eye(3, dtype=F64))[None]
    return means, covs, torch.tensor([[1.0, 0.5, 0.25]], dtype=F64), torch.tensor([opacity], dtype=F64)


def test_expected_depth_of_one_gaussian_is_its_camera_z():
    camera = _camera(24, 24)
    means, covs, colors, opacities = _single([0.55, 0.45, 0.6], 0.05)
    out = render(means, covs, colors, opacities, camera, BG)
    z = camera.project(means)[1][0]
    covered = out["alpha"] > 0
    assert covered.sum() > 10
    torch.testing.assert_close(out["depth_expected"][covered], torch.full_like(out["alpha"][covered], z.item()))
    assert (out["depth"][~covered] == 0).all()


def test_opaque_gaussians_saturate_alpha_hand_computed():
    camera = _camera(17, 17)          # cx = cy = 8.5: the optical axis hits the centre of pixel (8, 8)
    centre = (8, 8)
    means, covs, colors, opacities = _single([0.5, 0.5, 0.5], 0.2, opacity=1.0)
    assert render(means, covs, colors, opacities, camera, BG)["alpha"][centre].item() == pytest.approx(0.99)
    # four 0.95-opaque layers on the axis: T = 0.05, 0.0025, 1.25e-4 (>= T_min); the 4th would give
    # 6.25e-6 < T_min, so compositing stops before it (3DGS rule)
    means = torch.tensor([[0.5, 0.5, 0.5 + 0.01 * k] for k in range(4)], dtype=F64)
    colors = torch.eye(4, 3, dtype=F64)   # red, green, blue, black
    out = render(means, covs.repeat(4, 1, 1), colors, torch.full((4,), 0.95, dtype=F64), camera, BG)
    w = torch.tensor([0.95, 0.95 * 0.05, 0.95 * 0.05**2], dtype=F64)
    assert out["alpha"][centre].item() == pytest.approx(1 - 0.05**3, abs=1e-12)
    torch.testing.assert_close(out["rgb"][centre], w + 0.05**3 * BG)
    z = 1.5 + 0.01 * torch.arange(3, dtype=F64)
    assert out["depth"][centre].item() == pytest.approx((w * z).sum().item())


def test_moving_right_moves_the_image_centroid_by_fx_dx_over_z():
    camera = _camera(64, 64)
    means, covs, colors, opacities = _single([0.5, 0.52, 0.5], 0.04)   # ~2.5 px std: well sampled
    right = torch.tensor(camera.w2c[0, :3], dtype=F64)        # world direction of image +x
    dx = 0.1   # ~6 px: the 3-sigma / alpha_min truncation aliases the centroid by ~3e-3 px

    def centroid(m):
        a = render(m, covs, colors, opacities, camera, BG)["alpha"]
        v, u = torch.meshgrid(torch.arange(64, dtype=F64) + 0.5, torch.arange(64, dtype=F64) + 0.5, indexing="ij")
        return torch.stack([(a * u).sum(), (a * v).sum()]) / a.sum()

    c0, c1 = centroid(means), centroid(means + dx * right)
    z = camera.project(means)[1][0].item()
    assert (c1 - c0)[0].item() == pytest.approx(camera.K[0, 0] * dx / z, rel=1e-3)
    assert abs((c1 - c0)[1].item()) < 1e-2     # pixels; only truncation aliasing moves it


def test_uniform_stretch_scales_silhouette_area_by_s_squared():
    """F = s I applied through follow(): means spread by s, covs by s^2; far camera ~ orthographic."""
    g = torch.Generator().manual_seed(0)
    d = torch.randn(400, 3, generator=g, dtype=F64)
    x0 = 0.5 + 0.15 * d / d.norm(dim=1, keepdim=True) * torch.rand(400, 1, generator=g, dtype=F64) ** (1 / 3)
    covs0 = (0.015**2 * torch.eye(3, dtype=F64)).repeat(400, 1, 1)
    idx = torch.arange(400)
    binding = Binding(rows=idx, cols=idx, weights=torch.ones(400, dtype=F64), n_gaussians=400, n_particles=400)
    camera = look_at([0.5, 0.5, -9.5], [0.5, 0.5, 0.5], [0, 1, 0], 3.0, 64, 64)   # 10 m away, narrow fov
    colors, opacities = torch.ones(400, 3, dtype=F64), torch.full((400,), 0.8, dtype=F64)
    areas = {}
    for s in (1.0, 1.4):
        x = 0.5 + s * (x0 - 0.5)
        F = s * torch.eye(3, dtype=F64).repeat(400, 1, 1)
        means, covs = follow(binding, x0, covs0, x0, x, F)
        areas[s] = render(means, covs, colors, opacities, camera, BG)["alpha"].sum().item()
    assert areas[1.0] > 200                                      # the ball is well resolved
    assert areas[1.4] / areas[1.0] == pytest.approx(1.4**2, rel=0.06)


def test_behind_camera_and_offscreen_gaussians_are_culled():
    camera = _camera(16, 16)
    # behind the camera (z = -0.5), closer than the near plane (z = 0.005), far off-screen
    means = torch.tensor([[0.5, 0.5, -1.5], [0.5, 0.5, -0.995], [30.0, 0.5, 0.5]], dtype=F64)
    covs = (0.1**2 * torch.eye(3, dtype=F64)).repeat(3, 1, 1)
    out = render(means, covs, torch.ones(3, 3, dtype=F64), torch.ones(3, dtype=F64), camera, BG)
    assert (out["alpha"] == 0).all()
    torch.testing.assert_close(out["rgb"], BG.expand(16, 16, 3))


# ---------------------------------------------------------------- input validation


@pytest.mark.parametrize("bad, message", [
    (lambda m, c, col, o: (m.clone().fill_(float("nan")), c, col, o), "non-finite"),
    (lambda m, c, col, o: (m, c, col, o + 1.0), r"\[0, 1\]"),
    (lambda m, c, col, o: (m[:, :2], c, col, o), "means must be"),
    (lambda m, c, col, o: (m, c[:, :2], col, o), "covs must be"),
    (lambda m, c, col, o: (m, c, col, o[:-1]), "opacities must be"),
    (lambda m, c, col, o: (m, c, col.float(), o), "one floating dtype"),
])
def test_bad_inputs_raise_naming_the_file(bad, message):
    inputs = bad(*_scene(5, seed=0))
    with pytest.raises(RenderError, match=f"rasterize.py.*{message}"):
        render(*inputs, _camera(8, 8), BG)


def test_gsplat_backend_refuses_cpu_tensors_clearly():
    with pytest.raises(RenderError, match="gsplat.*CUDA"):
        render(*_scene(3, seed=0), _camera(8, 8), BG, backend="gsplat")
    with pytest.raises(RenderError, match="unknown backend"):
        render(*_scene(3, seed=0), _camera(8, 8), BG, backend="opengl")


# ---------------------------------------------------------------- CUDA (skipped on CPU machines)


@pytest.mark.gpu
def test_cuda_matches_cpu():
    inputs = _scene(300, seed=2, dtype=torch.float32)
    camera = _camera(64, 48)
    cpu = render(*inputs, camera, BG.float())
    gpu = render(*[t.cuda() for t in inputs], camera, BG.float().cuda())
    for k in KEYS:
        torch.testing.assert_close(gpu[k].cpu(), cpu[k], atol=1e-5, rtol=0, msg=k)


@pytest.mark.gpu
def test_gsplat_backend_matches_torch_under_gsplat_rules():
    """gsplat clamps alpha at 0.999 and cuts at alpha < 1/255 only; with those rules we agree
    (measured on an H200: max |diff| ~1e-6, VJPs within ~4e-4 relative)."""
    pytest.importorskip("gsplat")
    inputs = [t.cuda().requires_grad_() for t in _scene(300, seed=2, dtype=torch.float32)]
    camera, bg = _camera(64, 48), BG.float().cuda()
    cfg = RasterConfig(alpha_max=0.999, sigma_cutoff=3.5)
    ours, theirs = render(*inputs, camera, bg, cfg=cfg), render(*inputs, camera, bg, backend="gsplat", cfg=cfg)
    for k in KEYS:
        torch.testing.assert_close(ours[k], theirs[k], atol=1e-4, rtol=0, msg=k)
    v_ours = torch.autograd.grad(sum(ours[k].sum() for k in KEYS), inputs)
    v_theirs = torch.autograd.grad(sum(theirs[k].sum() for k in KEYS), inputs)
    for a, b in zip(v_ours, v_theirs):
        assert ((a - b).abs().max() / b.abs().max()).item() < 2e-3


def test_ewa_projection_on_axis_hand_computed():
    """Isotropic sigma on the optical axis at depth z: Sigma_2d = (f sigma / z)^2 I + 0.3 I."""
    from gca.render import project_gaussians
    camera = _camera(32, 32, fov=60.0)
    K, w2c = camera.tensors(F64)
    sigma, z = 0.05, 1.5
    proj = project_gaussians(torch.tensor([[0.5, 0.5, 0.5]], dtype=F64), (sigma**2 * torch.eye(3, dtype=F64))[None],
                             K, w2c, 32, 32)
    var = (camera.K[0, 0] * sigma / z) ** 2 + 0.3
    torch.testing.assert_close(proj.conics[0], torch.tensor([1 / var, 0.0, 1 / var], dtype=F64))
    torch.testing.assert_close(proj.means2d[0], torch.tensor([16.0, 16.0], dtype=F64))
    assert proj.radii[0].item() == pytest.approx(3 * var**0.5)
    assert proj.depths[0].item() == pytest.approx(z)


# ---------------------------------------------------------------- frames at once (session 40)


def _frames(T: int, n: int, dtype=F64):
    """T frames of the same n Gaussians moved and stretched: means [T, n, 3], covs [T, n, 3, 3], colours [T, n, 3]
    (each frame its own, as view-dependent colours are), the shared opacities [n]."""
    means, covs, colors, opacities = _scene(n, seed=4, dtype=dtype)
    shift = torch.linspace(-0.05, 0.05, T, dtype=dtype)[:, None, None]
    stretch = 1.0 + torch.linspace(0.0, 0.3, T, dtype=dtype)[:, None, None, None]
    return means + shift, covs * stretch, colors * (1.0 - shift.abs()), opacities


def test_frames_at_once_equal_each_frame_and_name_a_bad_frame():
    """render with a leading frame dim (the torch backend: frame by frame inside) equals rendering each frame,
    values and gradients; its input stats are one row per frame, and a bad frame is named by its index."""
    means, covs, colors, opacities = (t.requires_grad_() for t in _frames(3, 40))
    camera = _camera(24, 20)
    checks = []
    out = render(means, covs, colors, opacities, camera, BG, checks=checks)
    assert out["rgb"].shape == (3, 20, 24, 3) and checks[0].shape == (3, 6)
    loss = sum((out[k] * (1.0 + torch.arange(out[k].numel(), dtype=F64).reshape(out[k].shape).sin())).sum()
               for k in KEYS)
    grads = torch.autograd.grad(loss, (means, covs, colors, opacities))
    g_opacity = torch.zeros_like(opacities)
    for t in range(3):
        inputs = [x[t].detach().requires_grad_() for x in (means, covs, colors)] + [opacities.detach().requires_grad_()]
        ref = render(*inputs, camera, BG)
        w = {k: 1.0 + torch.arange(out[k].numel(), dtype=F64).reshape(out[k].shape).sin()[t] for k in KEYS}
        for k in KEYS:
            torch.testing.assert_close(out[k][t], ref[k])
        r = torch.autograd.grad(sum((ref[k] * w[k]).sum() for k in KEYS), inputs)
        for a, b in zip(grads[:3], r[:3]):
            torch.testing.assert_close(a[t], b)
        g_opacity += r[3]
    torch.testing.assert_close(grads[3], g_opacity)
    bad = means.detach().clone()
    bad[2, 7, 0] = float("nan")
    with pytest.raises(RenderError, match="frame 2: means has 1 non-finite"):
        render(bad, covs.detach(), colors.detach(), opacities.detach(), camera, BG)
    with pytest.raises(RenderError, match=r"colors must be \[3, 40, C\]"):
        render(means.detach(), covs.detach(), colors.detach()[0], opacities.detach(), camera, BG)


@pytest.mark.gpu
def test_gsplat_frames_in_one_call_equal_each_frame():
    """gsplat's frame batch (a training iteration's frames in one call, session 40) renders what gsplat renders frame
    by frame: images and the gradients to each frame's means, covariances and colours, and to the shared opacities."""
    pytest.importorskip("gsplat")
    means, covs, colors, opacities = (t.float().cuda().requires_grad_() for t in _frames(4, 300))
    camera, bg = _camera(64, 48), BG.float().cuda()
    out = render(means, covs, colors, opacities, camera, bg, backend="gsplat")
    weights = {k: torch.rand(out[k].shape, device="cuda", generator=torch.Generator("cuda").manual_seed(0))
               for k in KEYS}
    grads = torch.autograd.grad(sum((out[k] * weights[k]).sum() for k in KEYS), (means, covs, colors, opacities))
    g_opacity = torch.zeros_like(opacities)
    for t in range(4):
        inputs = [x[t].detach().requires_grad_() for x in (means, covs, colors)] + [opacities.detach().requires_grad_()]
        ref = render(*inputs, camera, bg, backend="gsplat")
        for k in KEYS:
            torch.testing.assert_close(out[k][t], ref[k], atol=1e-5, rtol=1e-5, msg=k)
        r = torch.autograd.grad(sum((ref[k] * weights[k][t]).sum() for k in KEYS), inputs)
        for a, b in zip(grads[:3], r[:3]):
            torch.testing.assert_close(a[t], b, atol=1e-5 * float(b.abs().max()), rtol=1e-4)
        g_opacity += r[3]
    torch.testing.assert_close(grads[3], g_opacity, atol=1e-5 * float(g_opacity.abs().max()), rtol=1e-4)
