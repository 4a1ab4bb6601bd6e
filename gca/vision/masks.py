"""Object masks of the video: segmented from the lit frames, background difference, user files, or alpha.

Methods (``MaskConfig.method``):

- ``"segment"`` (the benchmark's default): background model + colour/edge cues + kornia morphology on the
  lit frames, or a learned segmenter from local weights (:mod:`gca.vision.segment`).
- ``"alpha"``: threshold a rendered alpha (tests and evaluation; the preprocess stage has no alpha: the
  scene directory holds none, issue 21).
- ``"background"``: a fixed camera sees a static background; pixels whose colour differs from it
  by more than ``diff_threshold`` (max over RGB, in [0, 1] units) are the object. The background is
  the per-pixel temporal median of the video (valid when the object moves off every pixel for
  more than half of the frames) or the constant ``background_color`` (a colour key, e.g. the white
  background of synthetic renders or a green screen) when that is given.
- ``"files"``: user-supplied masks, one PNG per frame in ``files_dir`` (sorted by name; nonzero =
  object).

The two computed methods are cleaned by a morphological opening with an ``open_px`` square
(removes specks and thin noise thinner than ``open_px``).
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import cv2
import numpy as np

from gca.vision.segment import SegmentConfig, segment_frames

_WHERE = "gca/vision/masks.py"
METHODS = ("segment", "alpha", "background", "files")


@dataclasses.dataclass(frozen=True)
class MaskConfig:
    """Mask extraction knobs (params section ``vision.masks``).

    Attributes:
        method: "segment", "alpha", "background" or "files".
        alpha_threshold: alpha above which a pixel is object [-].
        diff_threshold: colour difference (max over RGB) above which a pixel is object [0-1 units].
        background_color: constant RGB background [0-1 units] for a colour key; None = temporal median.
        open_px: side of the square opening kernel [px]; 0 or 1 disables the cleanup.
        files_dir: directory of per-frame mask PNGs (method "files").
        segment: the segmenter's settings (method "segment").
    """

    method: str = "segment"
    alpha_threshold: float = 0.5
    diff_threshold: float = 0.1
    background_color: tuple[float, float, float] | None = None
    open_px: int = 3
    files_dir: str = ""
    segment: SegmentConfig = SegmentConfig()

    def __post_init__(self) -> None:
        if self.method not in METHODS:
            raise ValueError(f"{_WHERE}: MaskConfig.method={self.method!r} not in {METHODS}")
        if self.background_color is not None:
            object.__setattr__(self, "background_color", tuple(float(c) for c in self.background_color))


def _as_unit_float(frames: np.ndarray) -> np.ndarray:
    """RGB frames [..., 3] as float32 in [0, 1] (uint8 divided by 255)."""
    frames = np.asarray(frames)
    if frames.shape[-1] != 3:
        raise ValueError(f"{_WHERE}: frames must end in 3 RGB channels, got shape {frames.shape}")
    return frames.astype(np.float32) / 255.0 if frames.dtype == np.uint8 else frames.astype(np.float32)


def open_mask(mask: np.ndarray, open_px: int) -> np.ndarray:
    """Morphological opening of a bool mask [H, W] by an ``open_px`` square (no-op if <= 1)."""
    if open_px <= 1:
        return mask.astype(bool)
    kernel = np.ones((open_px, open_px), np.uint8)
    return cv2.morphologyEx(mask.astype(np.uint8), cv2.MORPH_OPEN, kernel).astype(bool)


def mask_from_alpha(alpha: np.ndarray, threshold: float = 0.5) -> np.ndarray:
    """Object masks [T, H, W] (or [H, W]) bool from rendered alpha of the same shape."""
    alpha = np.asarray(alpha)
    if alpha.ndim not in (2, 3):
        raise ValueError(f"{_WHERE}: alpha must be [H, W] or [T, H, W], got shape {alpha.shape}")
    return alpha > threshold


def median_background(frames: np.ndarray) -> np.ndarray:
    """Per-pixel temporal median [H, W, 3] in [0, 1] of a fixed-camera video [T, H, W, 3]."""
    return np.median(_as_unit_float(frames), axis=0)


def mask_from_background(frames: np.ndarray, background: np.ndarray | None = None,
                         threshold: float = 0.1, open_px: int = 3) -> np.ndarray:
    """Object masks by background difference, cleaned by opening.

    Args:
        frames: video [T, H, W, 3], uint8 or float in [0, 1].
        background: [H, W, 3] or [3] (a colour key) in [0, 1]; None = temporal median.
        threshold: max-over-RGB absolute difference that marks the object [0-1 units].
        open_px: opening kernel side [px].

    Returns:
        masks [T, H, W] bool.
    """
    frames = _as_unit_float(frames)
    if frames.ndim != 4:
        raise ValueError(f"{_WHERE}: frames must be [T, H, W, 3], got shape {frames.shape}")
    bg = median_background(frames) if background is None else np.asarray(background, np.float32)
    diff = np.abs(frames - bg).max(-1)
    return np.stack([open_mask(d > threshold, open_px) for d in diff])


def load_mask_files(files_dir: str | Path, n_frames: int, size: tuple[int, int]) -> np.ndarray:
    """User masks: one PNG per frame in ``files_dir``, sorted by name; nonzero = object.

    Args:
        files_dir: directory of ``*.png`` masks.
        n_frames: expected number of frames T.
        size: expected (H, W).

    Returns:
        masks [T, H, W] bool.
    """
    files_dir = Path(files_dir)
    if not files_dir.is_dir():
        raise FileNotFoundError(f"{_WHERE}: mask directory {str(files_dir)!r} does not exist")
    paths = sorted(files_dir.glob("*.png"))
    if len(paths) != n_frames:
        raise ValueError(f"{_WHERE}: {files_dir} holds {len(paths)} mask PNGs but the video has {n_frames} frames")
    masks = []
    for path in paths:
        m = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
        if m is None:
            raise ValueError(f"{_WHERE}: {path} is not a readable image")
        if m.shape != tuple(size):
            raise ValueError(f"{_WHERE}: {path} is {m.shape[0]}x{m.shape[1]} (HxW) but frames are {size[0]}x{size[1]}")
        masks.append(m > 0)
    return np.stack(masks)


def compute_masks(cfg: MaskConfig, frames: np.ndarray | None = None,
                  alpha: np.ndarray | None = None) -> np.ndarray:
    """Masks [T, H, W] bool by the configured method.

    Args:
        cfg: mask config.
        frames: video [T, H, W, 3] (methods "segment", "background" and "files").
        alpha: rendered alpha [T, H, W] (method "alpha").
    """
    if cfg.method == "alpha":
        if alpha is None:
            raise ValueError(f"{_WHERE}: mask method 'alpha' needs the rendered alpha (synthetic scenes only)")
        return mask_from_alpha(alpha, cfg.alpha_threshold)
    if frames is None:
        raise ValueError(f"{_WHERE}: mask method {cfg.method!r} needs the video frames")
    if cfg.method == "segment":
        return segment_frames(frames, cfg.segment)
    if cfg.method == "background":
        return mask_from_background(frames, cfg.background_color, cfg.diff_threshold, cfg.open_px)
    return load_mask_files(cfg.files_dir, len(frames), tuple(np.shape(frames)[1:3]))
