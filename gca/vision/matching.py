"""2D correspondences between a rendered frame and a GT frame (the matcher F of paper Sec. 3.3).

Coordinates are float pixel ``(x, y)`` in the OpenCV keypoint convention: the centre of pixel
column i, row j is ``(i, j)`` (``gca.align.rdga`` uses the same). ``p`` [M, 2] lies in the render,
``q`` [M, 2] in the GT frame.

Backends (``MatchConfig.backend``):

- ``"sift"`` (no weights): OpenCV SIFT, brute-force L2 k-NN (k = 2), Lowe's ratio test,
  then RANSAC on a homography (default: a render and its GT frame differ by a small motion) or a
  fundamental matrix (general 3D motion; with ~10 matches an 8-point F fits outliers: on the duck's
  exact GT state F kept 20% wrong matches, mean 5.3 px, against 0.9 px for H at 3 px,
  ``benchmarks/match_quality.py``), or no geometric check. GT keypoints and descriptors can be computed once per frame
  (:func:`detect_keypoints`), stored (:func:`pack_keypoints`) and reused (:func:`match_cached`).
- ``"loftr"``: kornia's LoFTR, only from a LOCAL checkpoint (``loftr_weights``); dense, so there
  is no keypoint cache.
- ``"flow"`` (default, no weights): dense correspondences from OpenCV's DIS optical flow (Kroeger et al. 2016) between
  illumination-normalised images (:func:`flow_image`), taken on a grid of render pixels (``flow_stride``)
  and kept where the forward and backward flows agree (``flow_fb_px``): :func:`match_flow`. The paper's
  matcher is a learned one (SuperGlue, whose weights cannot be loaded here); SIFT on grey images, its
  weight-free stand-in, failed on the lit video frames of the calibration scene ``calib_torus`` (the render
  is unlit, the video lit and shadowed: 1.6 matches per frame at the *exact* state, median error 26 px), where
  this gives ~130 per frame within 0.2 px (benchmarks/NOTES.md, session 16; chosen on the three calibration
  scenes only). A departure from the paper's sparse matcher, documented in docs/architecture.md.

When too few ratio-test matches remain to fit the RANSAC model (8 for F, 4 for H), no match is
returned: unverified matches are dropped rather than trusted.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Callable

import cv2
import numpy as np

_WHERE = "gca/vision/matching.py"
BACKENDS = ("sift", "loftr", "flow")
FLOW_IMAGES = ("chroma_clahe", "gray")
FLOW_PRESETS = {"ultrafast": 0, "fast": 1, "medium": 2}  # cv2.DISOPTICAL_FLOW_PRESET_*
GEOMETRIES = ("fundamental", "homography", "none")
_MIN_MATCHES = {"fundamental": 8, "homography": 4, "none": 1}


@dataclasses.dataclass(frozen=True)
class MatchConfig:
    """Feature matching knobs (params section ``vision.matching``).

    Attributes:
        backend: "sift" or "loftr".
        n_features: SIFT keypoints kept per image, best first (0 = all) [count].
        ratio: Lowe ratio test threshold (best / second-best distance) [-].
        geometry: RANSAC model: "fundamental", "homography" or "none".
        ransac_px: RANSAC inlier threshold (epipolar or reprojection distance) [px].
        ransac_confidence: RANSAC confidence [-].
        loftr_weights: local LoFTR checkpoint (.ckpt with a "state_dict"), backend "loftr".
        loftr_confidence: minimum LoFTR match confidence [-].
        flow_image: what backend "flow" computes the flow on: "chroma_clahe" (shading-invariant chromaticity,
            contrast-equalised) or "gray" (:func:`flow_image`).
        flow_stride: spacing of the render pixels the flow is sampled at [px].
        flow_fb_px: largest forward-backward flow disagreement of a kept match [px].
        flow_preset: DIS preset, "ultrafast" | "fast" | "medium".
    """

    backend: str = "flow"
    n_features: int = 0
    ratio: float = 0.75
    geometry: str = "homography"
    ransac_px: float = 3.0
    ransac_confidence: float = 0.999
    loftr_weights: str = ""
    loftr_confidence: float = 0.5
    flow_image: str = "chroma_clahe"
    flow_stride: int = 6
    flow_fb_px: float = 1.0
    flow_preset: str = "medium"

    def __post_init__(self) -> None:
        if self.backend not in BACKENDS or self.geometry not in GEOMETRIES:
            raise ValueError(f"{_WHERE}: MatchConfig backend={self.backend!r} (allowed {BACKENDS}), "
                             f"geometry={self.geometry!r} (allowed {GEOMETRIES})")
        if self.flow_image not in FLOW_IMAGES or self.flow_preset not in FLOW_PRESETS:
            raise ValueError(f"{_WHERE}: MatchConfig flow_image={self.flow_image!r} (allowed {FLOW_IMAGES}), "
                             f"flow_preset={self.flow_preset!r} (allowed {tuple(FLOW_PRESETS)})")
        if self.flow_stride < 1 or not self.flow_fb_px > 0:
            raise ValueError(f"{_WHERE}: MatchConfig flow_stride must be >= 1 and flow_fb_px > 0, got "
                             f"{self.flow_stride} and {self.flow_fb_px}")
        if not 0 < self.ratio <= 1:
            raise ValueError(f"{_WHERE}: MatchConfig.ratio must lie in (0, 1], got {self.ratio}")


def rgb_uint8(frame: np.ndarray) -> np.ndarray:
    """An RGB frame [..., H, W, 3] (uint8, or float in [0, 1]: clipped and rounded) as uint8."""
    frame = np.asarray(frame)
    if frame.ndim < 3 or frame.shape[-1] != 3:
        raise ValueError(f"{_WHERE}: a frame must be [H, W, 3] RGB, got shape {frame.shape}")
    return frame if frame.dtype == np.uint8 else (np.clip(frame, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)


def to_gray_uint8(frame: np.ndarray) -> np.ndarray:
    """An RGB frame [H, W, 3] (uint8, or float in [0, 1]) as a uint8 grey image [H, W]."""
    frame = np.asarray(frame)
    if frame.ndim != 3:
        raise ValueError(f"{_WHERE}: a frame must be [H, W, 3] RGB, got shape {frame.shape}")
    return cv2.cvtColor(rgb_uint8(frame), cv2.COLOR_RGB2GRAY)


def detect_keypoints(frame: np.ndarray, cfg: MatchConfig = MatchConfig()) -> tuple[np.ndarray, np.ndarray]:
    """SIFT keypoints and descriptors of one frame.

    Args:
        frame: RGB frame [H, W, 3], uint8 or float in [0, 1].
        cfg: matching config (``n_features``).

    Returns:
        (kpts [K, 2] float32 (x, y), descriptors [K, 128] float32); K may be 0.
    """
    sift = cv2.SIFT_create(nfeatures=cfg.n_features)
    kps, desc = sift.detectAndCompute(to_gray_uint8(frame), None)
    if desc is None or len(kps) == 0:
        return np.zeros((0, 2), np.float32), np.zeros((0, 128), np.float32)
    return np.array([k.pt for k in kps], np.float32).reshape(-1, 2), desc.astype(np.float32)


def _ratio_test(desc_a: np.ndarray, desc_b: np.ndarray, ratio: float) -> np.ndarray:
    """Index pairs [M, 2] (a, b) passing Lowe's ratio test."""
    if len(desc_a) < 1 or len(desc_b) < 2:
        return np.zeros((0, 2), np.int64)
    knn = cv2.BFMatcher(cv2.NORM_L2).knnMatch(desc_a, desc_b, k=2)
    pairs = [(best[0].queryIdx, best[0].trainIdx) for best in knn
             if len(best) == 2 and best[0].distance < ratio * best[1].distance]
    return np.array(pairs, np.int64).reshape(-1, 2)


