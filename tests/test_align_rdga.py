"""RDGA terms and switches (gca/align/rdga.py) on small synthetic frames."""

import dataclasses
import sys
import functools
from pathlib import Path

import numpy as np
import pytest
import torch

from gca.align import rdga as _rdga
from gca.align.rdga import global_term, mask_loss, rdga_frames, rdga_loss, render_points, stable_region

# these tests were written for the mean silhouette (the default is params.yaml's sum since issue 24)
RDGAConfig = functools.partial(_rdga.RDGAConfig, mask_reduction="mean")

H = W = 48


def _disk(radius, size=H, centre=None):
    c = (size - 1) / 2 if centre is None else centre
    rows, cols = torch.meshgrid(torch.arange(size), torch.arange(size), indexing="ij")
    return ((rows - c) ** 2 + (cols - c) ** 2).sqrt() <= radius


def _scene(dtype=torch.float64):
    """A disk object with a bumpy rendered depth, matches p = q on a grid, and a premult uv image."""
    alpha = _disk(18).to(dtype)
    rows, cols = torch.meshgrid(torch.arange(H, dtype=dtype), torch.arange(W, dtype=dtype), indexing="ij")
    depth = (2.0 + 0.3 * torch.sin(cols / 3.0) * torch.cos(rows / 4.0) + 0.01 * (cols - 20) ** 2 / 20) * alpha
    pts = torch.stack(torch.meshgrid(torch.arange(6, 42, 4.0), torch.arange(6, 42, 4.0), indexing="xy"), -1)
    p = pts.reshape(-1, 2).to(dtype)
    uv = torch.stack([cols + 0.5, rows + 0.5], -1)  # renderer convention: pixel centre at i + 0.5
    return alpha, depth, p, uv


def test_mask_loss_hand_computed():
    alpha = torch.tensor([[1.0, 0.5], [0.0, 0.0]])
    gt = torch.tensor([[True, False], [True, False]])
    assert float(mask_loss(alpha, gt)) == pytest.approx((0 + 0.25 + 1 + 0) / 4)
    assert float(mask_loss(alpha, gt, "sum")) == pytest.approx(1.25)


def test_eroded_stable_region_removes_band_of_half_r_on_disk():
    R, r = 18, 9
    h = (r - 1) // 2
    disk = _disk(R, size=64, centre=32)
    stable = stable_region(disk, r)
    assert bool((stable & ~disk).any()) is False
    # through the centre, pixel (32, 32 - e) survives iff its kernel's corner (e + h, h) is in the
    # disk: e_max = floor(sqrt(R^2 - h^2)) - h (= 13 here, i.e. a band of 5 px ~ r / 2 removed)
    e_max = int(np.floor(np.sqrt(R**2 - h**2))) - h
    cols = torch.nonzero(stable[32])[:, 0]
    assert int(cols.min()) == 32 - e_max and int(cols.max()) == 32 + e_max
    dist = ((torch.arange(64)[:, None] - 32.0) ** 2 + (torch.arange(64)[None] - 32.0) ** 2).sqrt()
    assert bool(stable[dist <= R - h * np.sqrt(2) - 1].all())  # deep interior kept
    assert not bool(stable[dist > R - h].any())  # a band of width >= h removed everywhere


def test_paper_literal_stable_region_is_the_top_hat_protrusion():
    mask = torch.zeros(32, 32, dtype=torch.bool)
    mask[8:24, 8:20] = True  # a 16 x 12 block survives the opening
    mask[15, 20:30] = True  # a 1-px-wide protrusion does not
    literal = stable_region(mask, 5, "paper_literal")
    expected = torch.zeros_like(mask)
    expected[15, 20:30] = True
    assert torch.equal(literal, expected)
    assert not bool((stable_region(mask, 5, "eroded") & expected).any())


