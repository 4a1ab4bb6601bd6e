"""Exact and differentiable (soft) ranks and the Spearman rank correlation of depth patches.

RDGA (paper Sec. 3.3) scores a correspondence ``(p_i, q_i)`` by the Spearman rank correlation of
the ``k x k`` rendered-depth patch around ``p_i`` and the estimated-depth patch around ``q_i``::

    gamma = 1 - 6 * sum_j (r_j - s_j)^2 / (n (n^2 - 1)),      n = k^2.

Exact ranks are piecewise constant, so their gradient is zero almost everywhere. For the
anchor-level loss ``-gamma`` we replace the ranks of the *rendered* patch by a pairwise-sigmoid
soft rank (the estimated depth is a fixed target, so its ranks stay exact)::

    r_j(T) = 1/2 + sum_l sigmoid((z_j - z_l) / T),    z = (x - mean(x)) / std(x).

The ``l = j`` term contributes ``sigmoid(0) = 1/2``, so ``r_j(T)`` is the 1-based *average* rank
of ``x_j`` in the limit ``T -> 0`` (ties get the mean of their ranks, like
``scipy.stats.rankdata``), and ``sum_j r_j(T) = n (n + 1) / 2`` exactly for every ``T``.
Standardising by the patch's own std makes ``T`` dimensionless and the soft rank invariant to
positive scale and shift of the rendered depth, like the exact rank. The cost is ``O(n^2)``
per patch (``n = 49`` for ``k = 7``), which is negligible next to rendering.

We chose the pairwise sigmoid over Blondel et al.'s fast soft sort (O(n log n), isotonic
regression) because patches are small, the sigmoid form is a few readable lines of torch, and
its gradients are dense (every pair contributes), which suits a loss on ~50-element patches.
"""

from __future__ import annotations

import torch

_VAR_EPS = 1e-20  # added to a patch's variance before the sqrt [depth units^2]: keeps the
#                   gradient finite on a constant patch (RDGA excludes those from anchors anyway)


def _check_patches(x: torch.Tensor, name: str) -> None:
    if x.ndim != 2:
        raise ValueError(f"gca/align/softrank.py: {name} must be [M, n] patches, got shape {tuple(x.shape)}")
    if x.shape[1] < 2:
        raise ValueError(f"gca/align/softrank.py: {name} needs n >= 2 values per patch, got n={x.shape[1]}")


def exact_rank(x: torch.Tensor) -> torch.Tensor:
    """1-based average ranks along the last axis (ties share the mean of their ranks); no gradient.

    Args:
        x: values [M, n].

    Returns:
        ranks [M, n] in [1, n], same dtype as ``x``, detached.
    """
    _check_patches(x, "x")
    x = x.detach()
    diff = x[:, :, None] - x[:, None, :]  # [M, n, n]: x_j - x_l
    less = (diff > 0).sum(-1).to(x.dtype)
    equal = (diff == 0).sum(-1).to(x.dtype)  # includes l = j
    return less + (equal + 1.0) / 2.0


def soft_rank(x: torch.Tensor, temperature: float) -> torch.Tensor:
    """Pairwise-sigmoid soft ranks of standardised values; tends to :func:`exact_rank` as T -> 0.

    Args:
        x: values [M, n] (any positive scale and shift: they are standardised per row).
        temperature: T > 0, in units of the row's standard deviation.

    Returns:
        soft ranks [M, n], differentiable w.r.t. ``x``; each row sums to n (n + 1) / 2.
    """
    _check_patches(x, "x")
    if not temperature > 0:
        raise ValueError(f"gca/align/softrank.py: temperature must be > 0, got {temperature}")
    std = torch.sqrt(x.var(-1, keepdim=True) + _VAR_EPS)
    z = (x - x.mean(-1, keepdim=True)) / std
    diff = (z[:, :, None] - z[:, None, :]) / temperature  # [M, n, n]
    return 0.5 + torch.sigmoid(diff).sum(-1)


def spearman_from_ranks(r: torch.Tensor, s: torch.Tensor) -> torch.Tensor:
    """Spearman's formula ``1 - 6 sum d^2 / (n (n^2 - 1))`` for rank rows (paper Eq. for gamma_i).

    Args:
        r: ranks [M, n] (exact or soft).
        s: ranks [M, n].

    Returns:
        gamma [M] in [-1, 1] (exactly the Pearson correlation of the ranks when there are no ties).
    """
    if r.shape != s.shape:
        raise ValueError(f"gca/align/softrank.py: rank shapes differ: {tuple(r.shape)} vs {tuple(s.shape)}")
    n = r.shape[-1]
    return 1.0 - 6.0 * ((r - s) ** 2).sum(-1) / (n * (n * n - 1.0))


def spearman_exact(x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    """Exact Spearman gamma of row pairs (average ranks for ties); no gradient.

    Args:
        x: values [M, n].
        y: values [M, n].

    Returns:
        gamma [M].
    """
    return spearman_from_ranks(exact_rank(x), exact_rank(y))


def spearman_soft(x: torch.Tensor, y: torch.Tensor, temperature: float) -> torch.Tensor:
    """Spearman gamma with soft ranks for ``x`` (differentiable) and exact ranks for ``y`` (target).

    Args:
        x: values [M, n] with gradient (rendered depth patches).
        y: values [M, n], a fixed target (estimated depth patches).
        temperature: soft-rank temperature T > 0 (units of the patch std).

    Returns:
        gamma [M], differentiable w.r.t. ``x``; equals :func:`spearman_exact` as T -> 0.
    """
    return spearman_from_ranks(soft_rank(x, temperature), exact_rank(y))
