"""Depth backends (gca/vision/depth.py): the simulated estimator model and the offline Depth Anything checks."""

import dataclasses

import cv2
import numpy as np
import pytest
import scipy.stats

from gca.vision.depth import (DepthConfig, DepthError, SimulatedDepth, SimulatedDepthConfig, TransformersDepthConfig,
                              disparity_to_depth, estimate_depth, make_depth_estimator)

T, H, W, R = 3, 48, 48, 16


def _scene():
    """A ball-like object: hemisphere depth inside a disk that moves a little per frame."""
    rows, cols = np.mgrid[0:H, 0:W].astype(np.float64)
    depths, masks = [], []
    for t in range(T):
        rho2 = (rows - 23.5) ** 2 + (cols - 20.0 - 2 * t) ** 2
        mask = rho2 <= R**2
        depths.append(np.where(mask, 3.0 - 0.05 * np.sqrt(np.clip(R**2 - rho2, 0, None)), 0.0))
        masks.append(mask)
    frames = np.zeros((T, H, W, 3), np.uint8)
    return frames, np.stack(depths), np.stack(masks)


def _interior(mask, margin):
    return cv2.erode(mask.astype(np.uint8), np.ones((2 * margin + 1,) * 2, np.uint8)).astype(bool)


def _interior_stats(est, z, masks):
    """Per frame: Spearman(z, est) and the max affine-fit residual (relative) in the interior."""
    rhos, residuals = [], []
    for t in range(T):
        inner = _interior(masks[t], 4)
        rhos.append(scipy.stats.spearmanr(z[t][inner], est[t][inner]).statistic)
        A = np.stack([z[t][inner], np.ones(inner.sum())], -1)
        coef, *_ = np.linalg.lstsq(A, est[t][inner], rcond=None)
        residuals.append(np.abs(A @ coef - est[t][inner]).max() / np.ptp(est[t][inner]))
    return np.array(rhos), np.array(residuals)


# benchmark 2.0's non-monotone components off (the defaults follow params.yaml, which has them on): the 1.x model
_V1 = dict(texture_copy=0.0, smooth_sigma_px=0.0, thin_px=0, thin_flatten=0.0, flicker_tilt_std=0.0)


def test_simulated_depth_is_monotone_in_the_interior_but_not_affine():
    frames, z, masks = _scene()
    exact = SimulatedDepthConfig(noise_std=0.0, lowfreq_std=0.0, **_V1)  # warp + bleed + scale/shift only
    est = SimulatedDepth(exact, seed=3).estimate(frames, z, masks)
    assert est.shape == (T, H, W) and est.dtype == np.float32
    rhos, residuals = _interior_stats(est, z, masks)
    np.testing.assert_allclose(rhos, 1.0, atol=1e-9)  # monotone away from the edge band
    assert residuals.max() > 0.02, residuals  # the per-frame warp makes it non-affine
    rhos, _ = _interior_stats(SimulatedDepth(SimulatedDepthConfig(**_V1), seed=3).estimate(frames, z, masks), z, masks)
    assert rhos.min() > 0.95, rhos  # with the default noise the local order is still nearly kept


def test_simulated_depth_errors_concentrate_at_the_edge():
    frames, z, masks = _scene()
    cfg = SimulatedDepthConfig(gamma_max=1.0, noise_std=0.0, lowfreq_std=0.0, edge_band_px=3.0,
                               scale_range=(1.0, 1.0), shift_range=(0.0, 0.0), **_V1)
    est = SimulatedDepth(cfg).estimate(frames, z, masks)
    for t in range(T):
        zo = z[t][masks[t]]
        truth = np.where(masks[t], (z[t] - zo.min()) / np.ptp(zo), cfg.background)
        err = np.abs(est[t] - truth)
        far = _interior(masks[t], 4) | ~cv2.dilate(masks[t].astype(np.uint8), np.ones((9, 9), np.uint8)).astype(bool)
        assert err[far].max() < 1e-6
        assert err[~far].max() > 0.1  # foreground/background bleed inside the band


def test_simulated_depth_is_deterministic_per_seed():
    frames, z, masks = _scene()
    a = estimate_depth(frames, DepthConfig(), z, masks, seed=7)
    b = estimate_depth(frames, DepthConfig(), z, masks, seed=7)
    c = estimate_depth(frames, DepthConfig(), z, masks, seed=8)
    np.testing.assert_array_equal(a, b)
    assert np.abs(a - c).max() > 1e-3


def test_simulated_depth_needs_gt_and_checks_shapes():
    frames, z, masks = _scene()
    with pytest.raises(ValueError, match="needs gt_depth and masks"):
        SimulatedDepth(SimulatedDepthConfig()).estimate(frames)
    with pytest.raises(ValueError, match="depth.py"):
        SimulatedDepth(SimulatedDepthConfig()).estimate(frames, z[:, :-1], masks)
    bad = z.copy()
    bad[0, 24, 20] = np.nan
    with pytest.raises(ValueError, match="non-finite"):
        SimulatedDepth(SimulatedDepthConfig()).estimate(frames, bad, masks)


def test_transformers_backend_with_absent_weights_says_how_to_get_them(tmp_path):
    cfg = DepthConfig(backend="transformers", transformers=TransformersDepthConfig(weights_dir=str(tmp_path / "none")))
    with pytest.raises(DepthError) as info:
        make_depth_estimator(cfg)
    message = str(info.value)
    assert "depth.py" in message and "huggingface-cli download" in message and "weights_dir" in message
    try:
        import transformers  # noqa: F401
    except ImportError:
        assert "pip install 'gca[depth]'" in message