def test_anchor_term_rank_is_scale_invariant_and_gives_depth_gradient():
    alpha, depth, p, uv = _scene()
    depth.requires_grad_(True)
    cfg = RDGAConfig(use_global=False, r=7, k=5, tau=0.5, lambda2=1.0, lambda_mask=0.0, temperature=0.01)
    est = 3.0 * depth.detach() ** 2 + 1.0  # a positive monotone warp of the true depth
    loss, stats = rdga_loss({"alpha": alpha, "depth": depth}, alpha > 0.5, est, p, p, cfg)
    assert stats["n_matches"] == len(p) and 0 < stats["n_anchors"] == stats["n_stable"] < len(p)
    assert stats["mean_gamma"] == pytest.approx(1.0)
    assert float(loss.detach()) == pytest.approx(-stats["n_anchors"], rel=1e-3)  # sum of -gamma, gamma ~ 1
    loss.backward()
    assert torch.isfinite(depth.grad).all() and depth.grad.abs().sum() > 0
    for warped in (0.01 * est + 7.0, est ** 0.3):
        loss_w, _ = rdga_loss({"alpha": alpha, "depth": depth}, alpha > 0.5, warped, p, p, cfg)
        assert float(loss_w.detach()) == pytest.approx(float(loss.detach()), abs=1e-9)


def test_l1_ablation_is_not_scale_invariant():
    alpha, depth, p, _ = _scene()
    cfg = RDGAConfig(use_global=False, depth_term="l1", r=7, k=5, lambda_mask=0.0, lambda2=1.0)
    out = {"alpha": alpha, "depth": depth}
    same, _ = rdga_loss(out, alpha > 0.5, depth, p, p, cfg)
    scaled, _ = rdga_loss(out, alpha > 0.5, 3.0 * depth + 1.0, p, p, cfg)
    assert float(same) == pytest.approx(0.0) and float(scaled) > 1.0


def test_consensus_filter_rejects_reversed_depth():
    alpha, depth, p, _ = _scene()
    cfg = RDGAConfig(use_global=False, r=7, k=5, tau=0.5)
    _, stats = rdga_loss({"alpha": alpha, "depth": depth}, alpha > 0.5, -depth, p, p, cfg)
    assert stats["n_stable"] > 0 and stats["n_anchors"] == 0 and stats["mean_gamma"] == pytest.approx(-1.0)


@pytest.mark.parametrize("channels", [2, 3])
def test_global_term_zero_when_aligned_and_pulls_toward_q(channels):
    alpha, depth, p, uv = _scene()
    K = torch.tensor([[40.0, 0, W / 2], [0, 40.0, H / 2], [0, 0, 1]], dtype=torch.float64)
    delta = torch.zeros(2, dtype=torch.float64, requires_grad=True)  # a 2D shift of the "Gaussians"

    def pos_image():
        shifted = uv + delta
        if channels == 2:
            return shifted * alpha[..., None]
        z = torch.full_like(alpha, 2.0)[..., None]
        xy = (shifted - K[:2, 2]) / torch.stack([K[0, 0], K[1, 1]]) * z
        return torch.cat([xy, z], -1) * alpha[..., None]

    cfg = RDGAConfig(use_anchor=False, lambda_mask=0.0, lambda1=1.0, global_reduction="mean")
    out = {"alpha": alpha, "depth": depth}
    Kc = K if channels == 3 else None
    aligned, stats = rdga_loss(out, alpha > 0.5, depth, p, p, cfg, pos_image(), Kc)
    assert stats["n_global"] > 0 and float(aligned.detach()) < 1e-5
    shift = torch.tensor([2.0, 1.0], dtype=torch.float64)
    loss, _ = rdga_loss(out, alpha > 0.5, depth, p, p + shift, cfg, pos_image(), Kc)
    assert float(loss.detach()) == pytest.approx(float(shift.norm()), rel=1e-6)
    loss.backward()
    torch.testing.assert_close(-delta.grad, shift / shift.norm())  # descent moves toward q


