"""Law-level supervised fitting of the neural laws, and the law-level response error.

The prior stage warm-starts the neural networks by regression onto an analytic law before any
trajectory training: sample deformation gradients around the identity, evaluate the analytic law,
and fit. Elasticity is fitted on Kirchhoff stress, plasticity on the return map; both losses are in
network-output units (stress / ``stress_scale``, correction / ``alpha``), so they are O(1).

:func:`response_error` is the evaluation's law-level metric: ||tau - tau_ref||_F / ||tau_ref||_F
over a batch of deformation gradients, and :func:`sweep_response_error` averages it over
uniaxial (stretch and compression) and simple-shear sweeps.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Callable

import torch
from torch import nn

from gca.laws.neural import NeuralElasticity, NeuralPlasticity

Law = Callable[[torch.Tensor], torch.Tensor]  # F [N,3,3] -> tau or F_e [N,3,3]


@dataclasses.dataclass(frozen=True)
class DeformationSampling:
    """Distribution of deformation gradients F = R V diag(sigma) V^T (polar form, det F > 0).

    sigma_i = 1 + c * e_i with e_i ~ U(-compression, stretch) and one magnitude c ~ U(0, 1) per
    sample (so small strains are well represented); V uniform; R about a uniform axis by an angle
    ~ U(0, rotation).
    """

    stretch: float = 0.3  # largest principal stretch sigma - 1 [1]
    compression: float = 0.3  # largest principal compression 1 - sigma [1], < 1
    rotation: float = math.pi  # largest rotation angle of R [rad]

    def __post_init__(self):
        if not (self.stretch >= 0 and 0 <= self.compression < 1 and self.rotation >= 0):
            raise ValueError(f"gca/laws/pretrain.py: DeformationSampling needs stretch >= 0, 0 <= compression < 1, "
                             f"rotation >= 0; got {self}")


@dataclasses.dataclass(frozen=True)
class PretrainConfig:
    """Regression of a neural law onto an analytic one (params ``prior.fit``)."""

    sampling: DeformationSampling = DeformationSampling()  # where F is drawn from
    n_samples: int = 65536  # training-set size {paper: 65536, ci: 2048} [count]
    batch_size: int = 1024  # samples per Adam step [count]
    steps: int = 5000  # Adam steps {paper: 5000, ci: 300} [count]
    lr: float = 3e-3  # initial Adam learning rate, cosine-decayed to lr * lr_final_ratio
    lr_final_ratio: float = 0.01  # final / initial learning rate [1]
    seed: int = 0  # seeds sampling, batching (not the network init)


def random_rotations(n: int, generator: torch.Generator, max_angle: float = math.pi,
                     dtype: torch.dtype = torch.float32) -> torch.Tensor:
    """Rotations about uniform axes by angles ~ U(0, max_angle) (Rodrigues). Returns [n, 3, 3]."""
    axis = torch.randn(n, 3, generator=generator, dtype=dtype)
    axis = axis / axis.norm(dim=1, keepdim=True).clamp(min=1e-12)
    theta = max_angle * torch.rand(n, generator=generator, dtype=dtype)[:, None, None]
    K = torch.zeros(n, 3, 3, dtype=dtype)
    K[:, 0, 1], K[:, 0, 2], K[:, 1, 2] = -axis[:, 2], axis[:, 1], -axis[:, 0]
    K = K - K.transpose(1, 2)
    eye = torch.eye(3, dtype=dtype).expand(n, 3, 3)
    return eye + torch.sin(theta) * K + (1 - torch.cos(theta)) * (K @ K)


def sample_deformations(n: int, cfg: DeformationSampling, generator: torch.Generator,
                        dtype: torch.dtype = torch.float32) -> torch.Tensor:
    """Draw n deformation gradients from ``cfg`` (class docstring). Returns F [n, 3, 3], det F > 0."""
    if n < 1:
        raise ValueError(f"gca/laws/pretrain.py: sample_deformations: n must be >= 1, got {n}")
    e = torch.rand(n, 3, generator=generator, dtype=dtype) * (cfg.stretch + cfg.compression) - cfg.compression
    sigma = 1.0 + torch.rand(n, 1, generator=generator, dtype=dtype) * e
    V = random_rotations(n, generator, math.pi, dtype)
    R = random_rotations(n, generator, cfg.rotation, dtype)
    return R @ (V * sigma[:, None, :]) @ V.transpose(1, 2)


def _cosine_lr(step: int, cfg: PretrainConfig) -> float:
    t = step / max(cfg.steps - 1, 1)
    return cfg.lr * (cfg.lr_final_ratio + (1 - cfg.lr_final_ratio) * 0.5 * (1 + math.cos(math.pi * t)))


def _fit(law: nn.Module, F: torch.Tensor, target: torch.Tensor, unit: float, cfg: PretrainConfig,
         name: str) -> list[float]:
    """Adam on mean ||law(F_b) - target_b||_F^2 / unit^2 over random minibatches; returns the loss history."""
    params = [p for p in law.parameters() if p.requires_grad]
    if not params:
        raise ValueError(f"gca/laws/pretrain.py: {name}: the law has no trainable parameters")
    opt = torch.optim.Adam(params, lr=cfg.lr)
    g = torch.Generator().manual_seed(cfg.seed + 1)
    history = []
    for step in range(cfg.steps):
        idx = torch.randint(0, F.shape[0], (min(cfg.batch_size, F.shape[0]),), generator=g).to(F.device)
        loss = (law(F[idx]) - target[idx]).square().sum(dim=(1, 2)).mean() / unit ** 2
        if not torch.isfinite(loss):
            raise RuntimeError(f"gca/laws/pretrain.py: {name} diverged at step {step}/{cfg.steps}: loss={loss.item()}, "
                               f"last finite loss={history[-1] if history else None}, lr={_cosine_lr(step, cfg)}")
        for group in opt.param_groups:
            group["lr"] = _cosine_lr(step, cfg)
        opt.zero_grad()
        loss.backward()
        opt.step()
        history.append(loss.item())
    return history


def _training_set(law: nn.Module, reference: Law, cfg: PretrainConfig) -> tuple[torch.Tensor, torch.Tensor]:
    dtype, device = next(law.parameters()).dtype, next(law.parameters()).device
    F = sample_deformations(cfg.n_samples, cfg.sampling, torch.Generator().manual_seed(cfg.seed), dtype).to(device)
    with torch.no_grad():
        target = reference(F).to(dtype)
    if target.shape != F.shape or not torch.isfinite(target).all():
        raise ValueError(f"gca/laws/pretrain.py: reference law returned {tuple(target.shape)} with "
                         f"{int((~torch.isfinite(target)).sum())} non-finite entries for F {tuple(F.shape)}")
    return F, target


def fit_elasticity(law: NeuralElasticity, reference: Law, cfg: PretrainConfig) -> list[float]:
    """Regress ``law`` (in place) onto the Kirchhoff stress of ``reference``.

    Args:
        law: neural elasticity (its trainable parameters are optimised).
        reference: F [N,3,3] -> tau [N,3,3] (Pa), e.g. ``CorotatedElasticity(1e5, 0.2)``.
        cfg: sampling and optimisation settings.

    Returns:
        Loss per step: mean ||tau - tau_ref||_F^2 / stress_scale^2.
    """
    F, tau_ref = _training_set(law, reference, cfg)
    return _fit(law, F, tau_ref, law.cfg.stress_scale, cfg, "fit_elasticity")


def fit_plasticity(law: NeuralPlasticity, reference: Law, cfg: PretrainConfig) -> list[float]:
    """Regress ``law`` (in place) onto the return map F_trial -> F_e of ``reference``.

    Returns:
        Loss per step: mean ||F_e - F_e_ref||_F^2 / alpha^2 (network-output units).
    """
    F, F_ref = _training_set(law, reference, cfg)
    return _fit(law, F, F_ref, law.cfg.alpha, cfg, "fit_plasticity")


def response_error(law: Law, reference: Law, Fs: torch.Tensor) -> float:
    """Relative response error ||law(F) - ref(F)||_F / ||ref(F)||_F over the whole batch.

    Args:
        law, reference: F [N,3,3] -> [N,3,3] (stresses, Pa, for elasticities).
        Fs: deformation gradients [N, 3, 3] (not all at rest).

    Returns:
        The relative error [1].
    """
    if Fs.ndim != 3 or Fs.shape[1:] != (3, 3):
        raise ValueError(f"gca/laws/pretrain.py: response_error: Fs must be [N, 3, 3], got {tuple(Fs.shape)}")
    with torch.no_grad():
        out, ref = law(Fs), reference(Fs)
    ref_norm = float(ref.norm())
    if not ref_norm > 0:
        raise ValueError("gca/laws/pretrain.py: response_error: the reference response is zero on Fs "
                         "(all at rest?); the relative error is undefined")
    return float((out - ref).norm()) / ref_norm


def sweep_deformations(max_strain: float = 0.1, n: int = 10,
                       dtype: torch.dtype = torch.float32) -> dict[str, torch.Tensor]:
    """Uniaxial and simple-shear sweeps, each [2n, 3, 3] with strains in [-max, max] (0 excluded).

    uniaxial: F = diag(1 + e, 1, 1); shear: F = I + g e_x e_y^T.
    """
    steps = torch.linspace(max_strain / n, max_strain, n, dtype=dtype)
    strains = torch.cat([-steps.flip(0), steps])
    eye = torch.eye(3, dtype=dtype).expand(2 * n, 3, 3)
    uniaxial, shear = eye.clone(), eye.clone()
    uniaxial[:, 0, 0] += strains
    shear[:, 0, 1] += strains
    return {"uniaxial": uniaxial, "shear": shear}


def sweep_response_error(law: Law, reference: Law, max_strain: float = 0.1, n: int = 10,
                         dtype: torch.dtype = torch.float32) -> dict[str, float]:
    """:func:`response_error` on each sweep of :func:`sweep_deformations`, plus their mean."""
    errors = {name: response_error(law, reference, Fs)
              for name, Fs in sweep_deformations(max_strain, n, dtype).items()}
    errors["mean"] = sum(errors.values()) / len(errors)
    return errors
