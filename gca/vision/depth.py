"""Monocular relative depth for the GT video: a Depth Anything backend and a simulated estimator.

Every backend returns *relative depth* ``[T, H, W]`` float32 that increases with distance from
the camera, up to an unknown per-frame positive scale and shift (and, for real estimators, an
unknown monotone warp). RDGA only uses its local rank order, so these ambiguities are harmless to
the rank term and harmful to the L1 ablation, which is the paper's point.

Backends (``DepthConfig.backend``):

- ``"transformers"``: Depth Anything (V1/V2, e.g. ``depth-anything/Depth-Anything-V2-Small-hf``)
  through ``transformers.AutoModelForDepthEstimation`` loaded from a LOCAL directory, offline.
  Depth Anything predicts relative *inverse* depth (disparity, larger = nearer), affine-ambiguous:
  ``disp = a / z + b``. We min-max normalise each frame's disparity to [0, 1] and return
  ``1 / (disp_n + disparity_eps)``: strictly decreasing in disparity, so the rank order is exactly
  that of depth, while the values stay an (unknown) non-linear function of z. Frames are processed
  independently (Video Depth Anything is not in transformers; per-frame scale drift does not
  matter to a per-frame rank loss).
- ``"simulated"``: a MODEL of a monocular estimator for synthetic scenes, not an estimator: it
  takes the renderer's GT depth and mask and adds what estimators get wrong (see
  :class:`SimulatedDepthConfig`). Use it to run the pipeline without network weights.
"""

from __future__ import annotations

import abc
import dataclasses
import os
from pathlib import Path

import cv2
import numpy as np

_WHERE = "gca/vision/depth.py"
BACKENDS = ("simulated", "transformers")


class DepthError(RuntimeError):
    """A depth backend cannot run (names what is missing and how to get it)."""


@dataclasses.dataclass(frozen=True)
class SimulatedDepthConfig:
    """What the simulated estimator gets wrong, applied in this order on the GT depth z.

    Attributes:
        background: relative depth given to background pixels, in units of the object's per-frame
            depth range (object mapped to [0, 1]; must exceed 1 to lie behind it) [-].
        gamma_max: per-frame monotone warp d -> d^g with log g ~ U(-log gamma_max, log gamma_max)
            (>= 1; 1 disables the warp) [-].
        edge_band_px: half-width of the band around the mask edge where depth bleeds across the
            edge (blended with a Gaussian blur of sigma = edge_band_px); 0 disables [px].
        noise_std: i.i.d. Gaussian pixel noise [normalised depth units].
        lowfreq_std: smooth noise field (Gaussian-blurred, sigma = lowfreq_sigma_px) [normalised].
        lowfreq_sigma_px: correlation length of the smooth noise [px].
        scale_range: per-frame positive scale s ~ log-uniform in [lo, hi] [-].
        shift_range: per-frame shift b ~ uniform in [lo, hi] [-].
        texture_copy: texture copying: the high-pass of the frame's grey level (frame minus its Gaussian blur
            of sigma ``texture_sigma_px``) is added inside the object with this gain; darker reads nearer
            (more distant), as estimators read albedo and shading as relief; 0 disables [normalised depth
            per unit intensity].
        texture_sigma_px: scale of the copied texture [px].
        smooth_sigma_px: over-smoothing: the whole frame's depth (object and background) is blurred with
            this sigma, which rounds boundaries and flattens fine relief; 0 disables [px].
        thin_px: object parts thinner than this (removed by an opening with a square of this side) are
            thin parts; 0 disables [px].
        thin_flatten: thin parts' depth moves this fraction of the way to the background's (flattened into
            it, as estimators miss thin structures) [-].
        flicker_tilt_std: temporal flicker beyond scale/shift: a fresh random planar tilt per frame (std of
            its slope across the object's extent), so the same surface ranks differently frame to frame;
            0 disables [normalised depth].

    The non-monotone components (texture copying, over-smoothing, thin parts, flicker) default to off
    here; ``params.yaml`` sets the benchmark's values (docs/benchmark.md says where they come from).
    """

    background: float = 1.5
    gamma_max: float = 1.6
    edge_band_px: float = 3.0
    noise_std: float = 0.005
    lowfreq_std: float = 0.02
    lowfreq_sigma_px: float = 16.0
    scale_range: tuple[float, float] = (0.5, 2.0)
    shift_range: tuple[float, float] = (-0.5, 0.5)
    texture_copy: float = 0.15
    texture_sigma_px: float = 3.0
    smooth_sigma_px: float = 2.0
    thin_px: int = 7
    thin_flatten: float = 0.5
    flicker_tilt_std: float = 0.05

    def __post_init__(self) -> None:
        if min(self.texture_copy, self.smooth_sigma_px, self.thin_px, self.thin_flatten, self.flicker_tilt_std) < 0 \
                or self.thin_flatten > 1 or self.texture_sigma_px <= 0:
            raise ValueError(f"{_WHERE}: SimulatedDepthConfig's error components must be >= 0 (thin_flatten <= 1, "
                             f"texture_sigma_px > 0)")
        if self.gamma_max < 1 or self.background <= 1:
            raise ValueError(f"{_WHERE}: SimulatedDepthConfig needs gamma_max >= 1 and background > 1, "
                             f"got gamma_max={self.gamma_max}, background={self.background}")
        lo, hi = self.scale_range
        if not 0 < lo <= hi:
            raise ValueError(f"{_WHERE}: SimulatedDepthConfig.scale_range must be 0 < lo <= hi, got {self.scale_range}")
        object.__setattr__(self, "scale_range", tuple(self.scale_range))
        object.__setattr__(self, "shift_range", tuple(self.shift_range))