def test_global_max_px_drops_the_wrong_match_that_would_set_the_norms_direction():
    """Matches off by (2, 1) px but one off by (0, 14) px (all well inside the object): the paper's norm
    turns towards the outlier; with ``global_max_px`` 6 the term is the inliers' alone (value and gradient)."""
    alpha, depth, p, uv = _scene()
    centre = (H - 1) / 2
    p = p[((p - centre).norm(dim=1) <= 8.0)]  # q = p + shift stays > 2 px inside the radius-18 disk
    p = p[(p - centre).norm(dim=1).argsort()]  # p[0]: the most central, the outlier
    shift = torch.tensor([2.0, 1.0], dtype=torch.float64).repeat(len(p), 1)
    shift[0] = torch.tensor([0.0, 14.0], dtype=torch.float64)
    out, mask = {"alpha": alpha, "depth": depth}, alpha > 0.5
    delta = torch.zeros(2, dtype=torch.float64, requires_grad=True)

    def term(max_px, p, q):
        delta.grad = None
        cfg = RDGAConfig(use_anchor=False, lambda_mask=0.0, lambda1=1.0, global_max_px=max_px)
        loss, stats = rdga_loss(out, mask, depth, p, q, cfg, (uv + delta) * alpha[..., None])
        loss.backward()
        return float(loss.detach()), delta.grad.clone(), stats["n_global"]

    all_value, all_grad, n_all = term(0.0, p, p + shift)
    cut_value, cut_grad, n_cut = term(6.0, p, p + shift)
    ref_value, ref_grad, n_ref = term(0.0, p[1:], p[1:] + shift[1:])
    assert n_all == len(p) and n_cut == n_ref == len(p) - 1
    assert cut_value == pytest.approx(ref_value, rel=1e-9) and torch.allclose(cut_grad, ref_grad)
    assert cut_value == pytest.approx(5 ** 0.5 * n_cut ** 0.5, rel=1e-6)  # norm of (n-1) residuals of sqrt(5)
    cos = lambda a, b: float(a @ b / (a.norm() * b.norm()))  # noqa: E731
    assert cos(-cut_grad, shift[1]) > 0.999  # descent towards the inliers' q
    assert cos(-all_grad, shift[1]) < 0.97  # without the cut one outlier in ~a dozen turns it by > 14 deg
    with pytest.raises(ValueError, match="global_max_px"):
        RDGAConfig(global_max_px=-1.0)


def test_render_points_matches_the_pixel_centre_convention():
    alpha, _, p, uv = _scene()
    torch.testing.assert_close(render_points(uv * alpha[..., None], alpha, p[20:25]), p[20:25])


def test_switches():
    alpha, depth, p, uv = _scene()
    gt = _disk(16) > 0.5
    out = {"alpha": alpha, "depth": depth.requires_grad_(True)}
    base = RDGAConfig(r=7, k=5, lambda_mask=2.0)
    off, stats = rdga_loss(out, gt, depth.detach(), p, p, dataclasses.replace(base, enabled=False))
    assert float(off.detach()) == pytest.approx(2.0 * float(mask_loss(alpha, gt)))
    assert stats["n_anchors"] == 0
    no_anchor, _ = rdga_loss(out, gt, depth.detach(), p, p, dataclasses.replace(base, use_anchor=False),
                             uv * alpha[..., None])
    no_anchor.backward()
    assert depth.grad is None or float(depth.grad.abs().sum()) == 0.0
    with pytest.raises(ValueError, match="pos_image"):
        rdga_loss(out, gt, depth.detach(), p, p, base)


def test_bad_inputs_raise_with_diagnostics():
    alpha, depth, p, _ = _scene()
    cfg = RDGAConfig(use_global=False, r=7, k=5)
    with pytest.raises(ValueError, match="rdga.py.*est_depth"):
        rdga_loss({"alpha": alpha, "depth": depth}, alpha > 0.5, depth[:-1], p, p, cfg)
    with pytest.raises(ValueError, match="p and q"):
        rdga_loss({"alpha": alpha, "depth": depth}, alpha > 0.5, depth, p, p[:3], cfg)
    with pytest.raises(ValueError, match="RDGAConfig.k"):
        RDGAConfig(k=4)
    bad = depth.clone()
    bad[24, 24] = float("nan")
    with pytest.raises(FloatingPointError, match="non-finite"):
        rdga_loss({"alpha": alpha, "depth": bad}, alpha > 0.5, depth, p, p, cfg)


def test_anchors_survive_the_simulated_estimator_and_l1_does_not():
    """Rendered depth = GT depth; D_gt from the estimator model (warp, bleed, noise, scale/shift)."""
    from gca.vision.depth import SimulatedDepth, SimulatedDepthConfig

    alpha, depth, p, _ = _scene()
    est = SimulatedDepth(SimulatedDepthConfig(), seed=0).estimate(
        np.zeros((1, H, W, 3), np.uint8), depth.numpy()[None], (alpha > 0.5).numpy()[None])[0]
    out = {"alpha": alpha, "depth": depth}
    cfg = RDGAConfig(use_global=False, r=7, k=5, lambda_mask=0.0, lambda2=1.0, anchor_reduction="mean")
    rank, stats = rdga_loss(out, alpha > 0.5, est, p, p, cfg)
    assert stats["n_anchors"] >= 0.8 * stats["n_stable"] > 0 and stats["mean_gamma_anchor"] > 0.8, stats
    l1, _ = rdga_loss(out, alpha > 0.5, est, p, p, dataclasses.replace(cfg, depth_term="l1"))
    l1_true, _ = rdga_loss(out, alpha > 0.5, depth, p, p, dataclasses.replace(cfg, depth_term="l1"))
    assert float(l1_true) == 0.0 and float(l1) > 0.1  # the L1 term penalises the correct geometry
    assert float(rank) < -0.8  # the rank term nearly reaches its optimum at the correct geometry


