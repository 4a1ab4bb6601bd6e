"""Rank-based Depth-Geometric Anchors (RDGA, paper Sec. 3.3): silhouette, global and anchor terms.

Inputs for one frame (all torch, one device):

- ``render_out``: the renderer's ``{"rgb" [H,W,3], "alpha" [H,W], "depth" [H,W]}``; ``alpha`` is
  the soft rendered silhouette ``M_render`` and ``depth`` the rendered camera-space z (only its
  interior values are used: every anchor patch lies in the stable region, where alpha ~ 1).
- ``gt_mask`` [H,W]: the ground-truth object mask ``M_gt`` (bool or {0,1}).
- ``est_depth`` [H,W]: the monocular relative depth ``D_gt`` of the GT frame (increasing with
  distance; any unknown positive scale/shift/monotone warp, which the rank term ignores).
- ``p``, ``q`` [M,2]: matched pixel coordinates ``(x, y)`` in the rendered and GT images, in the
  *array-index* convention of OpenCV keypoints (the centre of pixel column i, row j is (i, j)).

Terms (paper Eqs. for L_mask and L_geo)::

    L_mask = mean_pixels (alpha - M_gt)^2                       (paper: ||.||_2^2, a sum; see below)
    L_geo  = lambda1 * ||P_render - P_gt||_2  +  lambda2 * sum_{i in A} (-gamma_i)
    loss   = lambda_mask * L_mask + lambda_geo * L_geo

Choices made where the paper is silent or ambiguous (each a switch in :class:`RDGAConfig`):

- ``mask_reduction="mean"``: the paper writes a squared L2 norm (a sum over pixels); the mean is the
  same up to the factor H*W and keeps ``lambda_mask`` independent of resolution. ``"sum"`` is literal.
- Stable region. The paper defines ``M_edge = M o K_rxr`` (opening) and ``M_stable = M \\ M_edge``.
  Read literally that set difference is the white top-hat: only structures thinner than r survive,
  i.e. thin protrusions, not the interior, which contradicts the stated intent ("stable interior
  regions", "mitigate depth estimation errors near object boundaries"). The default
  ``stable_region="eroded"`` therefore takes ``M_stable = M erode K_rxr``: the mask minus a
  boundary band of width (r - 1) / 2 px. ``"paper_literal"`` gives ``M - opening(M, K_rxr)``.
  Both are flat r x r max-poolings (:func:`_window_max`, a geodesic border: the image border does not erode the
  mask).
- ``P_render``/``P_gt`` (global term). The matcher's p_i are constants, so ``||p - q||`` has no
  gradient. We define ``P_render_i`` as the pixel at which the surface point seen at p_i
  projects: ``pi(X(p_i))`` where ``X`` is a rendered *position image* (Gaussian/particle positions
  rendered as colours, premultiplied by alpha, i.e. rendered on a zero background) bilinearly
  sampled at p_i and divided by the rendered alpha there. It is differentiable w.r.t. the
  positions of the Gaussians (hence particles) covering p_i. ``P_gt_i = q_i``. Minimising the term
  moves the material seen at p_i toward where its feature was observed in the GT frame. Only
  matches with rendered alpha(p_i) >= ``alpha_threshold`` and ``M_gt(q_i)`` set are used.
  Its gradient (``global_gradient="material"``, default) flows through the composited positions
  only, with the compositing weights held fixed: the surface seen at a pixel of a dense splat lies on
  that pixel's ray whatever the Gaussians do, so ``pi(X(p_i)) = p_i`` identically and its *full*
  derivative is ~0 plus discretisation noise (the weights' and the positions' parts cancel); held
  weights give ``d P_render_i / d mu_g = w_g / sum w * d pi / d mu_g``, i.e. the image motion of
  the material seen at p_i, which is what moving that feature towards q_i needs. ``"full"`` keeps
  the rasterizer's full derivative (measured ~0 on dense splats: benchmarks/NOTES.md, session 6).
  ``global_reduction="norm"`` is the paper's ``||.||_2`` of the whole [M,2] difference (Frobenius,
  grows like sqrt(M)); ``"mean"`` is the mean per-match distance [px]; ``"mean_sq"`` the mean squared
  per-match distance [px^2], whose gradient vanishes as the residual does (the two others push with a
  unit-length gradient even at the matcher's noise floor: benchmarks/NOTES.md, session 5).
  ``global_max_px`` > 0 drops matches whose current residual exceeds it [px] (a truncated loss): the
  norm is dominated by its largest residual, and one wrong match (6% are, at ~1 px RANSAC noise, at the
  exact state: benchmarks/NOTES.md, session 6) then sets the whole term's direction. 0 (default) keeps
  every match, as the paper writes it.
- Anchor term: ``anchor_reduction="sum"`` is literal; ``"mean"`` divides by |A|.
  ``depth_term="l1"`` (ablation "Replace Rank w/ L1") keeps the anchor selection (stable region +
  exact-rank consensus filter) and replaces ``-gamma_i`` by the mean absolute difference of the two
  raw depth patches (no scale alignment, as in the ablation).
- ``enabled=False`` (ablation "w/o RDGA") drops L_geo; L_mask stays (it is a term of the overall
  objective; set ``lambda_mask=0`` to drop it too).
"""

