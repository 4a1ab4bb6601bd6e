"""Batched 3x3 linear algebra shared by the laws, the simulator and the renderer (core layer: imports only torch)."""

from __future__ import annotations

import torch


def det3(F: torch.Tensor) -> torch.Tensor:
    """Determinant by cofactor expansion (a polynomial: smooth, exact 1 at F = I).

    Args:
        F: [N, 3, 3].

    Returns:
        J [N].
    """
    return (F[:, 0, 0] * (F[:, 1, 1] * F[:, 2, 2] - F[:, 1, 2] * F[:, 2, 1])
            - F[:, 0, 1] * (F[:, 1, 0] * F[:, 2, 2] - F[:, 1, 2] * F[:, 2, 0])
            + F[:, 0, 2] * (F[:, 1, 0] * F[:, 2, 1] - F[:, 1, 1] * F[:, 2, 0]))


def bmm3(A: torch.Tensor, B: torch.Tensor) -> torch.Tensor:
    """Batched 3x3 product A B by broadcasting, for [..., 3, 3] operands (any broadcastable batch).

    ``A @ B`` on [N, 3, 3] batches goes to cuBLAS batched GEMM, whose smallest tiles waste ~30x the
    work: ~0.1 ms per product for N = 1e5 on an H100, the largest cost of a neural-law MPM step
    (benchmarks/NOTES.md). Multiply-and-sum over the shared index is two memory-bound elementwise
    kernels (a few microseconds), forward and backward. Same values as ``A @ B`` up to summation order.
    """
    return (A.unsqueeze(-1) * B.unsqueeze(-3)).sum(-2)