def test_global_reductions_on_hand_computed_residuals():
    """Two matches off by (3, 4) and (0, 0) px: norm 5, mean 2.5, mean_sq 12.5; only mean_sq's gradient
    shrinks with the residual (x0.1 residual -> x0.1 gradient), the others keep a unit-size pull."""
    from gca.align.rdga import global_term
    q = torch.zeros(2, 2, dtype=torch.float64)
    for reduction, value in (("norm", 5.0), ("mean", 2.5), ("mean_sq", 12.5)):
        P = torch.tensor([[3.0, 4.0], [0.0, 0.0]], dtype=torch.float64, requires_grad=True)
        assert float(global_term(P, q, reduction).detach()) == pytest.approx(value, rel=1e-6)  # sqrt(. + 1e-12)
        (g_big,) = torch.autograd.grad(global_term(P, q, reduction), P)
        P_small = (0.1 * P.detach()).requires_grad_(True)
        (g_small,) = torch.autograd.grad(global_term(P_small, q, reduction), P_small)
        ratio = float(g_small.norm() / g_big.norm())
        assert ratio == pytest.approx(0.1 if reduction == "mean_sq" else 1.0, rel=1e-4)


def _sheet_motion(gradient: str) -> tuple[float, float]:
    """d P_render / d t [px/m] at the image centre for a dense sheet of small Gaussians (1 m in front of
    the camera) translated sideways by t, and the camera's fx [px]."""
    from gca.align.rdga import position_colors, position_image
    from gca.render import look_at
    from gca.render.rasterize import render

    camera = look_at((0.0, 0.0, 1.0), (0.0, 0.0, 0.0), (0.0, 1.0, 0.0), 30.0, 48, 48)
    K, _ = camera.tensors(torch.float64)
    g = torch.arange(-0.15, 0.1501, 0.006, dtype=torch.float64)
    gx, gy = torch.meshgrid(g, g, indexing="ij")
    means0 = torch.stack([gx.ravel(), gy.ravel(), torch.zeros(gx.numel(), dtype=torch.float64)], -1)
    covs = torch.diag(torch.tensor([0.006, 0.006, 0.002], dtype=torch.float64) ** 2).expand(len(means0), 3, 3)
    t = torch.zeros((), dtype=torch.float64, requires_grad=True)
    means = means0 + t * torch.tensor([1.0, 0.0, 0.0], dtype=torch.float64)
    colors = position_colors(camera.to_camera(means), gradient)
    out = render(means, covs, colors, torch.full((len(means),), 0.9, dtype=torch.float64), camera,
                 torch.zeros(colors.shape[1], dtype=torch.float64))
    alpha = out["alpha"].detach() if gradient == "material" else out["alpha"]
    P = render_points(position_image(out["rgb"], gradient), alpha, torch.tensor([[23.5, 23.5]], dtype=torch.float64), K)
    (dP,) = torch.autograd.grad(P[0, 0], t)
    return float(dP), float(K[0, 0])


def test_global_gradient_moves_the_material_seen_at_p_not_the_ray():
    """The surface seen at a pixel of a dense splat stays on that pixel's ray however the Gaussians move,
    so the rasterizer's full derivative of P_render is ~0 (a gradient of noise, benchmarks/NOTES.md
    session 6); with the compositing weights held it is the image motion of that material, fx / z."""
    material, fx = _sheet_motion("material")
    full, _ = _sheet_motion("full")
    assert abs(material) == pytest.approx(fx, rel=0.05)   # 1 m away: fx px per metre of motion
    assert abs(full) < 0.2 * fx  # 0.1 fx here, -> 0 as the splat gets denser


def test_material_position_image_keeps_the_value():
    from gca.align.rdga import position_colors, position_image

    x = torch.randn(5, 3, dtype=torch.float64, requires_grad=True)
    w = torch.rand(4, 5, dtype=torch.float64, requires_grad=True)  # stand-in compositing weights
    held = position_image(w @ position_colors(x, "material"), "material")
    torch.testing.assert_close(held, w @ x)
    gx, gw = torch.autograd.grad(held.sum(), (x, w))
    torch.testing.assert_close(gx, w.sum(0)[:, None].expand(5, 3).detach())
    torch.testing.assert_close(gw, torch.zeros_like(gw), rtol=0, atol=1e-12)  # none through the weights (to rounding)
    with pytest.raises(ValueError, match="global_gradient"):
        position_colors(x, "weights")


