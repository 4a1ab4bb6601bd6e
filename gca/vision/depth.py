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
    """

    background: float = 1.5
    gamma_max: float = 1.6
    edge_band_px: float = 3.0
    noise_std: float = 0.005
    lowfreq_std: float = 0.02
    lowfreq_sigma_px: float = 16.0
    scale_range: tuple[float, float] = (0.5, 2.0)
    shift_range: tuple[float, float] = (-0.5, 0.5)

    def __post_init__(self) -> None:
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


def _simulate_frame(z: np.ndarray, mask: np.ndarray, cfg: SimulatedDepthConfig,
                    rng: np.random.Generator) -> np.ndarray:
    """One frame of the estimator model: normalise, warp, bleed, noise, scale and shift."""
    d = _normalise_object_depth(z, mask, cfg.background)
    g = np.exp(rng.uniform(-np.log(cfg.gamma_max), np.log(cfg.gamma_max)))
    d = d ** g
    d = _edge_bleed(d, mask, cfg.edge_band_px)
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
    set to ``cfg.background``), warped by d^g_t (a random monotone power), blended toward its blur
    within ``edge_band_px`` of the mask edge (foreground/background bleed, as estimators smear
    depth discontinuities), perturbed by pixel noise and a smooth noise field, then mapped by a
    random positive scale and shift. Seeded: the same (cfg, seed) gives the same output.
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
        return np.stack([_simulate_frame(z, m, self.cfg, rng) for z, m in zip(gt_depth, masks)])


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