def _ransac_inliers(p: np.ndarray, q: np.ndarray, cfg: MatchConfig) -> np.ndarray:
    """Bool [M] inliers of the configured geometric model (all False if too few matches)."""
    if len(p) < _MIN_MATCHES[cfg.geometry]:
        return np.zeros(len(p), bool)
    if cfg.geometry == "none":
        return np.ones(len(p), bool)
    if cfg.geometry == "fundamental":
        _, inl = cv2.findFundamentalMat(p, q, cv2.FM_RANSAC, cfg.ransac_px, cfg.ransac_confidence)
    else:
        _, inl = cv2.findHomography(p, q, cv2.RANSAC, cfg.ransac_px, confidence=cfg.ransac_confidence)
    return np.zeros(len(p), bool) if inl is None else inl.ravel().astype(bool)


def match_descriptors(kpts_r: np.ndarray, desc_r: np.ndarray, kpts_g: np.ndarray, desc_g: np.ndarray,
                      cfg: MatchConfig = MatchConfig()) -> tuple[np.ndarray, np.ndarray]:
    """Ratio-test + RANSAC matches between render keypoints and GT keypoints.

    Args:
        kpts_r: render keypoints [Kr, 2]; desc_r: their descriptors [Kr, D].
        kpts_g: GT keypoints [Kg, 2]; desc_g: their descriptors [Kg, D].
        cfg: matching config.

    Returns:
        (p [M, 2], q [M, 2]) float32 pixel coordinates in the render and the GT frame.
    """
    if len(kpts_r) != len(desc_r) or len(kpts_g) != len(desc_g):
        raise ValueError(f"{_WHERE}: keypoint/descriptor counts differ: {len(kpts_r)}/{len(desc_r)}, "
                         f"{len(kpts_g)}/{len(desc_g)}")
    pairs = _ratio_test(desc_r, desc_g, cfg.ratio)
    p, q = kpts_r[pairs[:, 0]].astype(np.float32), kpts_g[pairs[:, 1]].astype(np.float32)
    keep = _ransac_inliers(p, q, cfg)
    return p[keep].reshape(-1, 2), q[keep].reshape(-1, 2)