@dataclasses.dataclass(frozen=True)
class TransformersDepthConfig:
    """Depth Anything through transformers (optional extra ``pip install 'gca[depth]'``).

    Attributes:
        weights_dir: local directory holding the Hugging Face model (config.json, weights,
            preprocessor_config.json); relative paths are taken from the working directory.
        device: torch device for inference ("cpu", "cuda").
        batch_size: frames per forward pass [count].
        disparity_eps: added to the [0, 1]-normalised disparity before inversion [-].
    """

    weights_dir: str = "models/depth/Depth-Anything-V2-Small-hf"
    device: str = "cpu"
    batch_size: int = 8
    disparity_eps: float = 0.05


@dataclasses.dataclass(frozen=True)
class DepthConfig:
    """Which depth backend, and its settings (params section ``vision.depth``)."""

    backend: str = "simulated"
    simulated: SimulatedDepthConfig = SimulatedDepthConfig()
    transformers: TransformersDepthConfig = TransformersDepthConfig()

    def __post_init__(self) -> None:
        if self.backend not in BACKENDS:
            raise ValueError(f"{_WHERE}: DepthConfig.backend={self.backend!r} not in {BACKENDS}")


def _check_frames(frames: np.ndarray) -> np.ndarray:
    frames = np.asarray(frames)
    if frames.ndim != 4 or frames.shape[-1] != 3:
        raise ValueError(f"{_WHERE}: frames must be [T, H, W, 3], got shape {frames.shape}")
    return frames


class DepthEstimator(abc.ABC):
    """Interface: ``estimate(frames [T,H,W,3]) -> relative depth [T,H,W]`` float32."""

    @abc.abstractmethod
    def estimate(self, frames: np.ndarray, gt_depth: np.ndarray | None = None,
                 masks: np.ndarray | None = None) -> np.ndarray:
        """Relative depth of each frame, increasing with distance.

        Args:
            frames: RGB video [T, H, W, 3], uint8 in [0, 255] or float in [0, 1].
            gt_depth: GT camera-space depth [T, H, W] (simulated backend only).
            masks: GT object masks [T, H, W] bool (simulated backend only).

        Returns:
            relative depth [T, H, W] float32.
        """


def _normalise_object_depth(z: np.ndarray, mask: np.ndarray, background: float) -> np.ndarray:
    """Map the object's depth in one frame to [0, 1] (background -> ``background``)."""
    d = np.full(z.shape, background, dtype=np.float64)
    if mask.any():
        zo = z[mask].astype(np.float64)
        lo, hi = zo.min(), zo.max()
        d[mask] = (zo - lo) / max(hi - lo, 1e-12)
    return d


