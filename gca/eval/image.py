"""Image metrics: PSNR, SSIM (kornia, window 11) and LPIPS when local weights exist.

Images are channels-first float tensors in [0, max_val]: [C, H, W] or [B, C, H, W] with C in
{1, 3}. Masks (optional, to "filter the background" as the paper does for real scenes) are
[H, W], [1, H, W] or [B, 1, H, W], bool or float in [0, 1]; a metric is then averaged over
masked pixels only. Batched inputs return one value per image ([B]); unbatched a scalar.
"""

from __future__ import annotations

import glob
import importlib.util
import os
from typing import Optional

import torch

SSIM_WINDOW = 11  # Gaussian window side [px], sigma 1.5 (kornia's default, Wang et al. 2004)


def _as_batch(img: torch.Tensor, name: str) -> tuple[torch.Tensor, bool]:
    if img.ndim not in (3, 4) or img.shape[-3] not in (1, 3):
        raise ValueError(f"gca/eval/image.py: {name} must be [C, H, W] or [B, C, H, W] with C in (1, 3) "
                         f"(channels first; use img.permute(2, 0, 1) for [H, W, C]), got {tuple(img.shape)}")
    return (img, True) if img.ndim == 4 else (img[None], False)


def _as_mask(mask: Optional[torch.Tensor], img: torch.Tensor) -> torch.Tensor:
    """Mask as float [B, 1, H, W] (all ones when None)."""
    B, _, H, W = img.shape
    if mask is None:
        return img.new_ones(B, 1, H, W)
    m = mask.to(img.dtype)
    m = m.reshape(-1, 1, *m.shape[-2:]) if m.ndim in (2, 3, 4) else m
    if m.shape[-2:] != (H, W) or m.shape[0] not in (1, B):
        raise ValueError(f"gca/eval/image.py: mask {tuple(mask.shape)} does not match images {tuple(img.shape)}")
    if m.sum() <= 0:
        raise ValueError("gca/eval/image.py: mask selects no pixel")
    return m.expand(B, 1, H, W)


def _prepare(img: torch.Tensor, ref: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, bool]:
    x, batched = _as_batch(img, "img")
    y, _ = _as_batch(ref, "ref")
    if x.shape != y.shape:
        raise ValueError(f"gca/eval/image.py: img {tuple(img.shape)} and ref {tuple(ref.shape)} differ in shape")
    return x, y, batched


def _masked_mean(values: torch.Tensor, m: torch.Tensor) -> torch.Tensor:
    """Per-image mean of [B, C, H, W] ``values`` over masked pixels and all channels -> [B]."""
    C = values.shape[1]
    return (values * m).sum(dim=(1, 2, 3)) / (m.sum(dim=(1, 2, 3)) * C)


def psnr(img: torch.Tensor, ref: torch.Tensor, mask: Optional[torch.Tensor] = None,
         max_val: float = 1.0) -> torch.Tensor:
    """Peak signal-to-noise ratio 10 log10(max_val^2 / MSE) [dB], MSE over masked pixels and channels.

    Args:
        img: [B, C, H, W] or [C, H, W] prediction.
        ref: same shape, reference.
        mask: optional pixel mask (see module docstring).
        max_val: peak value of the image range.

    Returns:
        [B] or scalar PSNR in dB (inf for identical images).
    """
    x, y, batched = _prepare(img, ref)
    mse = _masked_mean((x - y).square(), _as_mask(mask, x))
    out = 10.0 * torch.log10(max_val ** 2 / mse)
    return out if batched else out[0]


def ssim(img: torch.Tensor, ref: torch.Tensor, mask: Optional[torch.Tensor] = None,
         max_val: float = 1.0, window: int = SSIM_WINDOW) -> torch.Tensor:
    """Structural similarity (kornia.metrics.ssim map, Gaussian window), averaged over masked pixels.

    Args:
        img: [B, C, H, W] or [C, H, W] prediction.
        ref: same shape, reference.
        mask: optional pixel mask (see module docstring).
        max_val: peak value of the image range.
        window: Gaussian window side [px].

    Returns:
        [B] or scalar SSIM in [-1, 1] (1 for identical images).
    """
    import kornia

    x, y, batched = _prepare(img, ref)
    ssim_map = kornia.metrics.ssim(x, y, window, max_val=max_val)
    out = _masked_mean(ssim_map, _as_mask(mask, x))
    return out if batched else out[0]


def _lpips_backbone_file(net: str) -> Optional[str]:
    """Path of a locally cached torchvision backbone checkpoint for ``net`` (None if absent)."""
    import torch.hub

    stem = {"vgg": "vgg16-", "alex": "alexnet-", "squeeze": "squeezenet1_1-"}.get(net)
    if stem is None:
        raise ValueError(f"gca/eval/image.py: unknown LPIPS net {net!r} (vgg, alex, squeeze)")
    hits = glob.glob(os.path.join(torch.hub.get_dir(), "checkpoints", stem + "*.pth"))
    return hits[0] if hits else None


def lpips_unavailable_reason(net: str = "vgg") -> Optional[str]:
    """Why LPIPS cannot be computed here, or None when it can (package, torchvision, local weights)."""
    if importlib.util.find_spec("lpips") is None:
        return "lpips: package not installed (it also needs torchvision and backbone weights)"
    if importlib.util.find_spec("torchvision") is None:
        return "lpips: torchvision not installed (lpips imports it to build the backbone)"
    if _lpips_backbone_file(net) is None:
        return (f"lpips: no local {net} backbone weights under torch.hub.get_dir()/checkpoints "
                "(lpips would download them at run time; this machine is offline)")
    return None


def lpips_or_reason(img: torch.Tensor, ref: torch.Tensor, net: str = "vgg",
                    max_val: float = 1.0) -> tuple[Optional[torch.Tensor], Optional[str]]:
    """LPIPS distance if it can be computed offline, else ``(None, reason)``.

    Args:
        img: [B, 3, H, W] or [3, H, W] prediction in [0, max_val].
        ref: same shape, reference.
        net: LPIPS backbone (the NeuMA evaluation uses ``"vgg"``).
        max_val: peak value of the image range (inputs are mapped to [-1, 1]).

    Returns:
        ``(value [B] or scalar, None)`` or ``(None, reason string)``.
    """
    x, y, batched = _prepare(img, ref)
    reason = lpips_unavailable_reason(net)
    if reason is not None:
        return None, reason
    import lpips  # noqa: PLC0415 (optional dependency, only when weights are present)

    model = lpips.LPIPS(net=net, verbose=False).to(x.device).eval()
    with torch.no_grad():
        out = model(2 * x / max_val - 1, 2 * y / max_val - 1).reshape(-1)
    return (out if batched else out[0]), None