def _selected_reference(out, gt, est, p, q, cfg, pos, K=None):
    """Session 31's RDGA (boolean-mask selections, checks read per frame), from its definitions: the global term on
    the selected matches and the anchor term on the selected patches, summed as rdga_loss weighs them."""
    from gca.align.rdga import _lookup, gather_patches, global_term, render_points, stable_matches
    from gca.align.softrank import spearman_exact, spearman_soft

    alpha, depth = out["alpha"], out["depth"]
    on = _lookup(alpha.detach() > cfg.alpha_threshold, p) & _lookup(gt, q)
    P_r, P_g = render_points(pos, alpha.detach(), p[on], K), q[on]
    inl = (P_r.detach() - P_g).norm(dim=-1) <= cfg.global_max_px if cfg.global_max_px > 0 else torch.ones_like(on[on])
    l_global = global_term(P_r[inl], P_g[inl], cfg.global_reduction)
    stable = stable_matches(alpha, gt, p, q, cfg)
    N_p, N_q = gather_patches(depth, p[stable], cfg.k)[0], gather_patches(est, q[stable], cfg.k)[0]
    varied = (N_p.detach().std(-1) > 0) & (N_q.std(-1) > 0)
    N_p, N_q = N_p[varied], N_q[varied]
    anchors = spearman_exact(N_p, N_q) > cfg.tau
    per = -spearman_soft(N_p[anchors], N_q[anchors], cfg.temperature)
    l_anchor = per.sum() if cfg.anchor_reduction == "sum" else per.mean()
    loss = cfg.lambda_mask * mask_loss(alpha, gt) + cfg.lambda_geo * (cfg.lambda1 * l_global + cfg.lambda2 * l_anchor)
    return loss, int(on[on][inl].sum()) if cfg.global_max_px > 0 else int(on.sum()), int(anchors.sum())


@pytest.mark.parametrize("channels", [2, 3])
@pytest.mark.parametrize("reduction", ["norm", "mean", "mean_sq"])
def test_rdga_with_deferred_checks_equals_the_selected_terms_and_reads_nothing(reduction, channels):
    """Session 32: a training frame's RDGA keeps its selections as 0/1 weights and its checks and stats as tensors
    (``checks=`` a list, judged once per iteration), so the host never waits for the device mid-frame. Same loss,
    gradient and stats as the boolean-mask selection (float64); under the CPU sync detector it reads nothing,
    where the immediate form (``checks=None``) must read (the control)."""
    sys.path.insert(0, str(Path(__file__).parent))
    from host_sync import HostSync, no_host_sync

    alpha, depth, p, uv = _scene()
    gt = _disk(17) > 0.5  # the GT silhouette a little smaller: some matches leave it
    q = p + torch.tensor([0.6, -0.4], dtype=torch.float64) * (p[:, :1] > 24)  # half of them off by < 1 px
    est = 1.5 * depth + 0.05 * torch.sin(torch.arange(H * W, dtype=torch.float64).reshape(H, W))
    cfg = RDGAConfig(r=7, k=5, lambda_mask=2.0, lambda1=0.7, lambda2=0.3, global_reduction=reduction,
                     global_max_px=0.5, tau=0.5)
    K = torch.tensor([[40.0, 0, W / 2], [0, 40.0, H / 2], [0, 0, 1]], dtype=torch.float64)
    results = {}
    for mode in ("reference", "immediate", "deferred"):
        d = depth.clone().requires_grad_(True)
        shift = torch.zeros(2, dtype=torch.float64, requires_grad=True)
        out, pos = {"alpha": alpha, "depth": d}, _positions(uv + shift, alpha, K if channels == 3 else None)
        Kc = K if channels == 3 else None  # training's form: camera-frame xyz projected with the intrinsics
        if mode == "reference":
            loss, n_global, n_anchors = _selected_reference(out, gt, est, p, q, cfg, pos, Kc)
            stats = {"n_global": n_global, "n_anchors": n_anchors}
        elif mode == "immediate":
            loss, stats = rdga_loss(out, gt, est, p, q, cfg, pos, Kc)
        else:
            checks = []
            with no_host_sync():
                loss, stats = rdga_loss(out, gt, est, p, q, cfg, pos, Kc, checks=checks)
            assert all(isinstance(v, torch.Tensor) for k, v in stats.items() if k != "n_matches")
            _rdga.judge(checks)  # passes: nothing non-finite
        loss.backward()
        results[mode] = (float(loss.detach()), d.grad.clone(), shift.grad.clone(), int(stats["n_global"]), int(stats["n_anchors"]))
    ref = results["reference"]
    assert 0 < ref[3] < len(p) and 0 < ref[4] < len(p)  # both selections select some, not all: not vacuous
    assert float(ref[1].abs().sum()) > 0 and float(ref[2].abs().sum()) > 0
    for mode in ("immediate", "deferred"):
        got = results[mode]
        assert got[0] == pytest.approx(ref[0], rel=1e-12) and got[3:] == ref[3:]
        torch.testing.assert_close(got[1], ref[1], rtol=1e-10, atol=1e-14)
        torch.testing.assert_close(got[2], ref[2], rtol=1e-10, atol=1e-14)
    with pytest.raises(HostSync):  # control: the immediate form reads the device
        with no_host_sync():
            rdga_loss({"alpha": alpha, "depth": depth}, gt, est, p, q, cfg, uv * alpha[..., None])