def _edge_bleed(d: np.ndarray, mask: np.ndarray, band_px: float) -> np.ndarray:
    """Blend depth with its blur within ``band_px`` of the mask edge (weight 1 at the edge)."""
    if band_px <= 0:
        return d
    m = mask.astype(np.uint8)
    # distance to the other side of the edge: inside, to the nearest background pixel; outside, to the
    # nearest object pixel (each transform is zero on the other side, so the sum is the distance)
    dist = cv2.distanceTransform(m, cv2.DIST_L2, 5) + cv2.distanceTransform(1 - m, cv2.DIST_L2, 5)
    w = np.clip(1.0 - dist / band_px, 0.0, 1.0)
    blurred = cv2.GaussianBlur(d, (0, 0), sigmaX=band_px, borderType=cv2.BORDER_REPLICATE)
    return (1.0 - w) * d + w * blurred


def texture_copy(d: np.ndarray, grey: np.ndarray, mask: np.ndarray, gain: float, sigma_px: float) -> np.ndarray:
    """Add the high-pass of the grey image [H, W] (in [0, 1]) inside the object: darker = farther."""
    if gain <= 0:
        return d
    high = grey - cv2.GaussianBlur(grey, (0, 0), sigmaX=sigma_px, borderType=cv2.BORDER_REPLICATE)
    return d - gain * high * mask


def oversmooth(d: np.ndarray, sigma_px: float) -> np.ndarray:
    """Blur the whole depth map (object and background) with ``sigma_px``."""
    if sigma_px <= 0:
        return d
    return cv2.GaussianBlur(d, (0, 0), sigmaX=sigma_px, borderType=cv2.BORDER_REPLICATE)


def thin_parts(mask: np.ndarray, thin_px: int) -> np.ndarray:
    """Object pixels [H, W] bool that an opening with a ``thin_px`` square removes."""
    if thin_px <= 1:
        return np.zeros_like(mask, dtype=bool)
    m = mask.astype(np.uint8)
    opened = cv2.morphologyEx(m, cv2.MORPH_OPEN, np.ones((thin_px, thin_px), np.uint8))
    return mask.astype(bool) & ~opened.astype(bool)


def flatten_thin(d: np.ndarray, mask: np.ndarray, thin_px: int, weight: float, background: float) -> np.ndarray:
    """Move thin parts' depth ``weight`` of the way to the background's."""
    thin = thin_parts(mask, thin_px)
    if weight <= 0 or not thin.any():
        return d
    return np.where(thin, (1 - weight) * d + weight * background, d)


def flicker_tilt(d: np.ndarray, mask: np.ndarray, std: float, rng: np.random.Generator) -> np.ndarray:
    """Add a random plane (slope ~ N(0, std) per object extent along x and y) inside the object."""
    if std <= 0 or not mask.any():
        return d
    rows, cols = np.nonzero(mask)
    extent = max(np.ptp(rows), np.ptp(cols), 1)
    gy, gx = rng.normal(0.0, std, 2)
    yy, xx = np.mgrid[0:d.shape[0], 0:d.shape[1]]
    plane = (gy * (yy - rows.mean()) + gx * (xx - cols.mean())) / extent
    return d + plane * mask


def _simulate_frame(z: np.ndarray, mask: np.ndarray, cfg: SimulatedDepthConfig,
                    rng: np.random.Generator, grey: np.ndarray | None = None) -> np.ndarray:
    """One frame of the estimator model: normalise, warp, texture copy, thin parts, flicker, bleed, smooth,
    noise, scale and shift."""
    d = _normalise_object_depth(z, mask, cfg.background)
    g = np.exp(rng.uniform(-np.log(cfg.gamma_max), np.log(cfg.gamma_max)))
    d = d ** g
    if grey is not None:
        d = texture_copy(d, grey, mask, cfg.texture_copy, cfg.texture_sigma_px)
    d = flatten_thin(d, mask, cfg.thin_px, cfg.thin_flatten, cfg.background)
    d = flicker_tilt(d, mask, cfg.flicker_tilt_std, rng)
    d = _edge_bleed(d, mask, cfg.edge_band_px)
    d = oversmooth(d, cfg.smooth_sigma_px)
    d = d + cfg.noise_std * rng.standard_normal(d.shape)
    if cfg.lowfreq_std > 0:
        field = cv2.GaussianBlur(rng.standard_normal(d.shape), (0, 0), sigmaX=cfg.lowfreq_sigma_px)
        d = d + cfg.lowfreq_std * field / max(field.std(), 1e-12)
    s = np.exp(rng.uniform(np.log(cfg.scale_range[0]), np.log(cfg.scale_range[1])))
    b = rng.uniform(*cfg.shift_range)
    return (s * d + b).astype(np.float32)