from __future__ import annotations

import dataclasses
from typing import Any, Mapping

import numpy as np
import torch
import torch.nn.functional as F_nn

from gca.align.softrank import spearman_exact, spearman_soft
from gca.config import NOT_A_PARAM

_WHERE = "gca/align/rdga.py"
STABLE_MODES = ("eroded", "paper_literal")
STABLE_ON = ("render", "gt", "both")
DEPTH_TERMS = ("rank", "l1")
GLOBAL_GRADIENTS = ("material", "full")


@dataclasses.dataclass(frozen=True)
class RDGAConfig:
    """RDGA knobs (paper Sec. 3.3). The paper gives no values for r, k, tau or the lambdas.

    Attributes:
        enabled: compute L_geo at all (False = ablation "w/o RDGA"; L_mask stays).
        use_global: the global alignment term (False = ablation "w/o global").
        use_anchor: the anchor-level term (False = ablation "w/o Anchor Superv.").
        depth_term: "rank" (paper: -gamma_i) or "l1" (ablation: L1 of raw depth patches).
        r: side of the square structuring element K_rxr [px, odd]; removes a (r-1)/2 px band.
        k: side of the depth patches N_p, N_q [px, odd, >= 3]; keep k <= r so patches at
            stable points stay inside the object.
        tau: consensus threshold on the exact Spearman gamma (anchor iff gamma > tau) [-].
        lambda1: weight of the global term [1/px].
        lambda2: weight of the anchor term [-].
        lambda_mask: weight lambda_m of L_mask in the returned loss [-].
        lambda_geo: weight lambda_g of L_geo in the returned loss [-].
        temperature: soft-rank temperature, in units of the patch's depth std [-].
        stable_region: "eroded" (default, the stated intent) or "paper_literal" (top-hat).
        stable_on: which mask defines M_stable and which point must lie in it: "render"
            (p_i in the rendered mask's stable region, literal), "gt" (q_i in M_gt's) or "both".
        alpha_threshold: rendered alpha above which a pixel is in the rendered mask [-].
        mask_reduction: "mean" or "sum" over pixels for L_mask.
        global_reduction: "norm" (paper, Frobenius of [M,2]), "mean" (per-match distance [px]) or
            "mean_sq" (mean squared per-match distance [px^2]).
        anchor_reduction: "sum" (paper) or "mean" over anchors.
        global_gradient: "material" (the global term's gradient moves the material seen at p_i:
            compositing weights held) or "full" (the rasterizer's full derivative, ~0 on dense splats).
        global_max_px: matches whose residual |P_render - P_gt| exceeds this are left out of the
            global term [px]; 0 keeps all (paper).
    """

    # which terms run is the method's declaration (gca.train.methods.TERMS -> Method.rdga_switches), not a knob
    enabled: bool = dataclasses.field(default=True, metadata=NOT_A_PARAM)
    use_global: bool = dataclasses.field(default=True, metadata=NOT_A_PARAM)
    use_anchor: bool = dataclasses.field(default=True, metadata=NOT_A_PARAM)
    depth_term: str = dataclasses.field(default="rank", metadata=NOT_A_PARAM)
    r: int = 9
    k: int = 7
    tau: float = 0.5
    # lambda_1, lambda_2, lambda_m: tuned on the calibration scenes (tuning/record.json, GCA trial 4; paper-literal
    # 0.01, 0.01, 1.0 before): params.yaml holds the same (test_pipeline_schema)
    lambda1: float = 0.22769935911115308
    lambda2: float = 3.2485386221615973
    lambda_mask: float = 1.5626689207170845
    lambda_geo: float = 1.0
    temperature: float = 0.1
    stable_region: str = "eroded"
    stable_on: str = "render"
    alpha_threshold: float = 0.5
    mask_reduction: str = "sum"
    global_reduction: str = "norm"
    anchor_reduction: str = "sum"
    global_gradient: str = "material"
    global_max_px: float = 0.0

    def __post_init__(self) -> None:
        choices = {"depth_term": DEPTH_TERMS, "stable_region": STABLE_MODES, "stable_on": STABLE_ON,
                   "mask_reduction": ("mean", "sum"), "global_reduction": ("norm", "mean", "mean_sq"),
                   "anchor_reduction": ("sum", "mean"), "global_gradient": GLOBAL_GRADIENTS}
        for name, allowed in choices.items():
            if getattr(self, name) not in allowed:
                raise ValueError(f"{_WHERE}: RDGAConfig.{name}={getattr(self, name)!r} not in {allowed}")
        if self.r < 1 or self.r % 2 == 0:
            raise ValueError(f"{_WHERE}: RDGAConfig.r must be an odd integer >= 1, got {self.r}")
        if self.k < 3 or self.k % 2 == 0:
            raise ValueError(f"{_WHERE}: RDGAConfig.k must be an odd integer >= 3, got {self.k}")
        if not self.global_max_px >= 0:
            raise ValueError(f"{_WHERE}: RDGAConfig.global_max_px must be >= 0 [px] (0 = off), got {self.global_max_px}")
        if not -1.0 <= self.tau < 1.0:
            raise ValueError(f"{_WHERE}: RDGAConfig.tau must lie in [-1, 1), got {self.tau}")
        if not self.temperature > 0:
            raise ValueError(f"{_WHERE}: RDGAConfig.temperature must be > 0, got {self.temperature}")