def _positions(uv, alpha, K=None):
    """The premultiplied position image of pixel-centre points ``uv`` [H, W, 2]: the points themselves (2 channels)
    or their camera-frame xyz at depth 2 (3 channels, projected back with ``K``)."""
    if K is None:
        return uv * alpha[..., None]
    z = torch.full_like(alpha, 2.0)[..., None]
    xy = (uv - K[:2, 2]) / torch.stack([K[0, 0], K[1, 1]]) * z
    return torch.cat([xy, z], -1) * alpha[..., None]


def test_deferred_checks_raise_when_judged_and_name_the_count():
    alpha, depth, p, uv = _scene()
    cfg = RDGAConfig(use_global=False, r=7, k=5)
    bad = depth.clone()
    bad[24, 24] = float("nan")  # inside a stable anchor patch
    checks = []
    loss, _ = rdga_loss({"alpha": alpha, "depth": bad}, alpha > 0.5, depth, p, p, cfg, checks=checks)
    with pytest.raises(FloatingPointError, match=r"rendered depth is non-finite in [1-9]\d* of \d+ anchor patches"):
        _rdga.judge(checks)
    checks = []
    rdga_loss({"alpha": alpha, "depth": depth}, alpha > 0.5, depth, p, p, cfg, checks=checks)
    _rdga.judge(checks)  # control: the same frame with a finite depth passes


def test_global_term_over_a_selection_equals_the_selected_sets():
    g = torch.Generator().manual_seed(3)
    P = torch.randn(9, 2, dtype=torch.float64, generator=g)
    Q = torch.randn(9, 2, dtype=torch.float64, generator=g)
    for use in (torch.tensor([1, 0, 1, 1, 0, 0, 1, 0, 1], dtype=torch.bool), torch.zeros(9, dtype=torch.bool)):
        for reduction in ("norm", "mean", "mean_sq"):
            a, b = P.clone().requires_grad_(True), P.clone().requires_grad_(True)
            masked = global_term(a, Q, reduction, use=use)
            selected = global_term(b[use], Q[use], reduction)
            (masked + 0.0).backward()
            (selected + 0.0).backward() if selected.requires_grad else None
            assert float(masked.detach()) == pytest.approx(float(selected.detach()), rel=1e-12, abs=0.0)
            torch.testing.assert_close(a.grad, b.grad if b.grad is not None else torch.zeros_like(P))