class SimulatedDepth(DepthEstimator):
    """A model of a monocular depth estimator for synthetic scenes (NOT an estimator).

    Per frame t, on the GT depth z and mask M: the object's depth is mapped to [0, 1] (background
    set to ``cfg.background``), warped by d^g_t (a random monotone power), given the non-monotone
    errors of real estimators (texture copying from the frame, thin parts flattened toward the
    background, a per-frame random tilt: flicker), blended toward its blur within ``edge_band_px`` of
    the mask edge (foreground/background bleed), blurred as a whole (over-smoothing), perturbed by pixel
    noise and a smooth noise field, then mapped by a random positive scale and shift. Seeded: the same
    (cfg, seed) gives the same output.
    """

    def __init__(self, cfg: SimulatedDepthConfig, seed: int = 0) -> None:
        self.cfg, self.seed = cfg, seed

    def estimate(self, frames, gt_depth=None, masks=None):
        frames = _check_frames(frames)
        if gt_depth is None or masks is None:
            raise ValueError(f"{_WHERE}: the simulated depth backend needs gt_depth and masks "
                             "(it models an estimator from the GT; use backend 'transformers' for real video)")
        gt_depth, masks = np.asarray(gt_depth), np.asarray(masks).astype(bool)
        if gt_depth.shape != frames.shape[:3] or masks.shape != frames.shape[:3]:
            raise ValueError(f"{_WHERE}: gt_depth {gt_depth.shape} and masks {masks.shape} must be "
                             f"[T, H, W] = {frames.shape[:3]}")
        if not np.isfinite(gt_depth[masks]).all():
            raise ValueError(f"{_WHERE}: gt_depth is non-finite inside the object mask")
        rng = np.random.default_rng(self.seed)
        unit = frames.astype(np.float64) / 255.0 if frames.dtype == np.uint8 else frames.astype(np.float64)
        grey = unit.mean(-1)
        return np.stack([_simulate_frame(z, m, self.cfg, rng, g) for z, m, g in zip(gt_depth, masks, grey)])


_HOWTO = ("to obtain the weights, on a machine with network run\n"
          "    huggingface-cli download depth-anything/Depth-Anything-V2-Small-hf --local-dir {dir}\n"
          "(or any Depth Anything *-hf model), copy the directory here and set "
          "vision.depth.transformers.weights_dir in params.yaml")


def _missing_parts(weights_dir: Path) -> list[str]:
    """What prevents loading Depth Anything offline (empty when nothing)."""
    problems = []
    if not (weights_dir / "config.json").is_file():
        problems.append(f"no model at weights_dir={str(weights_dir)!r} (config.json not found); "
                        + _HOWTO.format(dir=weights_dir))
    try:
        import transformers  # noqa: F401  (optional extra, imported lazily)
    except ImportError:
        problems.append("the 'transformers' package is not installed: pip install 'gca[depth]' "
                        "(transformers>=4.45, safetensors)")
    return problems