def test_disparity_to_depth_reverses_the_order_per_frame():
    disp = np.random.default_rng(0).random((2, 8, 8)) * 5 + 1
    depth = disparity_to_depth(disp, 0.05)
    for t in range(2):
        assert scipy.stats.spearmanr(disp[t].ravel(), depth[t].ravel()).statistic == pytest.approx(-1.0)
    assert depth.max() == pytest.approx(1 / 0.05) and depth.min() == pytest.approx(1 / 1.05)


def test_bad_configs_raise():
    with pytest.raises(ValueError, match="backend"):
        DepthConfig(backend="midas")
    with pytest.raises(ValueError, match="gamma_max"):
        dataclasses.replace(SimulatedDepthConfig(), gamma_max=0.5)


# ---- non-monotone error components (issue 21, item 4): one test of each component's effect ----

_OFF = dict(gamma_max=1.0, noise_std=0.0, lowfreq_std=0.0, edge_band_px=0.0, scale_range=(1.0, 1.0),
            shift_range=(0.0, 0.0), **_V1)


def _cfg(**components) -> SimulatedDepthConfig:
    """Every error off but the given components."""
    return SimulatedDepthConfig(**{**_OFF, **components})


def _spearman_inside(est, z, masks):
    return np.array([scipy.stats.spearmanr(z[t][masks[t]], est[t][masks[t]]).statistic for t in range(len(z))])


def test_texture_copying_follows_the_image_and_breaks_the_rank_order():
    _, z, masks = _scene()
    rng = np.random.default_rng(0)
    frames = (rng.uniform(0, 1, (T, H, W, 3)) * 255).astype(np.uint8)  # a strongly textured object
    clean = SimulatedDepth(_cfg(), 0).estimate(frames, z, masks)
    copied = SimulatedDepth(_cfg(texture_copy=0.3, texture_sigma_px=2.0), 0).estimate(frames, z, masks)
    err = (copied - clean)[masks]
    grey = frames.mean(-1) / 255.0
    high = np.stack([g - cv2.GaussianBlur(g, (0, 0), 2.0, borderType=cv2.BORDER_REPLICATE) for g in grey])[masks]
    assert np.corrcoef(err, high)[0, 1] < -0.99            # darker texture reads farther, exactly the high-pass
    assert np.all((copied - clean)[~masks] == 0)            # only inside the object
    assert _spearman_inside(copied, z, masks).max() < 0.99  # not a monotone function of depth any more
    np.testing.assert_allclose(_spearman_inside(clean, z, masks), 1.0, atol=1e-9)


def test_over_smoothing_rounds_boundaries_and_flattens_relief():
    frames, z, masks = _scene()
    clean = SimulatedDepth(_cfg(), 0).estimate(frames, z, masks)
    smooth = SimulatedDepth(_cfg(smooth_sigma_px=2.0), 0).estimate(frames, z, masks)
    ring = masks[0] & ~_interior(masks[0], 2)                  # the object's boundary pixels
    assert np.abs(smooth[0] - clean[0])[ring].mean() > 5 * np.abs(smooth[0] - clean[0])[_interior(masks[0], 6)].mean()
    gy, gx = np.gradient(smooth[0])
    cy, cx = np.gradient(clean[0])
    assert np.hypot(gy, gx).max() < 0.5 * np.hypot(cy, cx).max()   # the depth step is smeared


def test_thin_parts_are_flattened_toward_the_background_and_thick_parts_kept():
    z = np.zeros((1, H, W))
    masks = np.zeros((1, H, W), bool)
    masks[0, 10:30, 10:30] = True                             # thick body
    masks[0, 18:20, 30:44] = True                             # a 2-px-thin arm
    z[masks] = 2.0 + 0.01 * np.arange(masks.sum())
    frames = np.zeros((1, H, W, 3), np.uint8)
    cfg = _cfg(thin_px=5, thin_flatten=0.8)
    clean = SimulatedDepth(_cfg(), 0).estimate(frames, z, masks)[0]
    flat = SimulatedDepth(cfg, 0).estimate(frames, z, masks)[0]
    arm, body = np.zeros_like(masks[0]), np.zeros_like(masks[0])
    arm[18:20, 32:44], body[12:28, 12:28] = True, True
    np.testing.assert_allclose(flat[body], clean[body])
    bg = cfg.background
    assert np.all(np.abs(flat[arm] - bg) <= 0.2 * np.abs(clean[arm] - bg) + 1e-6)  # 80% of the way to the background


def test_flicker_changes_a_static_surface_from_frame_to_frame_beyond_scale_and_shift():
    frames, z, masks = _scene()
    z, masks = np.repeat(z[:1], 4, 0), np.repeat(masks[:1], 4, 0)   # a static object
    frames = np.repeat(frames[:1], 4, 0)
    rhos = {}
    for std in (0.0, 0.2):
        est = SimulatedDepth(_cfg(flicker_tilt_std=std), 1).estimate(frames, z, masks)
        m = masks[0]
        # rank agreement of consecutive frames on the same pixels (scale/shift cannot change it)
        rhos[std] = min(scipy.stats.spearmanr(est[t][m], est[t + 1][m]).statistic for t in range(3))
    assert rhos[0.0] > 0.999 and rhos[0.2] < 0.97, rhos


def test_error_components_reject_negative_amplitudes():
    with pytest.raises(ValueError, match="depth.py"):
        SimulatedDepthConfig(texture_copy=-0.1)
