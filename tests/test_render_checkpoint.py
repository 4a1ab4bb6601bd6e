"""The torch rasterizer's bounded memory (issue 20 item 3): with ``RasterConfig.checkpoint`` a rendered
frame keeps only its inputs for backward and recomputes its per-pixel tensors there.

- gradients identical (bitwise on the CPU) with and without it, over several frames;
- what autograd holds after K frames' forward grows with K by the inputs only: measured with
  ``saved_tensors_hooks`` (bytes of every tensor saved for backward, a deterministic proxy of the
  memory a single backward over all frames needs), against the per-pixel tensors without it.
"""

from __future__ import annotations

import dataclasses
import sys
from pathlib import Path

import torch

from gca.render import RasterConfig, render

sys.path.insert(0, str(Path(__file__).parent))
from test_render_raster import BG, _camera, _scene  # noqa: E402


def _frames(K: int, checkpoint: bool, n: int = 400):
    """K frames of one moving scene (float32); returns (loss, leaves)."""
    means, covs, colors, opac = [t.float().requires_grad_(True) for t in _scene(n, seed=7)]
    cfg = RasterConfig(checkpoint=checkpoint)
    camera = _camera(48, 40)
    loss = 0.0
    for k in range(K):
        shift = torch.tensor([0.01 * k, 0.0, 0.0])
        out = render(means + shift, covs, colors, opac, camera, BG.float(), cfg=cfg)
        loss = loss + (out["rgb"] ** 2).sum() + out["alpha"].sum() + 0.1 * out["depth"].sum()
    return loss, [means, covs, colors, opac]


def _saved_bytes(K: int, checkpoint: bool) -> int:
    total = [0]

    def pack(t):
        total[0] += t.numel() * t.element_size()
        return t

    with torch.autograd.graph.saved_tensors_hooks(pack, lambda t: t):
        loss, _ = _frames(K, checkpoint)
    return total[0]


def test_checkpointed_render_gives_identical_gradients():
    for K in (1, 3):
        (l0, p0), (l1, p1) = _frames(K, False), _frames(K, True)
        assert torch.equal(l0, l1)
        g0, g1 = torch.autograd.grad(l0, p0), torch.autograd.grad(l1, p1)
        for a, b in zip(g0, g1):
            assert torch.equal(a, b)
            assert a.abs().sum() > 0


def test_checkpointed_render_memory_does_not_grow_with_per_pixel_tensors():
    plain = [_saved_bytes(K, False) for K in (1, 4)]
    ckpt = [_saved_bytes(K, True) for K in (1, 4)]
    per_frame_plain = (plain[1] - plain[0]) / 3
    per_frame_ckpt = (ckpt[1] - ckpt[0]) / 3
    assert per_frame_plain > 20 * per_frame_ckpt  # negative control: without it, each frame holds its slabs
    inputs = 400 * (3 + 9 + 3 + 1) * 4
    assert per_frame_ckpt <= 4 * inputs  # with it, about a frame's inputs


def test_no_checkpoint_without_autograd():
    means, covs, colors, opac = [t.float() for t in _scene(50, seed=1)]
    cfg = RasterConfig()
    with torch.no_grad():
        a = render(means, covs, colors, opac, _camera(16, 16), BG.float(), cfg=cfg)
    b = render(means, covs, colors, opac, _camera(16, 16), BG.float(), cfg=dataclasses.replace(cfg, checkpoint=False))
    assert torch.equal(a["rgb"], b["rgb"]) and not a["rgb"].requires_grad