class TransformersDepth(DepthEstimator):
    """Depth Anything via transformers, offline from a local directory (module docstring)."""

    def __init__(self, cfg: TransformersDepthConfig) -> None:
        weights_dir = Path(cfg.weights_dir)
        problems = _missing_parts(weights_dir)
        if problems:
            raise DepthError(f"{_WHERE}: the transformers depth backend cannot run:\n- " + "\n- ".join(problems))
        os.environ.setdefault("HF_HUB_OFFLINE", "1")
        os.environ.setdefault("TRANSFORMERS_OFFLINE", "1")
        from transformers import AutoImageProcessor, AutoModelForDepthEstimation

        self.cfg = cfg
        self.processor = AutoImageProcessor.from_pretrained(weights_dir, local_files_only=True)
        self.model = AutoModelForDepthEstimation.from_pretrained(weights_dir, local_files_only=True)
        self.model.to(cfg.device).eval()

    def _disparity(self, batch: np.ndarray) -> np.ndarray:
        """Raw model output (relative disparity) resized to the frames' size [B, H, W]."""
        import torch

        H, W = batch.shape[1:3]
        inputs = self.processor(images=list(batch), return_tensors="pt").to(self.cfg.device)
        with torch.no_grad():
            pred = self.model(**inputs).predicted_depth  # [B, h, w]
        pred = torch.nn.functional.interpolate(pred[:, None], size=(H, W), mode="bilinear", align_corners=False)
        return pred[:, 0].float().cpu().numpy()

    def estimate(self, frames, gt_depth=None, masks=None):
        frames = _check_frames(frames)
        if frames.dtype != np.uint8:
            frames = (np.clip(frames, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)
        disp = np.concatenate([self._disparity(frames[i:i + self.cfg.batch_size])
                               for i in range(0, len(frames), self.cfg.batch_size)])
        return disparity_to_depth(disp, self.cfg.disparity_eps)


def disparity_to_depth(disp: np.ndarray, eps: float) -> np.ndarray:
    """Relative depth from relative disparity: ``1 / (minmax_t(disp) + eps)`` per frame.

    Args:
        disp: relative disparity [T, H, W] (larger = nearer).
        eps: offset of the normalised disparity (> 0; bounds the far depth at 1 / eps) [-].

    Returns:
        relative depth [T, H, W] float32, a strictly decreasing function of disparity per frame.
    """
    if disp.ndim != 3 or not eps > 0:
        raise ValueError(f"{_WHERE}: disparity_to_depth needs [T, H, W] and eps > 0, got {disp.shape}, {eps}")
    lo = disp.min(axis=(1, 2), keepdims=True)
    hi = disp.max(axis=(1, 2), keepdims=True)
    return (1.0 / ((disp - lo) / np.maximum(hi - lo, 1e-12) + eps)).astype(np.float32)


def make_depth_estimator(cfg: DepthConfig, seed: int = 0) -> DepthEstimator:
    """The configured backend (the transformers one checks its weights and package here)."""
    if cfg.backend == "simulated":
        return SimulatedDepth(cfg.simulated, seed)
    return TransformersDepth(cfg.transformers)


def estimate_depth(frames: np.ndarray, cfg: DepthConfig, gt_depth: np.ndarray | None = None,
                   masks: np.ndarray | None = None, seed: int = 0) -> np.ndarray:
    """Relative depth [T, H, W] of a video [T, H, W, 3] with the configured backend."""
    return make_depth_estimator(cfg, seed).estimate(frames, gt_depth, masks)


def silhouette_depth(masks: np.ndarray, background: float = 1.5) -> np.ndarray:
    """A depth fallback needing only masks (captures without a depth model): relative depth [T, H, W] float32,
    ``background`` outside the mask and ``1 - d / d_max`` inside, d the Euclidean distance to the mask's edge
    [px]: the object reads as a rounded solid nearest at its silhouette's middle. It carries no texture or
    surface detail, so RDGA's anchor and global terms see only this shape prior (README, "Your own object").

    Args:
        masks: [T, H, W] bool object masks.
        background: relative depth of background pixels [1] (``vision.depth.simulated.background``'s role).
    """
    import cv2

    masks = np.asarray(masks, dtype=bool)
    if masks.ndim != 3:
        raise ValueError(f"{_WHERE}: silhouette_depth needs masks [T, H, W], got {masks.shape}")
    out = np.full(masks.shape, background, dtype=np.float32)
    for t, m in enumerate(masks):
        if m.any():
            d = cv2.distanceTransform(m.astype(np.uint8), cv2.DIST_L2, 3)
            out[t][m] = 1.0 - d[m] / max(float(d.max()), 1e-6)
    return out