@pytest.mark.parametrize("r", [1, 2, 3, 4, 9, 41])
@pytest.mark.parametrize("mode", ["eroded", "paper_literal"])
def test_stable_region_equals_a_geodesic_morphology(r, mode):
    """The max-pooling stable region equals a geodesic erosion and opening by a flat r x r square (outside pixels
    ignored) from scipy.ndimage for every r (even r: the dilation's window reflected, Minkowski's convention, which
    kornia >= 0.9 shares) and kornia.morphology's for odd r (the default 9 among them), on masks with a solid block,
    1-px strokes and noise, touching the image border, r = 41 larger than the image; a border that erodes (0
    outside), the control, differs from it on a full mask."""
    import kornia.morphology as morph
    from scipy import ndimage

    rng = np.random.default_rng(r)
    for _ in range(3):
        mask = rng.random((37, 29)) > 0.4
        mask[5:30, 3:20] = True  # a solid block (the default r = 9 leaves its interior)
        mask[:, 0] = True  # a 1-px stroke along the border
        mask[10, :] = True  # and one across the image
        eroded = ndimage.grey_erosion(mask.astype(float), size=(r, r), mode="constant", cval=np.inf)
        opened = ndimage.grey_dilation(eroded, size=(r, r), mode="constant", cval=-np.inf)
        ref = eroded > 0.5 if mode == "eroded" else (mask.astype(float) - opened) > 0.5
        got = stable_region(torch.from_numpy(mask), r, mode)
        assert np.array_equal(got.numpy(), ref)
        if r % 2:
            m = torch.from_numpy(mask).float()[None, None]
            kernel = torch.ones(r, r)
            k_ref = morph.erosion(m, kernel) if mode == "eroded" else m - morph.opening(m, kernel)
            assert torch.equal(got, k_ref[0, 0] > 0.5)
    if mode == "eroded" and r > 1:  # the control: a border that erodes eats a band of a full mask; this one does not
        full = torch.ones(37, 29, dtype=torch.bool)
        eroding = ndimage.grey_erosion(np.ones((37, 29)), size=(r, r), mode="constant", cval=0.0) > 0.5
        assert stable_region(full, r).all() and not eroding.all()


@pytest.mark.parametrize("depth_term", ["rank", "l1"])
@pytest.mark.parametrize("reduction", ["norm", "mean_sq"])
def test_frames_at_once_equal_each_frame_alone(depth_term, reduction):
    """rdga_frames (session 40: a training iteration's frames in one call, each frame's matches padded to the
    longest with ``valid`` rows) equals rdga_loss frame by frame: each frame's loss, its gradient to the depth and
    to the positions, its terms and its stats (float64). Three frames of different objects and match counts, one
    with none; the padded rows sit where a real match would count (on the object, in the stable region), so a
    padding that leaked into the sums would change them. Control: the same call without ``valid`` differs."""
    alpha0, depth0, p0, uv = _scene()
    K = torch.tensor([[40.0, 0, W / 2], [0, 40.0, H / 2], [0, 0, 1]], dtype=torch.float64)
    cfg = RDGAConfig(r=7, k=5, lambda_mask=2.0, lambda1=0.7, lambda2=0.3, global_reduction=reduction, tau=0.3,
                     depth_term=depth_term)
    g = torch.Generator().manual_seed(0)
    frames = []
    for t, (n, shift) in enumerate([(len(p0), 0.0), (17, 1.5), (0, -2.0)]):
        alpha = _disk(18 - 2 * t, centre=(H - 1) / 2 + shift).to(torch.float64)
        depth = depth0.roll(t, 1) * alpha + 0.02 * t
        p = p0[torch.randperm(len(p0), generator=g)[:n]] + 0.3 * t
        q = p + 0.4 * torch.randn(p.shape, generator=g, dtype=torch.float64)
        est = 1.5 * depth + 0.05 * torch.sin(torch.arange(H * W, dtype=torch.float64).reshape(H, W) + t)
        frames.append((alpha, depth, p, q, est, _disk(17 - t) > 0.5))
    depth = torch.stack([f[1] for f in frames]).requires_grad_(True)
    pos = torch.stack([_positions(uv, f[0], K) for f in frames]).requires_grad_(True)
    M = max(len(f[2]) for f in frames)
    pad = torch.tensor([24.0, 24.0], dtype=torch.float64)  # the centre: a stable, on-object place
    P = torch.stack([torch.cat([f[2], pad.expand(M - len(f[2]), 2)]) for f in frames])
    Q = torch.stack([torch.cat([f[3], pad.expand(M - len(f[3]), 2)]) for f in frames])
    valid = torch.stack([torch.arange(M) < len(f[2]) for f in frames])
    maps = dict(alpha=torch.stack([f[0] for f in frames]), gt_mask=torch.stack([f[5] for f in frames]),
                est_depth=torch.stack([f[4] for f in frames]))
    terms, checks = {}, []
    loss, stats = rdga_frames(depth=depth, p=P, q=Q, cfg=cfg, pos_image=pos, K=K, valid=valid, terms=terms,
                              checks=checks, **maps)
    _rdga.judge(checks)
    assert loss.shape == (3,) and set(terms) == {"silhouette", "global", "anchor_l1" if depth_term == "l1" else "anchor"}
    torch.testing.assert_close(sum(terms.values()), loss)
    g_depth, g_pos = torch.autograd.grad(loss @ torch.tensor([1.0, -2.0, 3.0], dtype=torch.float64), (depth, pos))
    anchors = 0
    for t, (alpha, d, p, q, est, gt) in enumerate(frames):
        d1, pos1 = d.clone().requires_grad_(True), _positions(uv, alpha, K).requires_grad_(True)
        terms1 = {}
        ref, ref_stats = rdga_loss({"alpha": alpha, "depth": d1}, gt, est, p, q, cfg, pos1, K, terms=terms1)
        assert float(loss[t].detach()) == pytest.approx(float(ref.detach()), rel=1e-12)
        for key, value in terms1.items():
            assert float(terms[key][t].detach()) == pytest.approx(float(value.detach()), rel=1e-12, abs=1e-15)
        got_stats = {k: (float(v[t]) if isinstance(v, torch.Tensor) else v) for k, v in stats.items()}
        assert got_stats == pytest.approx(ref_stats, rel=1e-12, abs=1e-15)
        r_depth, r_pos = torch.autograd.grad(ref, (d1, pos1))
        weight = (1.0, -2.0, 3.0)[t]
        torch.testing.assert_close(g_depth[t], weight * r_depth, rtol=1e-10, atol=1e-14)
        torch.testing.assert_close(g_pos[t], weight * r_pos, rtol=1e-10, atol=1e-14)
        anchors += ref_stats["n_anchors"]
    assert anchors > 0 and stats["n_global"][1] > 0 and float(stats["n_matches"][2]) == 0  # not vacuous
    unpadded, _ = rdga_frames(depth=depth, p=P, q=Q, cfg=cfg, pos_image=pos, K=K, **maps)
    assert not torch.allclose(unpadded[1:], loss[1:])  # control: the padded rows, counted, change frames 1 and 2