def mask_loss(alpha: torch.Tensor, gt_mask: torch.Tensor, reduction: str = "mean") -> torch.Tensor:
    """Silhouette loss ``(M_render - M_gt)^2`` over pixels, per frame.

    Args:
        alpha: rendered soft silhouette M_render [..., H, W] in [0, 1] (leading dims: frames).
        gt_mask: GT mask M_gt, alpha's shape (bool or {0, 1}).
        reduction: "mean" (default; resolution independent) or "sum" (the paper's ||.||_2^2).

    Returns:
        the loss [...] (a scalar for one [H, W] frame), differentiable w.r.t. ``alpha``.
    """
    if alpha.ndim < 2 or alpha.shape != gt_mask.shape:
        raise ValueError(f"{_WHERE}: mask_loss needs alpha and gt_mask of equal shape [..., H, W], got "
                         f"{tuple(alpha.shape)} and {tuple(gt_mask.shape)}")
    sq = (alpha - gt_mask.to(alpha.dtype)) ** 2
    return sq.mean((-2, -1)) if reduction == "mean" else sq.sum((-2, -1))


def stable_region(mask: torch.Tensor, r: int, mode: str = "eroded") -> torch.Tensor:
    """The stable interior region M_stable of a binary mask (see the module docstring).

    Args:
        mask: object mask M [..., H, W] (bool or {0, 1}; leading dims: frames, each its own mask).
        r: side of the square structuring element K_rxr [px].
        mode: "eroded" (M erode K: the mask minus a (r-1)/2 px boundary band) or
            "paper_literal" (M minus opening(M, K): the white top-hat, thin protrusions only).

    Returns:
        M_stable, mask's shape, bool.
    """
    if mask.ndim < 2:
        raise ValueError(f"{_WHERE}: stable_region needs a [..., H, W] mask, got shape {tuple(mask.shape)}")
    if mode not in STABLE_MODES:
        raise ValueError(f"{_WHERE}: stable_region mode={mode!r} not in {STABLE_MODES}")
    m = (mask > 0.5).to(torch.float32).reshape(-1, 1, *mask.shape[-2:])
    eroded = _window_max(-m, r).neg()  # erosion: the window's min
    out = eroded if mode == "eroded" else m - _window_max(eroded, r, reflected=True)  # opening: erosion, dilation
    return out.reshape(mask.shape) > 0.5


def _window_max(x: torch.Tensor, r: int, reflected: bool = False) -> torch.Tensor:
    """Max of ``x`` [B, 1, H, W] over the r x r window that puts its cell (r // 2, r // 2) on each pixel (``reflected``:
    the window reflected through that pixel, as a dilation's in Minkowski's convention; the same window for odd r), the
    pixels outside the image left out: a geodesic erosion or dilation by a flat r x r square (equal to scipy.ndimage's
    for every r and to kornia.morphology's, which it replaces here, for odd r; tested), in one pooling where kornia's
    ``unfold`` engine takes ~40 launches and its CPU ``shift`` engine ~1500, for every training frame (NOTES s39)."""
    a, b = r // 2, r - 1 - r // 2  # the window's reach before and after the pixel, per axis
    if reflected:
        a, b = b, a
    return F_nn.max_pool2d(F_nn.pad(x, (a, b, a, b), value=float("-inf")), r, stride=1)


