"""Random deformation gradients and rotations for the law tests (float64 by default)."""

import torch

f64 = torch.float64


def random_F(n: int, seed: int, spread: float = 0.3, dtype=f64) -> torch.Tensor:
    """F = I + spread * N(0, 1) entries [n, 3, 3] (det F > 0 for small spreads, not guaranteed)."""
    g = torch.Generator().manual_seed(seed)
    return torch.eye(3, dtype=dtype) + spread * torch.randn(n, 3, 3, generator=g, dtype=dtype)


def random_rotations(n: int, seed: int, dtype=f64) -> torch.Tensor:
    """Proper rotations [n, 3, 3] from the QR of Gaussian matrices (sign-fixed, det = +1)."""
    g = torch.Generator().manual_seed(seed)
    Q, R = torch.linalg.qr(torch.randn(n, 3, 3, generator=g, dtype=dtype))
    Q = Q * torch.sign(torch.diagonal(R, dim1=1, dim2=2))[:, None, :]
    Q[torch.det(Q) < 0, :, 0] *= -1
    return Q
