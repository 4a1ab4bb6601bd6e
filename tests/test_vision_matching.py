"""Matching (gca/vision/matching.py): SIFT and dense flow on textured synthetic pairs with a known true map."""

import cv2
import numpy as np
import pytest

from gca.vision.matching import (MatchConfig, apply_homography, detect_keypoints, flow_image, match_cached,
                                 match_features, match_flow, match_frame, match_precision, pack_keypoints,
                                 unpack_keypoints)

SIFT = MatchConfig(backend="sift")

S = 160
HOMOGRAPHY = np.array([[1.02, 0.03, 3.2], [-0.02, 0.99, -2.1], [1e-4, -5e-5, 1.0]])


def _texture(seed=0):
    """Multi-scale value noise, uint8 RGB [S, S, 3]."""
    rng = np.random.default_rng(seed)
    img = sum(cv2.resize(rng.random((S // s, S // s, 3)), (S, S), interpolation=cv2.INTER_CUBIC) for s in (2, 4, 8, 16))
    img = (img - img.min()) / np.ptp(img)
    return (img * 255).astype(np.uint8)


@pytest.mark.parametrize("geometry", ["homography", "fundamental"])
def test_sift_precision_on_known_homography(geometry):
    img = _texture()
    warped = cv2.warpPerspective(img, HOMOGRAPHY, (S, S), borderMode=cv2.BORDER_REFLECT)
    p, q = match_features(img, warped, MatchConfig(backend="sift", geometry=geometry))
    precision = match_precision(p, q, HOMOGRAPHY, tol_px=2.0)
    print(f"SIFT+{geometry}: {len(p)} matches, precision@2px = {precision:.3f}")
    assert len(p) >= 50 and precision > 0.9
    assert match_precision(p, np.roll(q, 7, axis=0), HOMOGRAPHY, 2.0) < 0.1  # negative control


def test_sift_precision_on_known_shift_with_float_frames():
    img = _texture(1)
    shift = np.float32([[1, 0, 5], [0, 1, -3]])
    moved = cv2.warpAffine(img, shift, (S, S), borderMode=cv2.BORDER_REFLECT)
    p, q = match_features(img.astype(np.float32) / 255.0, moved, MatchConfig(backend="sift", geometry="homography"))
    assert len(p) >= 50
    assert match_precision(p, q, lambda x: x + np.array([5.0, -3.0]), tol_px=2.0) > 0.9


def test_cached_matching_equals_direct_and_pack_roundtrips(tmp_path):
    img = _texture()
    warped = cv2.warpPerspective(img, HOMOGRAPHY, (S, S), borderMode=cv2.BORDER_REFLECT)
    cfg = MatchConfig(backend="sift", geometry="none")  # deterministic (no RANSAC sampling)
    per_frame = [detect_keypoints(warped, cfg), detect_keypoints(img, cfg)]
    np.savez(tmp_path / "kp.npz", **pack_keypoints(per_frame))
    loaded = unpack_keypoints(np.load(tmp_path / "kp.npz"))
    for (k0, d0), (k1, d1) in zip(per_frame, loaded):
        np.testing.assert_array_equal(k0, k1)
        np.testing.assert_array_equal(d0, d1)
    p_direct, q_direct = match_features(img, warped, cfg)
    p_cached, q_cached = match_cached(img, *loaded[0], cfg)
    np.testing.assert_array_equal(p_direct, p_cached)
    np.testing.assert_array_equal(q_direct, q_cached)


def test_textureless_frames_give_no_matches():
    flat = np.full((S, S, 3), 255, np.uint8)
    p, q = match_features(flat, flat, SIFT)
    assert p.shape == (0, 2) and q.shape == (0, 2)


def test_apply_homography_identity_and_translation():
    x = np.array([[1.0, 2.0], [30.0, 4.0]])
    np.testing.assert_allclose(apply_homography(np.eye(3), x), x)
    np.testing.assert_allclose(apply_homography([[1, 0, 2], [0, 1, -1], [0, 0, 1]], x), x + [2, -1])


def test_loftr_without_local_weights_raises_clearly(tmp_path):
    cfg = MatchConfig(backend="loftr", loftr_weights=str(tmp_path / "loftr.ckpt"))
    with pytest.raises(FileNotFoundError, match="matching.py: backend 'loftr' needs a local checkpoint"):
        match_features(_texture(), _texture(), cfg)
    with pytest.raises(ValueError, match="cached keypoints exist for backend 'sift' only"):
        match_cached(_texture(), np.zeros((0, 2)), np.zeros((0, 128)), cfg)


# ------------------------------------------------------------------------------------------ dense flow

def _object_pair(shift=(5.0, -3.0), shading=None, seed=2):
    """A textured disc on a flat background, and the same disc moved by ``shift`` [px] in a second frame
    whose pixels are multiplied by ``shading`` [S, S] (a lighting change); (render, frame, render mask, frame mask)."""
    tex = _texture(seed)
    yy, xx = np.mgrid[0:S, 0:S]
    disc = (xx - S / 2) ** 2 + (yy - S / 2) ** 2 < (0.38 * S) ** 2
    render = np.where(disc[..., None], tex, 190).astype(np.uint8)
    move = np.float32([[1, 0, shift[0]], [0, 1, shift[1]]])
    frame = cv2.warpAffine(render, move, (S, S), borderValue=(190, 190, 190))
    frame_mask = cv2.warpAffine(disc.astype(np.uint8), move, (S, S)) > 0
    if shading is not None:
        frame = np.clip(frame * shading[..., None], 0, 255).astype(np.uint8)
    return render, frame, disc, frame_mask


def _shadow():
    """A lighting change: a smooth shading ramp (0.55-1.0) and a hard shadow (x 0.45) over a third of the image."""
    yy, xx = np.mgrid[0:S, 0:S]
    return (0.55 + 0.45 * xx / S) * np.where(yy > 0.62 * S, 0.45, 1.0)


def test_flow_matches_a_known_shift_densely_and_inside_the_masks():
    render, frame, m_r, m_f = _object_pair()
    cfg = MatchConfig(backend="flow")
    p, q = match_flow(render, frame, cfg, m_r, m_f)
    n_grid = int(m_r[cfg.flow_stride // 2::cfg.flow_stride, cfg.flow_stride // 2::cfg.flow_stride].sum())
    truth = lambda x: x + np.array([5.0, -3.0])  # noqa: E731
    print(f"flow: {len(p)} of {n_grid} grid points kept, precision@1px {match_precision(p, q, truth, 1.0):.3f}")
    assert len(p) >= 0.7 * n_grid and match_precision(p, q, truth, tol_px=1.0) > 0.95
    assert match_precision(p, q, lambda x: x, tol_px=1.0) < 0.05  # negative control: not the identity
    ij_p, ij_q = np.round(p).astype(int), np.round(q).astype(int)
    assert m_r[ij_p[:, 1], ij_p[:, 0]].all() and m_f[ij_q[:, 1], ij_q[:, 0]].all()
    assert np.all(p % cfg.flow_stride == cfg.flow_stride // 2)  # p on the sampling grid
    p2, q2 = match_features(render, frame, cfg)  # no masks: the whole grid, a superset
    assert len(p2) >= len(p)


def test_flow_image_is_invariant_to_shading_and_flow_survives_a_lighting_change():
    """The video is lit (a shading ramp, a hard shadow and pixel-scale shading noise) and the render is not. The
    chromaticity image is unchanged by a shading factor common to the three channels (up to uint8 rounding),
    the grey image is not (the negative control); the flow matches stay right under the lighting change. (That
    grey-level flow does worse on the calibration scenes' lit frames is measured there, benchmarks/NOTES.md s16:
    DIS's normalised patches survive these synthetic shadings too.)"""
    rng = np.random.default_rng(0)
    shading = _shadow() * (0.6 + 0.4 * rng.random((S, S)))
    render, frame, m_r, m_f = _object_pair(shading=shading)
    truth = lambda x: x + np.array([5.0, -3.0])  # noqa: E731
    p, q = match_flow(render, frame, MatchConfig(backend="flow"), m_r, m_f)
    assert len(p) > 200 and match_precision(p, q, truth, tol_px=1.0) > 0.95
    shaded = np.clip(render * shading[..., None], 0, 255).astype(np.uint8)
    change = {kind: np.abs(flow_image(shaded, kind).astype(int) - flow_image(render, kind))[m_r].mean()
              for kind in ("chroma_clahe", "gray")}
    print(f"mean change of the flow image under the shading [grey levels]: {change}")
    assert change["chroma_clahe"] < 6.0 and change["gray"] > 5 * change["chroma_clahe"]


def test_flow_forward_backward_check_drops_an_occluded_region():
    """Where the frame shows something else (an occluder), forward and backward flows disagree: few matches
    land there, and those that do are mostly wrong without the check (its negative control)."""
    render, frame, m_r, m_f = _object_pair(seed=3)
    occluded = np.zeros((S, S), bool)
    occluded[40:90, 50:110] = True
    frame[occluded] = _texture(9)[occluded]
    truth = lambda x: x + np.array([5.0, -3.0])  # noqa: E731
    in_occ = lambda q: occluded[np.round(q[:, 1]).astype(int), np.round(q[:, 0]).astype(int)]  # noqa: E731
    p, q = match_flow(render, frame, MatchConfig(backend="flow"), m_r, m_f)
    loose, q_loose = match_flow(render, frame, MatchConfig(backend="flow", flow_fb_px=1e6), m_r, m_f)
    print(f"in the occluder: {in_occ(q).sum()} kept with the check, {in_occ(q_loose).sum()} without")
    assert in_occ(q).sum() <= 0.5 * in_occ(q_loose).sum()
    assert match_precision(p, q, truth, 1.0) > match_precision(loose, q_loose, truth, 1.0)


def test_match_frame_dispatches_by_backend():
    render, frame, m_r, m_f = _object_pair()
    cfg = MatchConfig(backend="sift", geometry="none")
    kpts, desc = detect_keypoints(frame, cfg)
    for got, want in ((match_frame(render, frame, kpts, desc, cfg), match_cached(render, kpts, desc, cfg)),
                      (match_frame(render, frame, kpts, desc, MatchConfig(), m_r, m_f),
                       match_flow(render, frame, MatchConfig(), m_r, m_f))):
        np.testing.assert_array_equal(got[0], want[0])
        np.testing.assert_array_equal(got[1], want[1])
    empty = match_flow(render, frame, MatchConfig(), np.zeros((S, S), bool), m_f)
    assert empty[0].shape == (0, 2) and empty[1].shape == (0, 2)


@pytest.mark.parametrize("field", [{"flow_image": "hue"}, {"flow_preset": "slow"}, {"flow_stride": 0},
                                   {"flow_fb_px": 0.0}])
def test_flow_config_rejects_bad_values(field):
    with pytest.raises(ValueError, match="matching.py: MatchConfig flow_"):
        MatchConfig(backend="flow", **field)
