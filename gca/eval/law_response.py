"""Law-level response error on held-out deformation-gradient sweeps.

Two sweeps, never seen in training (they are homogeneous deformations, not rollout states):

- ``"uniaxial"``: F = diag(s, 1, 1), stretch s in [0.8, 1.2] (20 % compression to 20 % extension).
- ``"shear"``:    F = I + gamma e_x e_y^T, engineering shear gamma in [0, 0.3].

The error of a law against a reference law over a sweep is the relative Frobenius error of the
stacked responses, in percent:

    err = 100 * sqrt( sum_i ||tau_i - tau_ref_i||_F^2 / sum_i ||tau_ref_i||_F^2 )

(a sweep-level ratio, so the stress-free rest point F = I does not divide by zero). A law scaled
by 1.1 therefore has error exactly 10 %. Laws are modules or callables ``F[N,3,3] -> tau[N,3,3]``
(Kirchhoff stress, Pa); the same formula applies to plasticity maps ``F_trial -> F_e``.
"""

from __future__ import annotations

from typing import Callable

import torch

SWEEPS = {"uniaxial": (0.8, 1.2), "shear": (0.0, 0.3)}  # strain-parameter range of each sweep


def deformation_sweep(kind: str = "uniaxial", n: int = 41, dtype: torch.dtype = torch.float32,
                      device: str | torch.device = "cpu") -> tuple[torch.Tensor, torch.Tensor]:
    """Deformation gradients of a held-out sweep.

    Args:
        kind: ``"uniaxial"`` (stretch s) or ``"shear"`` (shear gamma).
        n: number of samples (>= 2), evenly spaced over the range in :data:`SWEEPS`.
        dtype, device: of the returned tensors.

    Returns:
        ``(strains [n], F [n, 3, 3])``: the sweep parameter (s or gamma, dimensionless) and F.
    """
    if kind not in SWEEPS:
        raise ValueError(f"gca/eval/law_response.py: unknown sweep {kind!r}; expected one of {list(SWEEPS)}")
    if n < 2:
        raise ValueError(f"gca/eval/law_response.py: a sweep needs n >= 2 samples, got {n}")
    lo, hi = SWEEPS[kind]
    strains = torch.linspace(lo, hi, n, dtype=dtype, device=device)
    F = torch.eye(3, dtype=dtype, device=device).repeat(n, 1, 1)
    if kind == "uniaxial":
        F[:, 0, 0] = strains
    else:
        F[:, 0, 1] = strains
    return strains, F


@torch.no_grad()
def law_response_curve(law: Callable[[torch.Tensor], torch.Tensor], kind: str = "uniaxial",
                       n: int = 41) -> dict[str, torch.Tensor]:
    """Response of one law over a sweep, for plotting.

    Args:
        law: ``F[n, 3, 3] -> tau[n, 3, 3]``.
        kind: sweep name (see :func:`deformation_sweep`).
        n: number of samples.

    Returns:
        ``{"strain": [n], "F": [n, 3, 3], "tau": [n, 3, 3], "component": [n]}`` where ``component``
        is tau_xx for the uniaxial sweep and tau_xy for the shear sweep (the plotted curve).
    """
    strains, F = deformation_sweep(kind, n)
    tau = law(F)
    if tau.shape != F.shape or not torch.isfinite(tau).all():
        raise ValueError(f"gca/eval/law_response.py: law returned {tuple(tau.shape)} "
                         f"(finite={bool(torch.isfinite(tau).all())}) for F {tuple(F.shape)}")
    component = tau[:, 0, 0] if kind == "uniaxial" else tau[:, 0, 1]
    return {"strain": strains, "F": F, "tau": tau, "component": component}


def law_response_error(law: Callable[[torch.Tensor], torch.Tensor],
                       reference_law: Callable[[torch.Tensor], torch.Tensor],
                       kind: str = "uniaxial", n: int = 41) -> float:
    """Relative response error [%] of ``law`` against ``reference_law`` over a held-out sweep.

    Args:
        law: learned law ``F[n, 3, 3] -> tau[n, 3, 3]``.
        reference_law: ground-truth law, same signature.
        kind: ``"uniaxial"`` or ``"shear"`` (see module docstring).
        n: number of samples of the sweep.

    Returns:
        The error in percent (0 for identical laws, 10 for a law scaled by 1.1).
    """
    tau = law_response_curve(law, kind, n)["tau"].double()
    tau_ref = law_response_curve(reference_law, kind, n)["tau"].double()
    denom = tau_ref.square().sum()
    if denom <= 0:
        raise ValueError("gca/eval/law_response.py: the reference law is stress-free over the whole sweep")
    return float(100.0 * ((tau - tau_ref).square().sum() / denom).sqrt())
