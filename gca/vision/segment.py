"""Object masks segmented from the lit video frames (issue 21, item 3): what a monocular method can get.

The camera is fixed, so the classical segmenter is background subtraction (Horprasert et al., "A
statistical approach for real-time robust background subtraction and shadow detection", ICCV FRAME-RATE
workshop 1999; Cucchiara et al., "Detecting moving objects, ghosts and shadows in video streams", TPAMI 2003).
Per frame t and pixel p, with the background model B_p and the frame I_p (RGB in [0, 1]):

1. **Background model** ``B``: a clean plate (``background: plate``, the default: a fixed camera films the
   empty scene before the throw; ``plate_color``, or the plate image passed in), the per-pixel temporal
   median of the video (``median``; wrong where the object covers a pixel for more than half of the
   frames, e.g. once it rests on the floor), or the first frame (``first_frame``: wrong where the object starts).
2. **Exposure / white balance**: a per-frame, per-channel gain ``g_t = median_p(I_p / B_p)`` over the image
   border (``border_px``; the object is assumed away from the border), divided out of every frame before
   the background model is built and again against it, so global drift is not foreground (a saturated
   channel cannot be corrected: a real limit).
3. **Colour cue**: brightness distortion ``a_p = <I_p, B_p> / |B_p|^2`` and chromaticity distortion
   ``CD_p = |I_p - a_p B_p|``. Foreground where ``CD_p > chroma_threshold`` or ``a_p < shadow_min``
   (too dark to be a shadow) or ``a_p > highlight_max``. A shadow (``shadow_min <= a_p < 1`` with a small
   ``CD_p``) is background: a dark shadow is taken for the object, a shadowed dark-grey object part is
   lost (the errors real segmenters make).
4. **Edge cue**: foreground also where the Sobel gradient magnitude of the frame exceeds the
   background's by ``edge_threshold`` (kornia) and a weak colour cue (half the thresholds) agrees
   (hysteresis), which recovers textured low-contrast parts without growing every boundary by the
   Sobel support.
5. **Cleanup** (kornia morphology): opening by an ``open_px`` square (specks), closing by ``close_px``
   (small holes and cracks), then the connected components smaller than ``min_area_frac`` of the
   largest are dropped, and holes fully enclosed by the object filled (``fill_holes``).

The errors this makes are real ones: anti-aliased boundaries are thresholded (boundary), object parts
whose colour matches the background are lost (low contrast), and dark cast shadows are added (shadow).
The benchmark reports the per-frame IoU against the true alpha (``nuisance`` stage).

A learned segmenter (``backend: learned``) runs a TorchScript model from local weights
(``learned_weights``: a ``torch.jit.save`` file mapping [B, 3, H, W] in [0, 1] to foreground logits
[B, 1, H, W]); no network access, and a clear error when the weights are absent.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import cv2
import numpy as np
import torch

_WHERE = "gca/vision/segment.py"
BACKENDS = ("background", "learned")
BACKGROUND_MODELS = ("median", "first_frame", "plate")


@dataclasses.dataclass(frozen=True)
class SegmentConfig:
    """Segmentation of the lit frames (params section ``vision.masks.segment``).

    Attributes:
        backend: "background" (classical, no weights) or "learned" (TorchScript from local weights).
        background: background model: "median" | "first_frame" | "plate".
        plate_color: RGB of the empty scene for ``plate`` [0-1 units].
        border_px: image border used to estimate the per-frame gain [px].
        chroma_threshold: chromaticity distortion CD above which a pixel is object [0-1 units].
        shadow_min: brightness ratio below which a darker pixel is object, not shadow [-].
        highlight_max: brightness ratio above which a brighter pixel is object [-].
        edge_threshold: Sobel magnitude above the background's that marks the object; 0 disables [-].
        open_px: opening kernel side [px] (<= 1 disables).
        close_px: closing kernel side [px] (<= 1 disables).
        min_area_frac: components smaller than this fraction of the largest are dropped [-].
        fill_holes: fill holes enclosed by the object.
        learned_weights: TorchScript file of the learned backend.
        learned_threshold: foreground probability threshold of the learned backend [-].
    """

    backend: str = "background"
    background: str = "plate"
    plate_color: tuple[float, float, float] = (0.75, 0.75, 0.75)
    border_px: int = 2
    chroma_threshold: float = 0.06
    shadow_min: float = 0.5
    highlight_max: float = 1.15
    edge_threshold: float = 0.25
    open_px: int = 3
    close_px: int = 3
    min_area_frac: float = 0.1
    fill_holes: bool = True
    learned_weights: str = ""
    learned_threshold: float = 0.5

    def __post_init__(self) -> None:
        if self.backend not in BACKENDS:
            raise ValueError(f"{_WHERE}: SegmentConfig.backend={self.backend!r} not in {BACKENDS}")
        if self.background not in BACKGROUND_MODELS:
            raise ValueError(f"{_WHERE}: SegmentConfig.background={self.background!r} not in {BACKGROUND_MODELS}")
        if not 0 < self.shadow_min < 1 < self.highlight_max:
            raise ValueError(f"{_WHERE}: need 0 < shadow_min < 1 < highlight_max, got {self.shadow_min}, {self.highlight_max}")
        object.__setattr__(self, "plate_color", tuple(float(c) for c in self.plate_color))


def _unit(frames: np.ndarray) -> np.ndarray:
    frames = np.asarray(frames)
    if frames.ndim != 4 or frames.shape[-1] != 3:
        raise ValueError(f"{_WHERE}: frames must be [T, H, W, 3], got shape {frames.shape}")
    return frames.astype(np.float32) / 255.0 if frames.dtype == np.uint8 else frames.astype(np.float32)


def background_model(frames: np.ndarray, cfg: SegmentConfig, plate: np.ndarray | None = None) -> np.ndarray:
    """The background B [H, W, 3] in [0, 1] of a fixed-camera video [T, H, W, 3] (``plate``: an image of the
    empty scene [H, W, 3], used by ``background: plate`` instead of ``plate_color``)."""
    frames = _unit(frames)
    if cfg.background == "plate" and plate is not None:
        return _unit(np.asarray(plate)[None])[0]
    if cfg.background == "median":
        return np.median(frames, axis=0)
    if cfg.background == "first_frame":
        return frames[0].copy()
    return np.broadcast_to(np.asarray(cfg.plate_color, np.float32), frames.shape[1:]).copy()


def frame_gain(frame: np.ndarray, bg: np.ndarray, border_px: int) -> np.ndarray:
    """Per-channel gain [3] of a frame [H, W, 3] against the background, from the image border."""
    if border_px <= 0:
        return np.ones(3, np.float32)
    b = border_px
    ring = np.ones(frame.shape[:2], bool)
    ring[b:-b, b:-b] = False
    ratio = frame[ring] / np.maximum(bg[ring], 1e-3)
    return np.median(ratio, axis=0).astype(np.float32)


def _morph(masks: torch.Tensor, op: str, px: int) -> torch.Tensor:
    """kornia opening/closing of [T, 1, H, W] float masks by a ``px`` square."""
    if px <= 1:
        return masks
    import kornia.morphology as km

    kernel = torch.ones(px, px, dtype=masks.dtype)
    return (km.opening if op == "open" else km.closing)(masks, kernel, border_type="constant", border_value=0.0)


def _components(mask: np.ndarray, min_area_frac: float, fill_holes: bool) -> np.ndarray:
    """Drop components smaller than ``min_area_frac`` of the largest; fill enclosed holes."""
    m = mask.astype(np.uint8)
    n, labels, stats, _ = cv2.connectedComponentsWithStats(m, connectivity=8)
    if n > 1:
        areas = stats[1:, cv2.CC_STAT_AREA]
        keep = np.flatnonzero(areas >= min_area_frac * areas.max()) + 1
        m = np.isin(labels, keep).astype(np.uint8)
    if fill_holes and m.any():
        H, W = m.shape
        flood = np.pad(1 - m, 1, constant_values=1).astype(np.uint8)
        cv2.floodFill(flood, None, (0, 0), 2)
        m = m | (flood[1:H + 1, 1:W + 1] == 1).astype(np.uint8)  # background not reached from outside = hole
    return m.astype(bool)


def _sobel_mag(images: torch.Tensor) -> torch.Tensor:
    """Sobel gradient magnitude of the grey image [T, 1, H, W] (kornia)."""
    import kornia.filters as kf

    return kf.sobel(images)


def normalise_gains(frames: np.ndarray, border_px: int) -> np.ndarray:
    """Frames [T, H, W, 3] divided by their per-frame, per-channel gain against the temporal median of the
    image border (exposure / white-balance drift removed before the background model is built)."""
    if border_px <= 0:
        return frames
    ref = np.median(frames, axis=0)
    gains = np.stack([frame_gain(f, ref, border_px) for f in frames])
    return frames / np.maximum(gains, 1e-3)[:, None, None, :]


def raw_foreground(frames: np.ndarray, cfg: SegmentConfig, plate: np.ndarray | None = None) -> np.ndarray:
    """Foreground evidence before cleanup [T, H, W] bool (colour and edge cues; module docstring)."""
    frames = normalise_gains(_unit(frames), cfg.border_px)
    bg = background_model(frames, cfg, plate)
    out = []
    grey_bg = torch.as_tensor(bg.mean(-1))[None, None]
    edge_bg = _sobel_mag(grey_bg)[0, 0].numpy() if cfg.edge_threshold > 0 else None
    for frame in frames:
        B = bg * frame_gain(frame, bg, cfg.border_px)
        a = (frame * B).sum(-1) / np.maximum((B * B).sum(-1), 1e-6)
        cd = np.linalg.norm(frame - a[..., None] * B, axis=-1)
        fg = (cd > cfg.chroma_threshold) | (a < cfg.shadow_min) | (a > cfg.highlight_max)
        if edge_bg is not None:
            edge = _sobel_mag(torch.as_tensor(frame.mean(-1))[None, None])[0, 0].numpy()
            weak = (cd > 0.5 * cfg.chroma_threshold) | (np.abs(a - 1.0) > 0.05)  # hysteresis: the edge cue only
            fg |= ((edge - edge_bg) > cfg.edge_threshold) & weak                   # confirms a weak colour cue
        out.append(fg)
    return np.stack(out)


def _learned(frames: np.ndarray, cfg: SegmentConfig) -> np.ndarray:
    path = Path(cfg.learned_weights)
    if not cfg.learned_weights or not path.is_file():
        raise FileNotFoundError(f"{_WHERE}: learned segmenter weights not found at {str(path)!r} "
                                "(vision.masks.segment.learned_weights: a local TorchScript file; or use backend: background)")
    model = torch.jit.load(str(path), map_location="cpu").eval()
    x = torch.as_tensor(_unit(frames)).permute(0, 3, 1, 2)
    with torch.no_grad():
        prob = torch.sigmoid(model(x))[:, 0]
    return (prob > cfg.learned_threshold).numpy()


def segment_frames(frames: np.ndarray, cfg: SegmentConfig = SegmentConfig(),
                   plate: np.ndarray | None = None) -> np.ndarray:
    """Object masks [T, H, W] bool of a fixed-camera video [T, H, W, 3] (uint8 or float in [0, 1]);
    ``plate``: the empty scene [H, W, 3] for ``background: plate`` (None: ``plate_color``)."""
    if cfg.backend == "learned":
        fg = _learned(frames, cfg)
    else:
        fg = raw_foreground(frames, cfg, plate)
    m = torch.as_tensor(fg, dtype=torch.float32)[:, None]
    m = _morph(_morph(m, "open", cfg.open_px), "close", cfg.close_px)[:, 0].numpy() > 0.5
    return np.stack([_components(f, cfg.min_area_frac, cfg.fill_holes) for f in m])


def iou(pred: np.ndarray, true: np.ndarray) -> np.ndarray:
    """Per-frame intersection over union [T] of bool masks [T, H, W] (1 where both are empty)."""
    pred, true = np.asarray(pred, bool), np.asarray(true, bool)
    inter = (pred & true).sum(axis=(-2, -1))
    union = (pred | true).sum(axis=(-2, -1))
    return np.where(union > 0, inter / np.maximum(union, 1), 1.0)
