"""A quick look at a Gaussian cloud: three orthographic scatter views coloured by the SH0 colour."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from gca.assets.ply import GaussianCloud, opacities, sh0_to_rgb
from gca.io import atomic_path


def write_preview(path: str | os.PathLike, cloud: GaussianCloud, title: str = "", max_points: int = 20000,
                  seed: int = 0) -> Path:
    """Save a PNG with front (x-y), side (z-y) and top (x-z) scatter views (atomic write).

    Args:
        path: destination ``.png``.
        cloud: the Gaussians; at most ``max_points`` random ones are drawn, far ones first.
        title: figure title.
        max_points: subsample size.
        seed: subsampling seed.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rng = np.random.default_rng(seed)
    keep = rng.permutation(cloud.n)[:max_points]
    x = cloud.means[keep]
    rgba = np.concatenate([np.clip(sh0_to_rgb(cloud.sh_dc[keep]), 0, 1), opacities(cloud)[keep, None]], axis=1)
    fig, axes = plt.subplots(1, 3, figsize=(12, 4.2))
    for ax, (a, b, depth, label) in zip(axes, ((0, 1, 2, "front x-y"), (2, 1, 0, "side z-y"), (0, 2, 1, "top x-z"))):
        order = np.argsort(-x[:, depth] if depth != 1 else x[:, depth])  # draw far points first
        ax.scatter(x[order, a], x[order, b], c=rgba[order], s=2, linewidths=0)
        ax.set_aspect("equal")
        ax.set_title(label)
    fig.suptitle(title)
    fig.tight_layout()
    path = Path(path)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=100, format="png")
    plt.close(fig)
    return path
