"""Constitutive Prior Regularizer (CPR), Algorithm 2 of the paper (section 3.4).

Classical laws act as soft priors on the neural laws. On a fixed random subset S of particles
(|S| = 256, chosen once per run from the seed), each hypothesis H_k is fitted to the neural law's
outputs, its credibility is omega_k = 1 / (Var{Theta_hat_k} + eps), and the residuals

    R_e = lambda_e * sum_k omega_e^k * mean_i ||E_theta(F_e,i) - H_e^k(F_e,i; E[Theta_hat_e^k])||_F^2 / s_e
    R_p = lambda_p * sum_m omega_p^m * mean_i ||P_theta(F_tr,i) - H_p^m(F_tr,i; E[Theta_hat_p^m])||_F^2 / s_p

pull the neural laws towards the credible hypotheses. The mean runs over all N particles (the
algorithm's F_e^t; ``residual_on="subset"`` restricts it to S). Parameters and weights are solved
targets: detached, so the gradient reaches only the neural laws (and F unless ``detach_F``).

Hypotheses (gca.laws, Kirchhoff stress in Pa): H_e = {corotated, stvk, volume, sigma} and
H_p = {identity, sigma, von_mises, drucker_prager}. Parameter solving, all in float64:

- elastic: every H_e is linear in its parameters (mu, lam; volume: lam only), so the least-squares
  fit is the normal equations of the basis responses H(F; 1, 0), H(F; 0, 1), with a tiny ridge.
- von Mises: one parameter, the yield strain k = sigma_y / (2 mu) (all the return map depends on),
  fitted on a log grid over ``yield_strain_range`` refined ``refine_rounds`` times.
- Drucker-Prager: the friction angle phi [deg] on a linear grid (refined likewise); the return map
  also needs lam/mu, taken from the most credible two-parameter elastic fit; cohesion is fixed.
- identity, sigma: no parameter.

Var{Theta_hat} (the paper leaves it open; our definition). S is split into ``n_groups`` fixed
disjoint random groups; each hypothesis is fitted on each group separately, giving estimates
Theta_g. E[Theta_hat] is their mean and the dispersion is the scale-free relative variance

    V_param = sum_j Var_g(Theta_g,j) / max(sum_j mean_g(Theta_g,j)^2, floor)

(population variance over groups; floors: (1e-4)^2 for the yield strain, (1 deg)^2 for phi). A law
that fits exactly gives the same estimate on every group, so V_param = 0. Parameter-free hypotheses
have V_param = 0 whatever their fit, and a law can fit badly yet consistently, so with
``include_fit_residual`` (default) we add the relative misfit on S,
V = V_param + mean_S ||target - H(E[Theta_hat])||^2 / s. An exact fit then has V = 0 and the largest
weight 1/eps; and since V >= misfit, each weighted term omega_k * misfit_k stays below 1.

Normalisation (s_e, s_p, detached, from S): stresses are 1e3-1e5 Pa, so s_e = mean_S ||E_theta(F_e)||^2
(the neural stress energy); plastic maps return F (~ I) but their content is the strain, so
s_p = mean_S ||F_trial - I||^2. A relative mismatch of order 1 thus gives a residual of order 1.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Callable, Optional

import torch

ELASTIC_HYPOTHESES = ("corotated", "stvk", "volume", "sigma")
PLASTIC_HYPOTHESES = ("identity", "sigma", "von_mises", "drucker_prager")
ELASTIC_PARAMS = {"corotated": ("mu", "lam"), "stvk": ("mu", "lam"), "volume": ("lam",), "sigma": ("mu", "lam")}
PLASTIC_PARAMS = {"identity": (), "sigma": (), "von_mises": ("yield_strain",), "drucker_prager": ("phi",)}
_TINY = 1e-30


@dataclasses.dataclass(frozen=True)
class CPRConfig:
    """Knobs of the Constitutive Prior Regularizer (params ``align.cpr``)."""

    subset_size: int = 256  # |S|, particles used for parameter solving (paper: 256) [count]
    n_groups: int = 8  # disjoint groups of S whose estimates give Var{Theta_hat} [count]
    eps: float = 1e-2  # smoothing in omega = 1/(Var + eps) [relative variance, dimensionless]
    elastic: tuple[str, ...] = ELASTIC_HYPOTHESES  # enabled H_e (drop one for the "target removed" test)
    plastic: tuple[str, ...] = PLASTIC_HYPOTHESES  # enabled H_p
    lambda_e: float = 1.0  # weight of R_e in the loss (paper: 1) [dimensionless]
    lambda_p: float = 1.0  # weight of R_p in the loss (paper: 1) [dimensionless]
    include_fit_residual: bool = True  # Var += relative misfit on S (False: parameter dispersion only)
    residual_on: str = "all"  # "all" particles (Algorithm 2) or the "subset" S (cheaper)
    detach_F: bool = True  # stop the CPR gradient at F_e / F_trial (it shapes the laws, not the path)
    refit_every: int = 1  # re-solve parameters and weights every k calls (Algorithm 2: 1) [calls]
    yield_strain_range: tuple[float, float] = (1e-4, 1.0)  # von Mises sigma_y/(2 mu) search [dimensionless]
    friction_angle_range: tuple[float, float] = (0.0, 60.0)  # Drucker-Prager phi search [deg]
    dp_cohesion: float = 0.0  # Drucker-Prager cohesion, fixed (NCLaw sand: 0) [log-strain]
    fallback_poisson: float = 0.2  # nu giving lam/mu for Drucker-Prager when no elastic fit exists
    grid_size: int = 16  # candidates per round of the 1-D plastic fits [count]
    refine_rounds: int = 3  # zoom rounds of the 1-D plastic fits [count]

    def __post_init__(self):
        object.__setattr__(self, "elastic", tuple(self.elastic))
        object.__setattr__(self, "plastic", tuple(self.plastic))
        bad = [h for h in self.elastic if h not in ELASTIC_HYPOTHESES] + \
              [h for h in self.plastic if h not in PLASTIC_HYPOTHESES]
        if bad:
            raise ValueError(f"gca/align/cpr.py: unknown hypotheses {bad}; elastic: {ELASTIC_HYPOTHESES}, "
                             f"plastic: {PLASTIC_HYPOTHESES}")
        if self.subset_size < 2 or self.n_groups < 2 or self.grid_size < 3 or self.refit_every < 1:
            raise ValueError("gca/align/cpr.py: need subset_size >= 2, n_groups >= 2, grid_size >= 3, "
                             f"refit_every >= 1; got {self}")
        if not self.eps > 0 or self.residual_on not in ("all", "subset"):
            raise ValueError(f"gca/align/cpr.py: eps must be > 0 and residual_on 'all'|'subset', got {self}")


@dataclasses.dataclass
class HypothesisFit:
    """One hypothesis fitted on S.

    Every field stays on the device of the fit (no host synchronisation while training); ``float()``
    reads one.

    Attributes:
        name: hypothesis name.
        theta: [P] float64, E[Theta_hat] (mean of the group estimates).
        theta_groups: [G, P] float64, per-group estimates.
        var_param: [] float64, relative variance of the group estimates (dimensionless).
        fit_residual: [] float64, relative misfit on S at theta (set after the residual pass).
        weight: [] float64, omega = 1 / (Var + eps).
    """

    name: str
    theta: torch.Tensor
    theta_groups: torch.Tensor
    var_param: torch.Tensor
    fit_residual: torch.Tensor | None = None
    weight: torch.Tensor | None = None


# ----------------------------------------------------------------------------- hypotheses
def elastic_tau(name: str, F: torch.Tensor, theta) -> torch.Tensor:
    """Kirchhoff stress of elastic hypothesis ``name`` with parameters ``theta`` ((mu, lam) or (lam,)).

    Args:
        name: one of :data:`ELASTIC_HYPOTHESES`.
        F: [N, 3, 3] elastic deformation gradient.
        theta: floats or [] tensors in the order of :data:`ELASTIC_PARAMS` (a [P] tensor works).

    Returns:
        [N, 3, 3] tau [Pa].
    """
    from gca.laws import elastic  # lazy: keeps `import gca.align` light

    if name == "volume":
        return elastic.volume_tau(F, theta[0])
    law = {"corotated": elastic.corotated_tau, "stvk": elastic.stvk_tau, "sigma": elastic.sigma_tau}[name]
    return law(F, theta[0], theta[1])


def plastic_map(name: str, F: torch.Tensor, theta, lam_over_mu: float, cohesion: float) -> torch.Tensor:
    """Return map F_trial -> F_e of plastic hypothesis ``name``.

    Args:
        name: one of :data:`PLASTIC_HYPOTHESES`.
        F: [N, 3, 3] trial deformation gradient.
        theta: () for identity/sigma, (k,) for von Mises (yield strain sigma_y/(2 mu)),
            (phi,) for Drucker-Prager (friction angle, deg); each a float or a [N] tensor.
        lam_over_mu: Lame ratio used by Drucker-Prager (float or [] tensor).
        cohesion: Drucker-Prager cohesion.

    Returns:
        [N, 3, 3] F_e.
    """
    from gca.laws import plastic  # lazy, as above

    if name == "identity":
        return plastic.identity_plastic(F)
    if name == "sigma":
        return plastic.sigma_plastic(F)
    if name == "von_mises":  # threshold sigma_y / (2 mu) = k with mu = 1/2
        return plastic.von_mises_plastic(F, 0.5, theta[0])
    return plastic.drucker_prager_plastic(F, 1.0, lam_over_mu, theta[0], cohesion)


# ----------------------------------------------------------------------------- solvers
def group_sums(values: torch.Tensor, group_ids: torch.Tensor, n_groups: int) -> torch.Tensor:
    """Sum ``values`` [S, ...] per group -> [G, ...]."""
    out = values.new_zeros((n_groups,) + values.shape[1:])
    return out.index_add_(0, group_ids, values)


def solve_linear_groups(basis: torch.Tensor, target: torch.Tensor, group_ids: torch.Tensor,
                        n_groups: int) -> torch.Tensor:
    """Least squares of ``target ~ sum_j theta_j basis_j`` per group (normal equations, float64).

    Args:
        basis: [P, S, 3, 3] responses to unit parameters.
        target: [S, 3, 3] neural response.
        group_ids: [S] group of each particle in [0, G).
        n_groups: G.

    Returns:
        [G, P] estimates (on the basis' device); a tiny ridge (1e-12 of the trace) keeps unidentifiable
        parameters at 0.
    """
    A = basis.flatten(2).double()  # [P, S, 9]
    b = target.flatten(1).double().to(A.device)  # [S, 9]
    group_ids = group_ids.to(A.device)
    gram = group_sums(torch.einsum("psk,qsk->spq", A, A), group_ids, n_groups)  # [G, P, P]
    rhs = group_sums(torch.einsum("psk,sk->sp", A, b), group_ids, n_groups)  # [G, P]
    trace = gram.diagonal(dim1=-2, dim2=-1).sum(-1)[:, None, None]
    eye = torch.eye(A.shape[0], dtype=torch.float64, device=A.device)
    return torch.linalg.solve_ex(gram + (1e-12 * trace + _TINY) * eye, rhs)[0]  # _ex: no host sync for its info


def _candidates(lo: torch.Tensor, hi: torch.Tensor, n: int, log: bool) -> torch.Tensor:
    """n candidates from lo to hi ([] tensors), evenly spaced (geometrically with ``log``), [n]."""
    t = torch.linspace(0.0, 1.0, n, dtype=torch.float64, device=lo.device)
    if log:
        return torch.exp(torch.log(lo) + (torch.log(hi) - torch.log(lo)) * t)
    return lo + (hi - lo) * t


def grid_fit_groups(errors: Callable[[torch.Tensor], torch.Tensor], lo: float, hi: float, log: bool,
                    group_ids: torch.Tensor, n_groups: int, grid_size: int, rounds: int,
                    device: torch.device | str = "cpu") -> torch.Tensor:
    """1-D least squares per group by a shared grid search with zoom refinement, on ``device``
    without host synchronisation (the zoom range stays a device tensor).

    Each round evaluates ``grid_size`` candidates on all of S, takes each group's best (ties go to
    the largest value, e.g. any yield strain beyond the largest strain fits an elastic response),
    and zooms to the hull of the groups' best neighbourhoods.

    Args:
        errors: candidates [K] -> [K, S] per-particle squared errors (one batched law call).
        lo, hi: search range; ``log`` for a geometric grid (lo > 0).
        group_ids: [S] group of each particle; n_groups: G.
        grid_size: candidates per round; rounds: number of rounds.
        device: where the candidates and the search live (that of ``errors``' output).

    Returns:
        [G, 1] float64 estimates on ``device``.
    """
    f64 = dict(dtype=torch.float64, device=device)
    lo_t, hi_t = torch.full((), float(lo), **f64), torch.full((), float(hi), **f64)  # fills, no host copy
    group_ids = group_ids.to(device)
    best_loss = torch.full((n_groups,), math.inf, **f64)
    best = torch.zeros(n_groups, **f64)
    for _ in range(rounds):
        cands = _candidates(lo_t, hi_t, grid_size, log)
        losses = group_sums(errors(cands).double().T, group_ids, n_groups)  # [G, K]
        idx = grid_size - 1 - losses.flip(1).argmin(1)  # [G], last minimiser
        loss = losses.gather(1, idx[:, None])[:, 0]
        better = loss <= best_loss
        best, best_loss = torch.where(better, cands[idx], best), torch.where(better, loss, best_loss)
        lo_t, hi_t = cands[(idx - 1).clamp(min=0)].min(), cands[(idx + 1).clamp(max=grid_size - 1)].max()
    return best[:, None]


def relative_variance(theta_groups: torch.Tensor, floor: float = _TINY) -> torch.Tensor:
    """Scale-free dispersion sum_j Var_g(theta_gj) / max(sum_j mean_g(theta_gj)^2, floor), a [] float64
    tensor on the estimates' device.

    Args:
        theta_groups: [G, P] per-group estimates (P = 0 gives 0).
        floor: lower bound of the normaliser (units of theta^2).
    """
    if theta_groups.shape[1] == 0:
        return theta_groups.new_zeros((), dtype=torch.float64)
    var = theta_groups.double().var(dim=0, unbiased=False).sum()
    norm = theta_groups.double().mean(dim=0).square().sum().clamp(min=floor)
    return var / norm


# ----------------------------------------------------------------------------- the regularizer
def _check_F(F: torch.Tensor, name: str) -> None:
    if F.ndim != 3 or F.shape[1:] != (3, 3):
        raise ValueError(f"gca/align/cpr.py: {name} must be [N, 3, 3], got {tuple(F.shape)}")


def _check_finite(named: dict[str, torch.Tensor]) -> None:
    """Raise FloatingPointError naming each [N, 3, 3] input with non-finite particles (one host read)."""
    counts = torch.stack([(~torch.isfinite(F.detach()).flatten(1).all(1)).sum() for F in named.values()]).tolist()
    bad = [f"{name} has {c} of {F.shape[0]} particles with non-finite entries"
           for (name, F), c in zip(named.items(), counts) if c]
    if bad:
        raise FloatingPointError("gca/align/cpr.py: " + "; ".join(bad) + "; the simulation diverged")


def _sq_error(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Per-particle squared Frobenius norm ||a - b||_F^2, [N]."""
    return (a - b).square().sum(dim=(-2, -1))


def lame_to_E_nu(mu: float, lam: float) -> tuple[float, float]:
    """Young's modulus [Pa] and Poisson ratio from Lame parameters (nan where undefined)."""
    if abs(lam + mu) < _TINY:
        return float("nan"), float("nan")
    return mu * (3 * lam + 2 * mu) / (lam + mu), lam / (2 * (lam + mu))


class CPR:
    """Constitutive Prior Regularizer with a fixed particle subset S (Algorithm 2).

    Args:
        cfg: :class:`CPRConfig`.
        n_particles: N, the number of particles of the run.
        seed: seeds the choice of S and of its groups (fixed for the run).
    """

    def __init__(self, cfg: CPRConfig, n_particles: int, seed: int):
        if n_particles < 2:
            raise ValueError(f"gca/align/cpr.py: CPR needs n_particles >= 2, got {n_particles}")
        self.cfg, self.n_particles = cfg, int(n_particles)
        g = torch.Generator().manual_seed(int(seed))
        self.subset = torch.randperm(self.n_particles, generator=g)[: min(cfg.subset_size, self.n_particles)]
        self.n_groups = min(cfg.n_groups, len(self.subset))
        self.group_ids = torch.arange(len(self.subset)) % self.n_groups  # S is already a random order
        self._calls, self._fits, self._on_device = 0, None, {}

    def _indices(self, device: torch.device) -> tuple[torch.Tensor, torch.Tensor]:
        """(S, group ids) on ``device``, copied once per device."""
        if device not in self._on_device:
            self._on_device[device] = (self.subset.to(device), self.group_ids.to(device))
        return self._on_device[device]

    # -- parameter solving ---------------------------------------------------------------------
    def fit_elastic(self, F_S: torch.Tensor, tau_S: torch.Tensor) -> dict[str, HypothesisFit]:
        """Fit every enabled elastic hypothesis to the neural stresses on S.

        Args:
            F_S: [S, 3, 3] F_e on S. tau_S: [S, 3, 3] neural tau on S [Pa] (detached).
        """
        F64, fits = F_S.detach().double(), {}
        for name in self.cfg.elastic:
            n_par = len(ELASTIC_PARAMS[name])
            units = torch.eye(n_par, dtype=torch.float64)
            basis = torch.stack([elastic_tau(name, F64, u.tolist()) for u in units])  # [P, S, 3, 3]
            groups = solve_linear_groups(basis, tau_S, self._indices(F64.device)[1], self.n_groups)
            fits[name] = HypothesisFit(name, groups.mean(0), groups, relative_variance(groups))
        return fits

    def _lam_over_mu(self, elastic_fits: dict[str, HypothesisFit], device) -> torch.Tensor:
        """lam/mu of the most credible two-parameter elastic fit with mu > 0 ([] float64 on ``device``;
        cfg.fallback_poisson's ratio when there is none), chosen on the device."""
        nu = self.cfg.fallback_poisson
        fallback = torch.full((), 2 * nu / (1 - 2 * nu), dtype=torch.float64, device=device)
        two = [f for f in elastic_fits.values() if f.theta.numel() == 2]
        if not two:
            return fallback
        theta = torch.stack([f.theta for f in two])  # [H, 2] (mu, lam)
        weight = torch.stack([f.weight for f in two])
        valid = theta[:, 0] > 0
        best = torch.where(valid, weight, torch.full_like(weight, -math.inf)).argmax()[None]
        (mu, lam), ok = theta.index_select(0, best)[0], valid.index_select(0, best)[0]  # a tensor index: no .item()
        ratio = lam / torch.where(ok, mu, torch.ones_like(mu))
        return torch.where(valid.any(), ratio, fallback)

    def _batched_errors(self, name: str, F: torch.Tensor, target: torch.Tensor, cands: torch.Tensor,
                        lam_over_mu) -> torch.Tensor:
        """[K, S] squared errors of hypothesis ``name`` at K candidate values (one law call on K*S)."""
        K, n = len(cands), F.shape[0]
        theta = cands.to(F.device).repeat_interleave(n)  # [K*S], candidate k for particles k*S .. (k+1)*S - 1
        out = plastic_map(name, F.repeat(K, 1, 1), (theta,), lam_over_mu, self.cfg.dp_cohesion)
        return _sq_error(out, target.repeat(K, 1, 1)).reshape(K, n)

    def fit_plastic(self, Ftr_S: torch.Tensor, Fe_S: torch.Tensor, lam_over_mu) -> dict[str, HypothesisFit]:
        """Fit every enabled plastic hypothesis to the neural return map on S.

        Args:
            Ftr_S: [S, 3, 3] F_trial on S. Fe_S: [S, 3, 3] neural F_e on S (detached).
            lam_over_mu: Lame ratio for Drucker-Prager (float or [] tensor).
        """
        cfg, F64, target, fits = self.cfg, Ftr_S.detach().double(), Fe_S.detach().double(), {}
        ranges = {"von_mises": (*cfg.yield_strain_range, True, cfg.yield_strain_range[0] ** 2),
                  "drucker_prager": (*cfg.friction_angle_range, False, 1.0)}
        for name in cfg.plastic:
            if name not in ranges:
                groups = torch.zeros(self.n_groups, 0, dtype=torch.float64, device=F64.device)
                fits[name] = HypothesisFit(name, groups.mean(0), groups, relative_variance(groups))
                continue
            lo, hi, log, floor = ranges[name]
            errors = lambda c, name=name: self._batched_errors(name, F64, target, c, lam_over_mu)
            groups = grid_fit_groups(errors, lo, hi, log, self._indices(F64.device)[1], self.n_groups, cfg.grid_size,
                                     cfg.refine_rounds, device=F64.device)
            fits[name] = HypothesisFit(name, groups.mean(0), groups, relative_variance(groups, floor))
        return fits

    # -- residuals -----------------------------------------------------------------------------
    def _weighted_residual(self, fits: dict[str, HypothesisFit], output: torch.Tensor,
                           hypothesis: Callable[[HypothesisFit], torch.Tensor], scale: torch.Tensor,
                           s_index, refit: bool) -> torch.Tensor:
        """sum_k omega_k mean_i ||output_i - H_k(.)_i||^2 / scale; sets misfit and omega when refitting."""
        total = output.new_zeros(())
        for fit in fits.values():
            err = _sq_error(output, hypothesis(fit).to(output.dtype)) / scale.to(output.dtype)  # [n]
            if refit:
                fit.fit_residual = err.detach()[s_index].double().mean()
                var = fit.var_param + (fit.fit_residual if self.cfg.include_fit_residual else 0.0)
                fit.weight = 1.0 / (var + self.cfg.eps)
            total = total + fit.weight.to(output.dtype) * err.mean()
        return total

    def _outputs(self, elasticity, plasticity, F_e, F_trial, tau, F_next):
        """Inputs (detached if configured) and the neural outputs, checked for divergence."""
        if self.cfg.detach_F:
            F_e, F_trial = F_e.detach(), F_trial.detach()
        tau = elasticity(F_e) if tau is None else tau
        F_next = plasticity(F_trial) if F_next is None else F_next
        for out, name in ((tau, "neural stress tau"), (F_next, "neural plastic F_e")):
            if out.shape != F_e.shape:
                raise ValueError(f"gca/align/cpr.py: {name} has shape {tuple(out.shape)}, expected {tuple(F_e.shape)}")
        return F_e, F_trial, tau, F_next

    def residuals(self, elasticity: Callable, plasticity: Callable, F_e: torch.Tensor, F_trial: torch.Tensor,
                  tau: Optional[torch.Tensor] = None, F_next: Optional[torch.Tensor] = None):
        """CPR residuals of one time step (Algorithm 2), with one host synchronisation (the finiteness
        check of the inputs and the neural outputs).

        Args:
            elasticity: neural elasticity, ``forward(F[N,3,3]) -> tau[N,3,3]`` (Kirchhoff, Pa).
            plasticity: neural plasticity, ``forward(F_trial[N,3,3]) -> F_e[N,3,3]``.
            F_e: [N, 3, 3] elastic deformation gradient of the state.
            F_trial: [N, 3, 3] trial deformation gradient after the Euler step.
            tau, F_next: optional precomputed ``elasticity(F_e)`` / ``plasticity(F_trial)`` (saves a
                forward pass when the simulator already has them; they keep whatever graph they carry,
                so ``detach_F`` then applies only to the hypotheses' side).

        Returns:
            ``(R_e, R_p, info)``: scalar tensors (dimensionless, differentiable w.r.t. the laws'
            parameters) and a dict with the fits (see :meth:`log_dict`; its numbers are [] tensors).
        """
        for F, name in ((F_e, "F_e"), (F_trial, "F_trial")):
            _check_F(F, name)
            if F.shape[0] != self.n_particles:
                raise ValueError(f"gca/align/cpr.py: {name} has {F.shape[0]} particles, CPR was built for "
                                 f"{self.n_particles}")
        F_e, F_trial, tau, F_next = self._outputs(elasticity, plasticity, F_e, F_trial, tau, F_next)
        _check_finite({"F_e": F_e, "F_trial": F_trial, "neural stress tau": tau, "neural plastic F_e": F_next})
        S, cfg = self._indices(F_e.device)[0], self.cfg
        idx, s_index = (S, slice(None)) if cfg.residual_on == "subset" else (slice(None), S)
        scale_e = tau.detach()[S].double().square().sum((-2, -1)).mean().clamp(min=_TINY)
        eye = torch.eye(3, dtype=torch.float64, device=F_trial.device)
        scale_p = (F_trial.detach()[S].double() - eye).square().sum((-2, -1)).mean().clamp(min=_TINY)
        refit = self._fits is None or self._calls % cfg.refit_every == 0
        self._calls += 1
        e_fits = self.fit_elastic(F_e[S], tau.detach()[S]) if refit else self._fits[0]
        R_e = self._weighted_residual(e_fits, tau[idx], lambda f: elastic_tau(f.name, F_e[idx], f.theta),
                                      scale_e, s_index, refit)
        lam_over_mu = self._lam_over_mu(e_fits, F_e.device) if refit else self._fits[2]
        p_fits = self.fit_plastic(F_trial[S], F_next.detach()[S], lam_over_mu) if refit else self._fits[1]
        R_p = self._weighted_residual(
            p_fits, F_next[idx],
            lambda f: plastic_map(f.name, F_trial[idx], f.theta, lam_over_mu, cfg.dp_cohesion),
            scale_p, s_index, refit)
        self._fits = (e_fits, p_fits, lam_over_mu)
        R_e, R_p = cfg.lambda_e * R_e, cfg.lambda_p * R_p
        info = {"elastic": e_fits, "plastic": p_fits, "scale_e": scale_e, "scale_p": scale_p,
                "lam_over_mu": lam_over_mu, "refit": refit, "R_e": R_e.detach(), "R_p": R_p.detach()}
        return R_e, R_p, info

    # -- logging -------------------------------------------------------------------------------
    @staticmethod
    def best(fits: dict[str, HypothesisFit]) -> Optional[str]:
        """Name of the hypothesis with the largest weight (None if no hypothesis is enabled)."""
        return max(fits, key=lambda k: float(fits[k].weight)) if fits else None

    @staticmethod
    def log_dict(info: dict, prefix: str = "cpr/") -> dict[str, float]:
        """Flat ``{name: float}`` of fitted parameters and weights, for MLflow / metrics JSON.

        Keys: ``{prefix}e/<hyp>/{mu,lam,E,nu,weight,var,misfit}``, ``{prefix}p/von_mises/{yield_strain,
        sigma_y}``, ``{prefix}p/drucker_prager/phi``, ``{prefix}p/<hyp>/{weight,var,misfit}``, ``R_e``, ``R_p``.
        sigma_y [Pa] = 2 mu k with mu of the most credible elastic fit (nan without one).
        """
        out = {f"{prefix}R_e": float(info["R_e"]), f"{prefix}R_p": float(info["R_p"])}
        mus = {n: float(f.theta[0]) for n, f in info["elastic"].items() if f.theta.numel() == 2}
        mu_ref = mus.get(CPR.best({n: info["elastic"][n] for n in mus}), float("nan")) if mus else float("nan")
        for kind, fits, names in (("e", info["elastic"], ELASTIC_PARAMS), ("p", info["plastic"], PLASTIC_PARAMS)):
            for name, fit in fits.items():
                key = f"{prefix}{kind}/{name}/"
                out.update({key + p: float(v) for p, v in zip(names[name], fit.theta)})
                out.update({key + "weight": float(fit.weight), key + "var": float(fit.var_param),
                            key + "misfit": float(fit.fit_residual)})
                if names[name] == ("mu", "lam"):
                    out[key + "E"], out[key + "nu"] = lame_to_E_nu(*(float(v) for v in fit.theta))
                if name == "von_mises":
                    out[key + "sigma_y"] = 2.0 * mu_ref * float(fit.theta[0])
        return out
