"""SIFT matching (gca/vision/matching.py) on textured synthetic pairs with a known true map."""

import cv2
import numpy as np
import pytest

from gca.vision.matching import (MatchConfig, apply_homography, detect_keypoints, match_cached, match_features,
                                 match_precision, pack_keypoints, unpack_keypoints)

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
    p, q = match_features(img, warped, MatchConfig(geometry=geometry))
    precision = match_precision(p, q, HOMOGRAPHY, tol_px=2.0)
    print(f"SIFT+{geometry}: {len(p)} matches, precision@2px = {precision:.3f}")
    assert len(p) >= 50 and precision > 0.9
    assert match_precision(p, np.roll(q, 7, axis=0), HOMOGRAPHY, 2.0) < 0.1  # negative control


def test_sift_precision_on_known_shift_with_float_frames():
    img = _texture(1)
    shift = np.float32([[1, 0, 5], [0, 1, -3]])
    moved = cv2.warpAffine(img, shift, (S, S), borderMode=cv2.BORDER_REFLECT)
    p, q = match_features(img.astype(np.float32) / 255.0, moved, MatchConfig(geometry="homography"))
    assert len(p) >= 50
    assert match_precision(p, q, lambda x: x + np.array([5.0, -3.0]), tol_px=2.0) > 0.9


def test_cached_matching_equals_direct_and_pack_roundtrips(tmp_path):
    img = _texture()
    warped = cv2.warpPerspective(img, HOMOGRAPHY, (S, S), borderMode=cv2.BORDER_REFLECT)
    cfg = MatchConfig(geometry="none")  # deterministic (no RANSAC sampling)
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
    p, q = match_features(flat, flat)
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