def _loftr_matcher(cfg: MatchConfig):
    """kornia LoFTR from a local checkpoint (clear error when it is absent)."""
    path = Path(cfg.loftr_weights)
    if not cfg.loftr_weights or not path.is_file():
        raise FileNotFoundError(
            f"{_WHERE}: backend 'loftr' needs a local checkpoint, but loftr_weights={cfg.loftr_weights!r} "
            "is not a file. On a machine with network download kornia's LoFTR weights "
            "(kornia.feature.loftr.loftr.urls, e.g. the 'outdoor' checkpoint), copy the .ckpt here "
            "and set vision.matching.loftr_weights; or use backend 'sift', which needs no weights.")
    import torch
    from kornia.feature import LoFTR

    state = torch.load(path, map_location="cpu", weights_only=True)
    matcher = LoFTR(pretrained=None)
    matcher.load_state_dict(state.get("state_dict", state))
    return matcher.eval()


def _match_loftr(render: np.ndarray, gt: np.ndarray, cfg: MatchConfig) -> tuple[np.ndarray, np.ndarray]:
    import torch

    def as_input(frame):
        return torch.from_numpy(to_gray_uint8(frame)).float()[None, None] / 255.0

    with torch.no_grad():
        out = _loftr_matcher(cfg)({"image0": as_input(render), "image1": as_input(gt)})
    keep = (out["confidence"] >= cfg.loftr_confidence).numpy()
    p, q = out["keypoints0"].numpy()[keep], out["keypoints1"].numpy()[keep]
    inl = _ransac_inliers(p.astype(np.float32), q.astype(np.float32), cfg)
    return p[inl].astype(np.float32).reshape(-1, 2), q[inl].astype(np.float32).reshape(-1, 2)


def match_features(render: np.ndarray, gt: np.ndarray,
                   cfg: MatchConfig = MatchConfig()) -> tuple[np.ndarray, np.ndarray]:
    """Correspondences between a rendered frame and a GT frame.

    Args:
        render: rendered RGB [H, W, 3], uint8 or float in [0, 1].
        gt: GT RGB [H', W', 3].
        cfg: matching config.

    Returns:
        (p [M, 2], q [M, 2]) float32 (x, y): p in the render, q in the GT frame.
    """
    if cfg.backend == "loftr":
        return _match_loftr(render, gt, cfg)
    if cfg.backend == "flow":
        return match_flow(render, gt, cfg)
    return match_descriptors(*detect_keypoints(render, cfg), *detect_keypoints(gt, cfg), cfg)


