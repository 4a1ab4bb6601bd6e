"""benchmarks/match_quality.py's truth for a moved render (``--warp``): a correct match has q = m^-1 p."""

import sys
from pathlib import Path

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))

import match_quality  # noqa: E402
from gca.vision.matching import MatchConfig, detect_keypoints  # noqa: E402

S = 128


def _disc():
    """A textured disc on a grey background: RGB [S, S, 3] in [0, 1] and its mask."""
    rng = np.random.default_rng(0)
    tex = sum(cv2.resize(rng.random((S // s, S // s, 3)), (S, S), interpolation=cv2.INTER_CUBIC) for s in (2, 4, 8))
    tex = (tex - tex.min()) / np.ptp(tex)
    yy, xx = np.mgrid[0:S, 0:S]
    mask = (xx - S / 2) ** 2 + (yy - S / 2) ** 2 < (0.35 * S) ** 2
    return np.where(mask[..., None], tex, 0.75).astype(np.float32), mask


def test_distances_of_a_moved_render_are_measured_from_the_moved_truth():
    rgb, mask = _disc()
    renders = [(rgb, mask)]
    m = match_quality.similarity(renders, (6.0, -4.0, 8.0, 1.0))
    moved = match_quality.warped(renders, m, (0.75, 0.75, 0.75))
    frames, masks = rgb[None], mask[None]  # the video is the unmoved state
    keypoints = [detect_keypoints((rgb * 255 + 0.5).astype(np.uint8))]
    d, counts = match_quality.distances(moved, frames, masks, keypoints, MatchConfig(backend="flow"), m)
    assert counts[0] > 100 and np.median(d) < 1.0
    d_wrong, _ = match_quality.distances(moved, frames, masks, keypoints, MatchConfig(backend="flow"), None)
    assert np.median(d_wrong) > 4.0  # negative control: measured as if the render had not moved
    exact, _ = match_quality.distances(renders, frames, masks, keypoints, MatchConfig(backend="flow"))
    assert np.median(exact) < 0.1