def test_gather_patches_is_advanced_indexings_patches_with_its_gradient():
    """Session 57: the patches as one index_select of the flattened frames: the values of ``frames[b, rows, cols]``
    bitwise and its gradient (float64, overlapping patches summed, points off the border clamped in, two frames);
    control: every frame read from frame 0 (a flat index without its frame stride) differs here."""
    from gca.align.rdga import _pixel_indices, gather_patches

    g = torch.Generator().manual_seed(0)
    B, H, W, M, k = 2, 9, 11, 25, 3
    image = torch.randn(B, H, W, generator=g, dtype=torch.float64, requires_grad=True)
    points = torch.rand(B, M, 2, generator=g, dtype=torch.float64) * torch.tensor([W + 2.0, H + 2.0]) - 1.0
    points[0, :5] = torch.tensor([4.2, 3.9], dtype=torch.float64)  # five points on one pixel: overlapping patches
    cot = torch.randn(B, M, k * k, generator=g, dtype=torch.float64)

    def reference():
        half = k // 2
        pix, inside = _pixel_indices(points, H, W, half)
        off = torch.arange(-half, half + 1)
        cols = pix[..., 0].clamp(half, W - 1 - half)[..., None, None] + off
        rows = pix[..., 1].clamp(half, H - 1 - half)[..., None, None] + off[:, None]
        return image[torch.arange(B)[:, None, None, None], rows, cols].reshape(B, M, k * k), inside

    patches, inside = gather_patches(image, points, k)
    ref, ref_inside = reference()
    assert torch.equal(patches, ref) and torch.equal(inside, ref_inside) and not bool(inside.all())
    (grad,) = torch.autograd.grad((patches * cot).sum(), image)
    (grad_ref,) = torch.autograd.grad((ref * cot).sum(), image)
    torch.testing.assert_close(grad, grad_ref, atol=1e-12, rtol=1e-12)
    assert float(grad.abs().max()) > 0
    # negative control: the bug the flat index could have (the frame stride dropped: every frame read from frame 0)
    # is visible in these data
    frame0 = gather_patches(image[:1].expand(B, H, W), points, k)[0]
    assert torch.equal(frame0[0], ref[0]) and not torch.allclose(frame0[1], ref[1])
    with pytest.raises(ValueError, match="at least 3 x 3 pixels, got 2 x 11"):  # a patch larger than the image
        gather_patches(image[:, :2], points, k)