def match_frame(render: np.ndarray, gt: np.ndarray, kpts_gt: np.ndarray, desc_gt: np.ndarray,
                cfg: MatchConfig = MatchConfig(), render_mask: np.ndarray | None = None,
                gt_mask: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Training's matcher: one render against its video frame, by ``cfg.backend``.

    Args:
        render: rendered RGB [H, W, 3]; gt: the video frame [H, W, 3] (uint8, or float in [0, 1]).
        kpts_gt, desc_gt: the video frame's cached SIFT keypoints [K, 2] and descriptors (backend "sift").
        cfg: matching config.
        render_mask, gt_mask: optional object masks [H, W] (bool) of the render and the frame (backend "flow":
            p inside the render's, q inside the frame's; the sparse backends leave that to the caller).

    Returns:
        (p [M, 2], q [M, 2]) float32 (x, y): p in the render, q in the video frame.
    """
    if cfg.backend == "sift":
        return match_cached(render, kpts_gt, desc_gt, cfg)
    if cfg.backend == "flow":
        return match_flow(render, gt, cfg, render_mask, gt_mask)
    return match_features(render, gt, cfg)


def flow_image(frame: np.ndarray, kind: str = "chroma_clahe") -> np.ndarray:
    """The single-channel uint8 image [H, W] backend "flow" computes optical flow on.

    ``"chroma_clahe"``: the chromaticity ``c = (R, G, B) / (R + G + B)`` (with 1 added to each uint8 channel),
    which a shading factor common to the three channels leaves unchanged (Lambertian shading and shadows under
    white light), as a grey image of ``1.5 * 255 c``, then CLAHE (clip 2, 8x8 tiles) to equalise the contrast
    of the texture's colour edges. ``"gray"``: the luma image (no normalisation).
    """
    if kind == "gray":
        return to_gray_uint8(frame)
    if kind != "chroma_clahe":
        raise ValueError(f"{_WHERE}: flow_image kind {kind!r} is not one of {FLOW_IMAGES}")
    if np.ndim(frame) != 3:
        raise ValueError(f"{_WHERE}: a frame must be [H, W, 3] RGB, got shape {np.shape(frame)}")
    rgb = rgb_uint8(frame).astype(np.float32) + 1.0
    chroma = np.clip(rgb / rgb.sum(-1, keepdims=True) * (1.5 * 255.0), 0.0, 255.0).astype(np.uint8)
    return cv2.createCLAHE(clipLimit=2.0, tileGridSize=(8, 8)).apply(cv2.cvtColor(chroma, cv2.COLOR_RGB2GRAY))


def _dis_flow(a: np.ndarray, b: np.ndarray, preset: str) -> np.ndarray:
    """DIS optical flow [H, W, 2] (dx, dy) [px] from grey image a to grey image b."""
    return cv2.DISOpticalFlow_create(FLOW_PRESETS[preset]).calc(a, b, None)


def _inside(xy: np.ndarray, shape: tuple[int, int], mask: np.ndarray | None = None) -> np.ndarray:
    """Bool [M]: the nearest pixel of each point [M, 2] lies in the image of ``shape`` (H, W) and, if given,
    in ``mask`` [H, W]."""
    h, w = shape
    ij = np.round(xy).astype(np.int64)
    ok = (ij[:, 0] >= 0) & (ij[:, 0] < w) & (ij[:, 1] >= 0) & (ij[:, 1] < h)
    if mask is not None:
        ok[ok] = np.asarray(mask, bool)[ij[ok, 1], ij[ok, 0]]
    return ok


def match_flow(render: np.ndarray, gt: np.ndarray, cfg: MatchConfig = MatchConfig(),
               render_mask: np.ndarray | None = None,
               gt_mask: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Dense correspondences from forward-backward consistent DIS optical flow (backend "flow").

    p runs over the render pixels ``(s/2 + i s, s/2 + j s)`` (``s = flow_stride``) inside ``render_mask``;
    ``q = p + f(p)`` with ``f`` the flow render -> frame on :func:`flow_image`; a pair is kept when the
    backward flow ``b`` (frame -> render, bilinear at q) brings it back: ``|q + b(q) - p| < flow_fb_px``
    (occlusions, texture-less patches and flow errors break that), and q lies inside the frame and
    ``gt_mask``.

    Args:
        render: rendered RGB [H, W, 3]; gt: the video frame [H, W, 3] (same size).
        cfg: matching config (``flow_*``).
        render_mask, gt_mask: object masks [H, W] (bool), or None for the whole image.

    Returns:
        (p [M, 2], q [M, 2]) float32 pixel coordinates (x, y) in the render and the frame.
    """
    a, b = flow_image(render, cfg.flow_image), flow_image(gt, cfg.flow_image)
    if a.shape != b.shape:
        raise ValueError(f"{_WHERE}: backend 'flow' needs frames of one size, got {a.shape} and {b.shape}")
    h, w = a.shape
    s = cfg.flow_stride
    ys, xs = np.mgrid[s // 2:h:s, s // 2:w:s]
    p = np.stack([xs.ravel(), ys.ravel()], 1).astype(np.float32)
    if render_mask is not None:
        p = p[_inside(p, (h, w), render_mask)]
    if len(p) == 0:
        return np.zeros((0, 2), np.float32), np.zeros((0, 2), np.float32)
    fwd, bwd = _dis_flow(a, b, cfg.flow_preset), _dis_flow(b, a, cfg.flow_preset)
    q = p + fwd[p[:, 1].astype(np.int64), p[:, 0].astype(np.int64)]
    back = q + cv2.remap(bwd, q[:, :1].copy(), q[:, 1:].copy(), cv2.INTER_LINEAR,
                         borderMode=cv2.BORDER_REPLICATE).reshape(-1, 2)
    keep = (np.linalg.norm(back - p, axis=1) < cfg.flow_fb_px) & _inside(q, (h, w), gt_mask)
    return p[keep].reshape(-1, 2), q[keep].astype(np.float32).reshape(-1, 2)


def match_cached(render: np.ndarray, kpts_gt: np.ndarray, desc_gt: np.ndarray,
                 cfg: MatchConfig = MatchConfig()) -> tuple[np.ndarray, np.ndarray]:
    """Like :func:`match_features` with the GT frame's precomputed SIFT keypoints [K, 2] and descriptors."""
    if cfg.backend != "sift":
        raise ValueError(f"{_WHERE}: cached keypoints exist for backend 'sift' only, not {cfg.backend!r}")
    return match_descriptors(*detect_keypoints(render, cfg), kpts_gt, desc_gt, cfg)


def pack_keypoints(per_frame: list[tuple[np.ndarray, np.ndarray]]) -> dict[str, np.ndarray]:
    """Flatten per-frame (kpts [K_t, 2], desc [K_t, D]) into arrays for one ``np.savez``.

    Returns:
        {"kpts": [sum K_t, 2], "desc": [sum K_t, D], "offsets": [T + 1]} (frame t owns rows
        offsets[t]:offsets[t+1]).
    """
    counts = [len(k) for k, _ in per_frame]
    return {"kpts": np.concatenate([k for k, _ in per_frame]).astype(np.float32).reshape(-1, 2),
            "desc": np.concatenate([d for _, d in per_frame]).astype(np.float32),
            "offsets": np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)}


def unpack_keypoints(packed) -> list[tuple[np.ndarray, np.ndarray]]:
    """Inverse of :func:`pack_keypoints` (accepts the dict or a loaded ``.npz``)."""
    offsets = np.asarray(packed["offsets"])
    kpts, desc = np.asarray(packed["kpts"]), np.asarray(packed["desc"])
    if offsets[-1] != len(kpts) or len(kpts) != len(desc):
        raise ValueError(f"{_WHERE}: packed keypoints are inconsistent: offsets end at {offsets[-1]}, "
                         f"{len(kpts)} keypoints, {len(desc)} descriptors")
    return [(kpts[a:b], desc[a:b]) for a, b in zip(offsets[:-1], offsets[1:])]


def apply_homography(Hm: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Map points [M, 2] by a 3x3 homography (pixel coordinates)."""
    ph = np.concatenate([points, np.ones((len(points), 1))], -1) @ np.asarray(Hm, np.float64).T
    return ph[:, :2] / ph[:, 2:]


def match_precision(p: np.ndarray, q: np.ndarray, true_map: np.ndarray | Callable[[np.ndarray], np.ndarray],
                    tol_px: float = 2.0) -> float:
    """Fraction of matches whose q lies within ``tol_px`` of the true correspondence of p.

    Args:
        p: [M, 2] points in the first image; q: [M, 2] their matches in the second.
        true_map: the true map first -> second, a 3x3 homography or a callable [M, 2] -> [M, 2].
        tol_px: tolerance [px].

    Returns:
        precision in [0, 1]; 0.0 when M = 0.
    """
    p, q = np.asarray(p, np.float64).reshape(-1, 2), np.asarray(q, np.float64)
    if q.shape != p.shape:
        raise ValueError(f"{_WHERE}: p and q must both be [M, 2], got {p.shape} and {q.shape}")
    if len(p) == 0:
        return 0.0
    mapped = true_map(p) if callable(true_map) else apply_homography(true_map, p)
    return float(np.mean(np.linalg.norm(mapped - q, axis=-1) <= tol_px))