def _pixel_indices(points: torch.Tensor, H: int, W: int, half: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Nearest pixel (col, row) [..., M, 2] of each point [..., M, 2] and whether its (2 half + 1)^2 patch is in bounds
    [..., M]."""
    cols = torch.round(points[..., 0].detach()).long()
    rows = torch.round(points[..., 1].detach()).long()
    inside = (cols >= half) & (cols < W - half) & (rows >= half) & (rows < H - half)
    return torch.stack([cols, rows], -1), inside


def _frames(image: torch.Tensor, points: torch.Tensor, trailing: int) -> tuple[torch.Tensor, torch.Tensor]:
    """``image`` [..., H, W, (C)] (``trailing`` = 2 or 3 dims per frame) and ``points`` [..., M, 2] with the same
    leading (frame) dims as [B, H, W, (C)] and [B, M, 2] (B = 1 for none)."""
    lead = image.shape[:image.ndim - trailing]
    if points.shape[:-2] != lead:
        raise ValueError(f"{_WHERE}: points {tuple(points.shape)} and image {tuple(image.shape)} must have the same "
                         f"leading (frame) dims")
    frames = image.reshape(-1, *image.shape[len(lead):])
    return frames, points.reshape(len(frames), *points.shape[-2:])


def gather_patches(image: torch.Tensor, points: torch.Tensor, k: int) -> tuple[torch.Tensor, torch.Tensor]:
    """The k x k patches of ``image`` centred at the nearest pixel of each point, frame by frame.

    Args:
        image: [..., H, W] (gradients flow to it; leading dims: frames).
        points: [..., M, 2] pixel coordinates (x, y), array-index convention, in the frame of the same leading index.
        k: odd patch side [px].

    Returns:
        patches [..., M, k*k] (row-major; clamped into the image for out-of-bounds points) and inside [..., M] bool.

    One ``index_select`` of the flattened frames (its backward one ``index_add_``): advanced indexing
    ``frames[b, rows, cols]`` gave the same values, but its backward (a sorted, deterministic ``index_put_``) cost
    ~0.54 ms a call on the H200, 10 calls a duck iteration (NOTES session 57). ``index_add_`` sums a pixel's
    overlapping patch entries with atomics on CUDA: the same gradient to float rounding, in an order that varies.
    """
    H, W = image.shape[-2:]
    if H < k or W < k:  # a clamped patch would start before the frame (the flat index: in the previous one)
        raise ValueError(f"{_WHERE}: {k} x {k} patches need an image of at least {k} x {k} pixels, got {H} x {W}")
    frames, pts = _frames(image, points, 2)
    half = k // 2
    pix, inside = _pixel_indices(pts, H, W, half)  # [B, M, 2], [B, M]
    offsets = torch.arange(-half, half + 1, device=image.device)
    cols = pix[..., 0].clamp(half, W - 1 - half)[..., None, None] + offsets  # [B, M, 1, k]
    rows = pix[..., 1].clamp(half, H - 1 - half)[..., None, None] + offsets[:, None]  # [B, M, k, 1]
    b = torch.arange(frames.shape[0], device=image.device)[:, None, None, None]
    flat = ((b * H + rows) * W + cols).reshape(-1)  # [B M k k] indices into the frames' pixels
    patches = frames.reshape(-1).index_select(0, flat)
    return patches.reshape(*points.shape[:-1], k * k), inside.reshape(points.shape[:-1])


def _lookup(mask: torch.Tensor, points: torch.Tensor) -> torch.Tensor:
    """Value of a bool mask [..., H, W] at the nearest pixel of each point [..., M, 2] (same leading dims) [..., M];
    False outside."""
    H, W = mask.shape[-2:]
    frames, pts = _frames(mask, points, 2)
    pix, inside = _pixel_indices(pts, H, W, 0)
    b = torch.arange(frames.shape[0], device=mask.device)[:, None]
    vals = frames[b, pix[..., 1].clamp(0, H - 1), pix[..., 0].clamp(0, W - 1)]
    return (vals & inside).reshape(points.shape[:-1])


def bilinear_sample(image: torch.Tensor, points: torch.Tensor) -> torch.Tensor:
    """Bilinear samples [..., M, C] of [..., H, W, C] images at points [..., M, 2] (x, y), array-index convention
    (leading dims: frames, each sampled at its own points)."""
    H, W, C = image.shape[-3:]
    frames, pts = _frames(image, points, 3)
    gx = 2.0 * pts[..., 0] / max(W - 1, 1) - 1.0
    gy = 2.0 * pts[..., 1] / max(H - 1, 1) - 1.0
    grid = torch.stack([gx, gy], -1).to(image.dtype)[:, None]  # [B, 1, M, 2]
    out = F_nn.grid_sample(frames.permute(0, 3, 1, 2), grid, mode="bilinear", align_corners=True)  # [B, C, 1, M]
    return out[:, :, 0, :].transpose(1, 2).reshape(*points.shape[:-1], C)


def sample_unpremultiplied(image: torch.Tensor, alpha: torch.Tensor, p: torch.Tensor) -> torch.Tensor:
    """An alpha-premultiplied image [..., H, W, C] (zero background) bilinearly sampled at points [..., M, 2]
    (array-index convention) and divided by the alpha [..., H, W] sampled there: the composited value [..., M, C] (a
    position image: the surface point seen at p)."""
    C = image.shape[-1]
    sampled = bilinear_sample(torch.cat([image, alpha[..., None]], -1), p)
    return sampled[..., :C] / sampled[..., C:].clamp_min(1e-6)


def render_points(pos_image: torch.Tensor, alpha: torch.Tensor, p: torch.Tensor,
                  K: torch.Tensor | None = None) -> torch.Tensor:
    """P_render: where the surface seen at p projects, from a premultiplied position image.

    Args:
        pos_image: alpha-premultiplied rendered positions (zero background) [..., H, W, C]: C = 2 holds
            the projected Gaussian centres (u, v) in the renderer's image convention (pixel
            centres at i + 0.5); C = 3 holds camera-frame 3D centres (x, y, z) and needs ``K``.
            Leading dims: frames (each with its own alpha and points).
        alpha: rendered alpha [..., H, W].
        p: [..., M, 2] matched points in the rendered image (array-index convention).
        K: intrinsics [3, 3] [px], required when C = 3.

    Returns:
        P_render [..., M, 2] in the array-index convention, differentiable w.r.t. ``pos_image``/``alpha``.
    """
    C = pos_image.shape[-1]
    if pos_image.ndim < 3 or pos_image.shape[:-1] != alpha.shape or C not in (2, 3):
        raise ValueError(f"{_WHERE}: pos_image must be [..., H, W, 2|3] matching alpha {tuple(alpha.shape)}, "
                         f"got {tuple(pos_image.shape)}")
    X = sample_unpremultiplied(pos_image, alpha, p)
    if C == 3:
        if K is None:
            raise ValueError(f"{_WHERE}: a 3-channel (camera-frame xyz) pos_image needs the intrinsics K")
        K = K.to(X)
        uv = (X @ K.T)
        X = uv[..., :2] / uv[..., 2:].clamp_min(1e-9)
    return X - 0.5  # renderer convention (centre i + 0.5) -> array-index convention (centre i)


def global_term(P_render: torch.Tensor, P_gt: torch.Tensor, reduction: str = "norm",
                use: torch.Tensor | None = None) -> torch.Tensor:
    """Global alignment ``||P_render - P_gt||_2`` [px] of matched point sets [..., M, 2], per set [...] (leading
    dims: frames).

    ``reduction="norm"`` is the paper's norm of the whole [M, 2] difference; ``"mean"`` the mean
    per-match Euclidean distance; ``"mean_sq"`` the mean squared one [px^2]. Zero (with grad) when M = 0.
    ``use`` [..., M] bool: only those matches count (the others' residuals are held at zero, no gradient), as if the
    sets were ``P_render[use], P_gt[use]``, without reading the device (equal to rounding; tested).
    """
    P_gt = P_gt.to(P_render)  # itself when dtype and device match already
    if use is None:
        use = torch.ones(P_render.shape[:-1], dtype=torch.bool, device=P_render.device)
    diff = torch.where(use[..., None], P_render, P_gt) - P_gt  # zero where unused
    n = use.sum(-1)
    sq = (diff ** 2).sum(-1)  # [..., M]
    if reduction == "norm":
        value = torch.sqrt(sq.sum(-1) + 1e-12)
    elif reduction == "mean_sq":
        value = sq.sum(-1) / n.clamp_min(1)
    else:
        value = torch.where(use, torch.sqrt(sq + 1e-12), 0.0).sum(-1) / n.clamp_min(1)
    return torch.where(n > 0, value, diff.sum((-2, -1)) * 0.0)


def _check_inputs(depth, alpha, gt_mask, est_depth, p, q, valid=None) -> None:
    shapes = {"render depth": depth.shape, "render alpha": alpha.shape,
              "gt_mask": gt_mask.shape, "est_depth": est_depth.shape}
    if depth.ndim != 3 or len(set(shapes.values())) != 1:
        raise ValueError(f"{_WHERE}: all maps must be [T, H, W] ([H, W] for one frame) of one size, got "
                         + ", ".join(f"{k} {tuple(v)}" for k, v in shapes.items()))
    if p.ndim != 3 or p.shape[-1] != 2 or p.shape != q.shape or len(p) != len(depth):
        raise ValueError(f"{_WHERE}: p and q must both be [T, M, 2] ([M, 2] for one frame) with the maps' T = "
                         f"{len(depth)}, got {tuple(p.shape)} and {tuple(q.shape)}")
    if valid is not None and valid.shape != p.shape[:-1]:
        raise ValueError(f"{_WHERE}: valid must be [T, M] = {tuple(p.shape[:-1])}, got {tuple(valid.shape)}")


def stable_matches(alpha: torch.Tensor, gt_mask: torch.Tensor, p: torch.Tensor, q: torch.Tensor,
                   cfg: RDGAConfig) -> torch.Tensor:
    """Which matches lie in M_stable (per ``cfg.stable_on``) with both k x k patches in bounds.

    Args:
        alpha, gt_mask: [..., H, W] (leading dims: frames); p, q: [..., M, 2].

    Returns:
        stable [..., M] bool.
    """
    H, W = alpha.shape[-2:]
    keep = torch.ones(p.shape[:-1], dtype=torch.bool, device=p.device)
    if cfg.stable_on in ("render", "both"):
        keep &= _lookup(stable_region(alpha.detach() > cfg.alpha_threshold, cfg.r, cfg.stable_region), p)
    if cfg.stable_on in ("gt", "both"):
        keep &= _lookup(stable_region(gt_mask > 0.5, cfg.r, cfg.stable_region), q)
    half = cfg.k // 2
    keep &= _pixel_indices(p, H, W, half)[1] & _pixel_indices(q, H, W, half)[1]
    return keep


def _per_row(fn, *patches: torch.Tensor) -> torch.Tensor:
    """``fn`` of [R, n] patch rows applied to patches [..., M, n]: [..., M] (the softrank functions take rows)."""
    n = patches[0].shape[-1]
    return fn(*(x.reshape(-1, n) for x in patches)).reshape(patches[0].shape[:-1])


def anchor_term(depth: torch.Tensor, est_depth: torch.Tensor, p: torch.Tensor, q: torch.Tensor,
                stable: torch.Tensor, cfg: RDGAConfig, checks: list | None = None) -> tuple[torch.Tensor, dict]:
    """Anchor-level supervision ``sum_{i in A} (-gamma_i)`` (or its L1 ablation), per frame.

    Args:
        depth: rendered depth D_render [..., H, W] (gradients flow to it; leading dims: frames).
        est_depth: estimated relative depth D_gt [..., H, W] (a fixed target).
        p: [..., M, 2] points in the render; q: [..., M, 2] points in the GT frame.
        stable: [..., M] bool, from :func:`stable_matches`.
        cfg: the RDGA config.
        checks: None: the patches' finiteness is checked here (one read of the device) and the stats are floats;
            a list: the checks are appended to it for the caller to :func:`judge` once (a training iteration, all
            its frames) and the stats stay tensors, so nothing here waits for the device.

    Returns:
        (term [...], stats) with stats [...] n_stable, n_anchors, mean_gamma (exact, over stable matches with
        non-constant patches) and mean_gamma_anchor.

    Every match is carried with 0/1 weights (its patches gathered, its gamma computed, the sums over the selected
    ones), not selected by boolean indexing, whose sizes the host would have to read; equal to the selected
    computation to rounding (tested).
    """
    deferred = [] if checks is None else checks
    N_p, _ = gather_patches(depth, p, cfg.k)  # [..., M, k^2]
    N_q, _ = gather_patches(est_depth, q, cfg.k)
    rows = stable[..., None]
    n_stable = stable.sum(-1)
    deferred.append((FloatingPointError, "rendered depth is non-finite in {} of {} anchor patches",
                     ((~torch.isfinite(N_p)) & rows).any(-1).sum(), n_stable.sum()))
    deferred.append((ValueError, "est_depth is non-finite in {} of {} patches",
                     ((~torch.isfinite(N_q)) & rows).any(-1).sum(), n_stable.sum()))
    matches = N_p.numel() > 0  # gamma undefined on constant patches (no match: no std to take; torch warns on none)
    varied = stable & (N_p.detach().std(-1) > 0) & (N_q.std(-1) > 0) if matches else stable
    gamma = torch.where(varied, _per_row(spearman_exact, N_p, N_q), 0.0) if matches else N_p.new_zeros(stable.shape)
    anchors = varied & (gamma > cfg.tau)
    n_anchors = anchors.sum(-1)
    stats = {"n_stable": n_stable, "n_anchors": n_anchors,
             "mean_gamma": gamma.sum(-1) / varied.sum(-1).clamp_min(1),
             "mean_gamma_anchor": torch.where(anchors, gamma, 0.0).sum(-1) / n_anchors.clamp_min(1)}
    sel = anchors[..., None]  # the other rows: constant zeros (no gradient, finite whatever the render holds there)
    X_p, X_q = torch.where(sel, N_p, 0.0), torch.where(sel, N_q, 0.0)
    if cfg.depth_term == "rank":
        per_anchor = -_per_row(lambda x, y: spearman_soft(x, y, cfg.temperature), X_p, X_q) if matches \
            else N_p.new_zeros(stable.shape)
    else:
        per_anchor = (X_p - X_q).abs().mean(-1)
    total = torch.where(anchors, per_anchor, 0.0).sum(-1)
    term = total if cfg.anchor_reduction == "sum" else total / n_anchors.clamp_min(1)
    if checks is None:
        judge(deferred)
        stats = _floats(stats)
    return term, stats


def judge(checks: list) -> None:
    """Raise the first failed check of ``checks`` (entries ``(error type, message with two {}, bad count [],
    total []`` as tensors, from :func:`rdga_frames` / :func:`anchor_term`), reading all their counts in one transfer.
    The counts are over a call's frames (a training chunk), the anchor patches' checks before the loss's: a chunk with
    a non-finite estimate in one frame and a non-finite loss in another raises the estimate's error."""
    if not checks:
        return
    counts = torch.stack([torch.stack([bad.double(), total.double()]) for _, _, bad, total in checks]).tolist()
    for (kind, what, _, _), (bad, total) in zip(checks, counts):
        if bad:
            raise kind(f"{_WHERE}: {what.format(int(bad), int(total))}")


def _floats(stats: dict) -> dict:
    """The stats' tensors (all of one shape: [] or [T] per frame) as floats (lists of T), read in one transfer."""
    keys = [k for k, v in stats.items() if isinstance(v, torch.Tensor)]
    read = dict(zip(keys, torch.stack([stats[k].detach().double().reshape(-1) for k in keys]).tolist())) if keys else {}

    def value(v, got):
        got = got if v.is_floating_point() else [int(x) for x in got]
        return got if v.ndim else got[0]
    return {k: (v if k not in read else value(v, read[k])) for k, v in stats.items()}


def position_colors(xyz: torch.Tensor, gradient: str = "material") -> torch.Tensor:
    """Extra colour channels to composite for the position image: [(T,) G, 3] positions -> [(T,) G, 3] ("full")
    or [(T,) G, 6] ("material": the positions and a detached copy, see :func:`position_image`)."""
    if gradient not in GLOBAL_GRADIENTS:
        raise ValueError(f"{_WHERE}: global_gradient={gradient!r} not in {GLOBAL_GRADIENTS}")
    return xyz if gradient == "full" else torch.cat([xyz, xyz.detach()], -1)


def position_image(channels: torch.Tensor, gradient: str = "material") -> torch.Tensor:
    """The premultiplied position image [(T,) H, W, 3] from the channels of :func:`position_colors` [(T,) H, W, 3|6].

    "material": ``sum w x`` minus ``sum w x.detach()`` (the weights' part of the derivative) plus its
    value: the value is ``sum w x``, the gradient ``sum w dx`` (compositing weights held).
    """
    if gradient == "full":
        return channels
    pos, pos_weights = channels[..., :3], channels[..., 3:]
    return pos - pos_weights + pos_weights.detach()


def _global_on_object(alpha, gt_mask, p, q, cfg, pos_image, K, valid) -> tuple[torch.Tensor, torch.Tensor]:
    """Global term over matches on the object in both frames (and within ``global_max_px`` of their render point),
    per frame: (term [T], number of matches used [T]), every match carried with a 0/1 weight (no read of the
    device); [T, H, W] maps, [T, M, 2] points, ``valid`` [T, M] or None."""
    if pos_image is None:
        raise ValueError(f"{_WHERE}: use_global=True needs pos_image (rendered positions, see render_points)")
    use = _lookup(alpha.detach() > cfg.alpha_threshold, p) & _lookup(gt_mask, q)  # on the object in both frames
    if valid is not None:
        use = use & valid
    held = alpha.detach() if cfg.global_gradient == "material" else alpha  # the un-premultiplying weights
    P_render = render_points(pos_image, held, p, K)
    P_gt = q.to(dtype=P_render.dtype)  # q is on the render's device already
    if cfg.global_max_px > 0:  # truncated: a wrong match's residual would set the norm's direction
        use = use & ((P_render.detach() - P_gt).norm(dim=-1) <= cfg.global_max_px)
    return global_term(P_render, P_gt, cfg.global_reduction, use=use), use.sum(-1)


def _as_tensor(x: Any, like: torch.Tensor) -> torch.Tensor:
    if isinstance(x, np.ndarray):
        x = torch.from_numpy(np.ascontiguousarray(x))
    dtype = like.dtype if x.dtype.is_floating_point else x.dtype
    return x if (x.device, x.dtype) == (like.device, dtype) else x.to(device=like.device, dtype=dtype)


def rdga_loss(render_out: Mapping[str, torch.Tensor], gt_mask: torch.Tensor, est_depth: torch.Tensor,
              p: torch.Tensor, q: torch.Tensor, cfg: RDGAConfig, pos_image: torch.Tensor | None = None,
              K: torch.Tensor | None = None, terms: dict | None = None, checks: list | None = None
              ) -> tuple[torch.Tensor, dict]:
    """RDGA loss of one frame: ``lambda_mask * L_mask + lambda_geo * L_geo`` (module docstring): :func:`rdga_frames`
    of a one-frame batch.

    Args:
        render_out: renderer output with "alpha" [H, W] and "depth" [H, W].
        gt_mask: M_gt [H, W] (bool or {0, 1}); numpy accepted.
        est_depth: estimated relative depth of the GT frame [H, W]; numpy accepted.
        p: matched points in the render [M, 2] (x, y), array-index convention; numpy accepted.
        q: their matches in the GT frame [M, 2].
        cfg, pos_image ([H, W, 2|3]), K, terms, checks: as :func:`rdga_frames`.

    Returns:
        (loss scalar, stats) with stats n_matches, n_global, n_stable, n_anchors, mean_gamma,
        mean_gamma_anchor, l_mask, l_global, l_anchor (for logging: floats, or tensors [] with ``checks``).
    """
    alpha, depth = render_out["alpha"], render_out["depth"]
    p, q = _as_tensor(p, depth).reshape(-1, 2), _as_tensor(q, depth).reshape(-1, 2)
    frame_terms = None if terms is None else {}
    loss, stats = rdga_frames(alpha[None], depth[None], _as_tensor(gt_mask, alpha)[None],
                              _as_tensor(est_depth, depth)[None], p[None], q[None], cfg,
                              pos_image=None if pos_image is None else pos_image[None], K=K, terms=frame_terms,
                              checks=checks)
    for key, value in (frame_terms or {}).items():
        terms[key] = value[0]
    stats = {k: v[0] if isinstance(v, torch.Tensor) else v for k, v in stats.items()}
    stats["n_matches"] = len(p)
    return loss[0], (stats if checks is not None else _floats(stats))


def rdga_frames(alpha: torch.Tensor, depth: torch.Tensor, gt_mask: torch.Tensor, est_depth: torch.Tensor,
                p: torch.Tensor, q: torch.Tensor, cfg: RDGAConfig, pos_image: torch.Tensor | None = None,
                K: torch.Tensor | None = None, valid: torch.Tensor | None = None, terms: dict | None = None,
                checks: list | None = None) -> tuple[torch.Tensor, dict]:
    """RDGA losses of T frames at once, ``lambda_mask * L_mask + lambda_geo * L_geo`` per frame (module docstring):
    one call's launches for all the frames of a training iteration where frame by frame took T times as many (the
    host's time per iteration, NOTES session 40). Equal to :func:`rdga_loss` frame by frame, to rounding (tested).

    Args:
        alpha, depth: the renders' alpha M_render and depth [T, H, W].
        gt_mask: M_gt [T, H, W] (bool or {0, 1}); est_depth: the frames' estimated relative depth [T, H, W].
        p: matched points in the renders [T, M, 2] (x, y), array-index convention; q: their matches in the frames
            [T, M, 2]. A frame with fewer matches is padded; ``valid`` [T, M] bool says which rows are matches
            (None: all).
        cfg: RDGA config (ablation switches included).
        pos_image: premultiplied position images [T, H, W, 2|3] (see :func:`render_points`); needed when the global
            term is on.
        K: intrinsics [3, 3] [px] (one camera) for a 3-channel ``pos_image``.
        terms: when given, filled with each weighted term's per-frame tensor [T] (with its graph), keyed as
            ``gca.train.methods.TERMS``: ``silhouette`` (lambda_m L_mask), ``global`` (lambda_g lambda_1 L_global),
            ``anchor`` or ``anchor_l1`` (lambda_g lambda_2 L_anchor); they sum to the loss.
        checks: None: the finiteness checks (the anchor patches, the loss) are read here and raise at once (one read
            of the device); a list: the checks are appended for the caller to :func:`judge` once per iteration (a
            training iteration, whose host work then never waits for the device: NOTES session 32).

    Returns:
        (loss [T], stats) with per-frame tensors [T] n_matches, n_global, n_stable, n_anchors, mean_gamma,
        mean_gamma_anchor, l_mask, l_global, l_anchor (floats 0 for a term that is off).
    """
    gt_mask = gt_mask > 0.5
    _check_inputs(depth, alpha, gt_mask, est_depth, p, q, valid)
    deferred = [] if checks is None else checks
    l_mask = mask_loss(alpha, gt_mask, cfg.mask_reduction)  # [T]
    n_matches = torch.full(p.shape[:1], p.shape[1], device=p.device) if valid is None else valid.sum(-1)
    stats: dict[str, Any] = {"n_matches": n_matches, "n_global": 0, "n_stable": 0, "n_anchors": 0,
                             "mean_gamma": 0.0, "mean_gamma_anchor": 0.0, "l_global": 0.0, "l_anchor": 0.0}
    l_geo = depth.sum((-2, -1)) * 0.0
    if cfg.enabled and cfg.use_global:
        l_global, n_global = _global_on_object(alpha, gt_mask, p, q, cfg, pos_image, K, valid)
        stats.update(n_global=n_global, l_global=l_global.detach())
        l_geo = l_geo + cfg.lambda1 * l_global
    if cfg.enabled and cfg.use_anchor:
        stable = stable_matches(alpha, gt_mask, p, q, cfg)
        if valid is not None:
            stable = stable & valid
        l_anchor, anchor_stats = anchor_term(depth, est_depth, p, q, stable, cfg, checks=deferred)
        stats.update(anchor_stats, l_anchor=l_anchor.detach())
        l_geo = l_geo + cfg.lambda2 * l_anchor
    loss = cfg.lambda_mask * l_mask + cfg.lambda_geo * l_geo
    if terms is not None:
        terms["silhouette"] = cfg.lambda_mask * l_mask
        if cfg.enabled and cfg.use_global:
            terms["global"] = cfg.lambda_geo * cfg.lambda1 * l_global
        if cfg.enabled and cfg.use_anchor:
            terms["anchor_l1" if cfg.depth_term == "l1" else "anchor"] = cfg.lambda_geo * cfg.lambda2 * l_anchor
    deferred.append((FloatingPointError, "non-finite RDGA loss in {} of {} frames", (~torch.isfinite(loss)).sum(),
                     loss.new_full((), len(loss), dtype=torch.long)))
    stats["l_mask"] = l_mask.detach()
    if checks is None:
        judge(deferred)
    return loss, stats


__all__ = ["RDGAConfig", "mask_loss", "stable_region", "gather_patches", "bilinear_sample", "render_points", "judge",
           "global_term", "stable_matches", "anchor_term", "rdga_loss", "rdga_frames"]
