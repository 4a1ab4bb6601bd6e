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

Weighting (``weighting``). With omega_k as written, the gradient of omega_k * misfit_k (omega detached)
is about grad misfit_k / misfit_k = grad log misfit_k for a hypothesis that fits badly: every wrong
hypothesis pulls the law towards itself with unit strength, however little credible it is. Measured
at the paper profile (benchmarks/NOTES.md, session 5): a gel duck whose prior already matched its law
drifted away from it (silhouette loss x50, CD x14) until it diverged. The default therefore weights by
the credibility distribution omega_k / sum_j omega_j: R is a weighted mean of the misfits, dominated
by the hypotheses whose parameters are stable and fit, and near zero when one of them explains the
neural law. ``weighting="raw"`` keeps the paper's unnormalised sum.

Normalisation (s_e, s_p, detached, from S): stresses are 1e3-1e5 Pa, so s_e = mean_S ||E_theta(F_e)||^2
(the neural stress energy); plastic maps return F (~ I) but their content is the strain, so
s_p = mean_S ||F_trial - I||^2. A relative mismatch of order 1 thus gives a residual of order 1.
Each is floored, s_e >= ``stress_floor``^2 and s_p >= ``strain_floor``^2: a frame in free flight
(|F - I| ~ 1e-7, stresses ~0.01 Pa) carries no constitutive information, and relative to its own
stresses its float32 round-off read as R_e ~ 1.9e3 on the paper bottle, 4e4 x every deformed frame's
(benchmarks/NOTES.md, session 8), so CPR's gradient was that frame's noise.
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
    weighting: str = "normalized"  # omega_k / sum_j omega_j ("normalized") or omega_k as written ("raw")
    residual_on: str = "all"  # "all" particles (Algorithm 2) or the "subset" S (cheaper)
    detach_F: bool = True  # stop the CPR gradient at F_e / F_trial (it shapes the laws, not the path)
    refit_every: int = 1  # re-solve parameters and weights every k calls (Algorithm 2: 1) [calls]
    yield_strain_range: tuple[float, float] = (1e-4, 1.0)  # von Mises sigma_y/(2 mu) search [dimensionless]
    friction_angle_range: tuple[float, float] = (0.0, 60.0)  # Drucker-Prager phi search [deg]
    dp_cohesion: float = 0.0  # Drucker-Prager cohesion, fixed (NCLaw sand: 0) [log-strain]
    fallback_poisson: float = 0.2  # nu giving lam/mu for Drucker-Prager when no elastic fit exists
    grid_size: int = 16  # candidates per round of the 1-D plastic fits [count]
    refine_rounds: int = 3  # zoom rounds of the 1-D plastic fits [count]
    stress_floor: float = 1e2  # s_e >= stress_floor^2: frames at rest weigh in absolute terms [Pa]
    strain_floor: float = 1e-3  # s_p >= strain_floor^2 [1]
    chunk_frames: int = 10  # training: CPR's gradient taken this many frames at a time, each chunk's graph
    #                        freed before the next (the neural law's activations on all particles); 0 = one call
    max_grad_ratio: float = 0.3  # > 0: the gradient of R_e + R_p is scaled to at most this multiple of the
    #                              data terms' gradient norm (a soft prior, not the objective); 0: as written

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
        if self.weighting not in ("normalized", "raw"):
            raise ValueError(f"gca/align/cpr.py: weighting must be 'normalized' or 'raw', got {self.weighting!r}")
        if not (self.stress_floor > 0 and self.strain_floor > 0):
            raise ValueError(f"gca/align/cpr.py: stress_floor and strain_floor must be > 0, got {self}")
        if self.chunk_frames < 0:
            raise ValueError(f"gca/align/cpr.py: chunk_frames must be >= 0, got {self.chunk_frames}")
        if not self.max_grad_ratio >= 0:
            raise ValueError(f"gca/align/cpr.py: max_grad_ratio must be >= 0, got {self.max_grad_ratio}")
        if not self.eps > 0 or self.residual_on not in ("all", "subset"):
            raise ValueError(f"gca/align/cpr.py: eps must be > 0 and residual_on 'all'|'subset', got {self}")


@dataclasses.dataclass
class HypothesisFit:
    """One hypothesis fitted on S, for one frame or, stacked along a leading dim, for several.

    Every field stays on the device of the fit (no host synchronisation while training); ``float()``
    reads one. Shapes for one frame (what ``CPR.residuals`` reports); the stacked form used inside
    :meth:`CPR.residuals_frames` puts a leading [T] before each.

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

    _TENSORS = ("theta", "theta_groups", "var_param", "fit_residual", "weight")

    def _map(self, fn: Callable[[torch.Tensor], torch.Tensor]) -> "HypothesisFit":
        """The fit with ``fn`` applied to each tensor field (None stays None)."""
        return HypothesisFit(self.name, *(None if (t := getattr(self, f)) is None else fn(t) for f in self._TENSORS))

    def rows(self, index: torch.Tensor) -> "HypothesisFit":
        """The stacked fit's rows ``index`` ([k] long tensor on the fit's device)."""
        return self._map(lambda t: t.index_select(0, index))

    def squeeze(self) -> "HypothesisFit":
        """A one-row stacked fit as a one-frame fit."""
        return self._map(lambda t: t[0])

    @staticmethod
    def cat(first: Optional["HypothesisFit"], then: "HypothesisFit") -> "HypothesisFit":
        """Rows of ``first`` (or none) followed by those of ``then`` (fields present in both)."""
        if first is None:
            return then
        join = lambda a, b: None if a is None or b is None else torch.cat([a, b])  # noqa: E731
        return HypothesisFit(then.name, *(join(getattr(first, f), getattr(then, f)) for f in HypothesisFit._TENSORS))


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
    """n candidates per row from lo to hi ([R] tensors), evenly spaced (geometrically with ``log``), [R, n]."""
    t = torch.linspace(0.0, 1.0, n, dtype=torch.float64, device=lo.device)
    if log:
        return torch.exp(torch.log(lo)[:, None] + (torch.log(hi) - torch.log(lo))[:, None] * t)
    return lo[:, None] + (hi - lo)[:, None] * t


def grid_fit_groups(errors: Callable[[torch.Tensor], torch.Tensor], lo: float, hi: float, log: bool,
                    group_ids: torch.Tensor, n_groups: int, grid_size: int, rounds: int, n_frames: int = 1,
                    device: torch.device | str = "cpu") -> torch.Tensor:
    """1-D least squares per (frame, group) by a grid search with zoom refinement, on ``device``
    without host synchronisation (the zoom ranges stay device tensors).

    Each round evaluates ``grid_size`` candidates per frame on all of that frame's S, takes each
    group's best (ties go to the largest value, e.g. any yield strain beyond the largest strain fits
    an elastic response), and zooms each frame to the hull of its groups' best neighbourhoods.

    Args:
        errors: candidates [R, K] -> [R, K, S] per-particle squared errors (one batched law call).
        lo, hi: search range; ``log`` for a geometric grid (lo > 0).
        group_ids: [S] group of each particle; n_groups: G.
        grid_size: candidates per round; rounds: number of rounds.
        n_frames: R, frames fitted at once (independently).
        device: where the candidates and the search live (that of ``errors``' output).

    Returns:
        [R, G, 1] float64 estimates on ``device``.
    """
    f64 = dict(dtype=torch.float64, device=device)
    R, K = n_frames, grid_size
    lo_t, hi_t = torch.full((R,), float(lo), **f64), torch.full((R,), float(hi), **f64)  # fills, no host copy
    group_ids = group_ids.to(device)
    best_loss = torch.full((R, n_groups), math.inf, **f64)
    best = torch.zeros(R, n_groups, **f64)
    for _ in range(rounds):
        cands = _candidates(lo_t, hi_t, K, log)  # [R, K]
        per_particle = errors(cands).double().permute(2, 0, 1)  # [S, R, K]
        losses = group_sums(per_particle, group_ids, n_groups).permute(1, 0, 2)  # [R, G, K]
        idx = K - 1 - losses.flip(-1).argmin(-1)  # [R, G], last minimiser
        loss = losses.gather(-1, idx[..., None])[..., 0]
        better = loss <= best_loss
        best, best_loss = torch.where(better, cands.gather(1, idx), best), torch.where(better, loss, best_loss)
        lo_t = cands.gather(1, (idx - 1).clamp(min=0)).min(1).values
        hi_t = cands.gather(1, (idx + 1).clamp(max=K - 1)).max(1).values
    return best[..., None]


def relative_variance(theta_groups: torch.Tensor, floor: float = _TINY) -> torch.Tensor:
    """Scale-free dispersion sum_j Var_g(theta_gj) / max(sum_j mean_g(theta_gj)^2, floor), float64 on
    the estimates' device.

    Args:
        theta_groups: [..., G, P] per-group estimates (P = 0 gives 0).
        floor: lower bound of the normaliser (units of theta^2).

    Returns:
        [...] (a [] tensor for [G, P] estimates).
    """
    if theta_groups.shape[-1] == 0:
        return theta_groups.new_zeros(theta_groups.shape[:-2], dtype=torch.float64)
    var = theta_groups.double().var(dim=-2, unbiased=False).sum(-1)
    norm = theta_groups.double().mean(dim=-2).square().sum(-1).clamp(min=floor)
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

    def state(self) -> dict:
        """What the run has changed: its call count and the most recent fits (the calls between two refits,
        ``refit_every`` > 1, reuse them). A training checkpoint holds it (tensors, numbers and names only),
        so a resumed run refits, and reuses, where the uninterrupted run would."""
        def fits(table):
            return {n: {"name": f.name, **{k: getattr(f, k) for k in HypothesisFit._TENSORS}} for n, f in table.items()}

        cached = self._fits
        return {"calls": self._calls, "fits": None if cached is None else {
            "elastic": fits(cached["elastic"]), "plastic": fits(cached["plastic"]), "lam_over_mu": cached["lam_over_mu"]}}

    def load_state(self, state: dict) -> None:
        """Continue from :meth:`state` (of a CPR of the same configuration and particles)."""
        def fits(table):
            return {n: HypothesisFit(**f) for n, f in table.items()}

        cached = state["fits"]
        self._calls = int(state["calls"])
        self._fits = None if cached is None else {"elastic": fits(cached["elastic"]), "plastic": fits(cached["plastic"]),
                                                  "lam_over_mu": cached["lam_over_mu"]}

    def _indices(self, device: torch.device) -> tuple[torch.Tensor, torch.Tensor]:
        """(S, group ids) on ``device``, copied once per device."""
        if device not in self._on_device:
            self._on_device[device] = (self.subset.to(device), self.group_ids.to(device))
        return self._on_device[device]

    # -- parameter solving (R frames at once, each independently) -----------------------------
    def _frame_groups(self, n_frames: int, device) -> tuple[torch.Tensor, int]:
        """Group ids [R*S] of R frames' subsets stacked (frame r's group g is r*G + g) and R*G."""
        group_ids = self._indices(device)[1]
        frame = torch.arange(n_frames, device=device)[:, None] * self.n_groups
        return (frame + group_ids).reshape(-1), n_frames * self.n_groups

    def fit_elastic(self, F_S: torch.Tensor, tau_S: torch.Tensor) -> dict[str, HypothesisFit]:
        """Fit every enabled elastic hypothesis to the neural stresses on S, per frame.

        Args:
            F_S: [R, S, 3, 3] F_e on S. tau_S: [R, S, 3, 3] neural tau on S [Pa] (detached).

        Returns:
            stacked fits: theta [R, P], theta_groups [R, G, P], var_param [R].
        """
        R, n = F_S.shape[:2]
        F64, fits = F_S.detach().double().reshape(R * n, 3, 3), {}
        gids, n_groups = self._frame_groups(R, F64.device)
        for name in self.cfg.elastic:
            n_par = len(ELASTIC_PARAMS[name])
            units = torch.eye(n_par, dtype=torch.float64)
            basis = torch.stack([elastic_tau(name, F64, u.tolist()) for u in units])  # [P, R*S, 3, 3]
            groups = solve_linear_groups(basis, tau_S.reshape(R * n, 3, 3), gids, n_groups).reshape(R, self.n_groups, n_par)
            fits[name] = HypothesisFit(name, groups.mean(1), groups, relative_variance(groups))
        return fits

    def _lam_over_mu(self, elastic_fits: dict[str, HypothesisFit], n_frames: int, device) -> torch.Tensor:
        """lam/mu per frame of the most credible two-parameter elastic fit with mu > 0 ([R] float64 on
        ``device``; cfg.fallback_poisson's ratio where there is none), chosen on the device."""
        nu = self.cfg.fallback_poisson
        fallback = torch.full((n_frames,), 2 * nu / (1 - 2 * nu), dtype=torch.float64, device=device)
        two = [f for f in elastic_fits.values() if f.theta.shape[-1] == 2]
        if not two:
            return fallback
        theta = torch.stack([f.theta for f in two])  # [H, R, 2] (mu, lam)
        weight = torch.stack([f.weight for f in two])  # [H, R]
        valid = theta[..., 0] > 0
        best = torch.where(valid, weight, torch.full_like(weight, -math.inf)).argmax(0, keepdim=True)  # [1, R]
        mu, lam = (theta[..., j].gather(0, best)[0] for j in (0, 1))  # a tensor index: no .item()
        ratio = lam / torch.where(valid.gather(0, best)[0], mu, torch.ones_like(mu))
        return torch.where(valid.any(0), ratio, fallback)

    def _batched_errors(self, name: str, F: torch.Tensor, target: torch.Tensor, cands: torch.Tensor,
                        lam_over_mu: torch.Tensor) -> torch.Tensor:
        """[R, K, S] squared errors of hypothesis ``name`` at each frame's K candidates [R, K] (one law
        call on R*K*S particles); ``F``, ``target`` [R, S, 3, 3], ``lam_over_mu`` [R]."""
        (R, n), K = F.shape[:2], cands.shape[1]
        flat = lambda t: t.expand(R, K, n, *t.shape[3:]).reshape(R * K * n, *t.shape[3:])  # noqa: E731
        theta = flat(cands.to(F.device)[:, :, None])
        out = plastic_map(name, flat(F[:, None]), (theta,), flat(lam_over_mu[:, None, None]), self.cfg.dp_cohesion)
        return _sq_error(out, flat(target[:, None])).reshape(R, K, n)

    def fit_plastic(self, Ftr_S: torch.Tensor, Fe_S: torch.Tensor, lam_over_mu: torch.Tensor) -> dict[str, HypothesisFit]:
        """Fit every enabled plastic hypothesis to the neural return map on S, per frame.

        Args:
            Ftr_S: [R, S, 3, 3] F_trial on S. Fe_S: [R, S, 3, 3] neural F_e on S (detached).
            lam_over_mu: [R] Lame ratio for Drucker-Prager.

        Returns:
            stacked fits: theta [R, P], theta_groups [R, G, P], var_param [R].
        """
        cfg, F64, target, fits = self.cfg, Ftr_S.detach().double(), Fe_S.detach().double(), {}
        R = F64.shape[0]
        ranges = {"von_mises": (*cfg.yield_strain_range, True, cfg.yield_strain_range[0] ** 2),
                  "drucker_prager": (*cfg.friction_angle_range, False, 1.0)}
        for name in cfg.plastic:
            if name not in ranges:
                groups = torch.zeros(R, self.n_groups, 0, dtype=torch.float64, device=F64.device)
                fits[name] = HypothesisFit(name, groups.mean(1), groups, relative_variance(groups))
                continue
            lo, hi, log, floor = ranges[name]
            errors = lambda c, name=name: self._batched_errors(name, F64, target, c, lam_over_mu)
            groups = grid_fit_groups(errors, lo, hi, log, self._indices(F64.device)[1], self.n_groups, cfg.grid_size,
                                     cfg.refine_rounds, n_frames=R, device=F64.device)
            fits[name] = HypothesisFit(name, groups.mean(1), groups, relative_variance(groups, floor))
        return fits

    # -- residuals -----------------------------------------------------------------------------
    def _weighted_residual(self, new: Optional[dict[str, HypothesisFit]], cached: Optional[dict[str, HypothesisFit]],
                           output: torch.Tensor, hypothesis: Callable[[str, torch.Tensor], torch.Tensor],
                           scale: torch.Tensor, s_index, plan: "_RefitPlan") -> tuple[torch.Tensor, dict]:
        """sum_b sum_k omega_k^b mean_i ||output_bi - H_k(.)_bi||^2 / scale_b over the B frames.

        ``new`` (or None) are the stacked fits of the plan's refit frames; their misfit and omega are
        set here from those frames' errors. The table the plan indexes is ``cached`` (or no) rows
        followed by the new ones; it is returned.

        Args:
            output: [B, n, 3, 3] neural outputs. scale: [B].
            hypothesis: (name, theta [B, P]) -> [B, n, 3, 3].
        """
        table, weights, misfits = {}, [], []
        for name in (new if new is not None else cached):
            old, fresh = (None if d is None else d[name] for d in (cached, new))
            theta = torch.cat([f.theta for f in (old, fresh) if f is not None]).index_select(0, plan.source)  # [B, P]
            err = _sq_error(output, hypothesis(name, theta).to(output.dtype)) / scale.to(output.dtype)[:, None]  # [B, n]
            if fresh is not None:
                fresh.fit_residual = err.detach()[plan.refit][:, s_index].double().mean(1)  # [R]
                var = fresh.var_param + (fresh.fit_residual if self.cfg.include_fit_residual else 0.0)
                fresh.weight = 1.0 / (var + self.cfg.eps)
            rows = HypothesisFit.cat(old, fresh) if fresh is not None else old
            table[name] = rows
            weights.append(rows.weight.index_select(0, plan.source).to(output.dtype))  # [B]
            misfits.append(err.mean(1))  # [B]
        if not weights:  # no hypothesis enabled on this side
            return output.new_zeros(()), table
        w, e = torch.stack(weights), torch.stack(misfits)  # [K, B]
        if self.cfg.weighting == "normalized":
            w = w / w.sum(0, keepdim=True)
        return (w * e).sum(), table

    def _outputs(self, elasticity, plasticity, F_e, F_trial, tau, F_next):
        """Inputs (detached if configured) and the neural outputs, checked for divergence; [B*N, 3, 3]."""
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
        """CPR residuals of one time step (Algorithm 2): :meth:`residuals_frames` of one frame.

        Args:
            F_e: [N, 3, 3] elastic deformation gradient of the state.
            F_trial: [N, 3, 3] trial deformation gradient after the Euler step.
            tau, F_next: optional precomputed [N, 3, 3] ``elasticity(F_e)`` / ``plasticity(F_trial)``.

        Returns:
            ``(R_e, R_p, info)`` as :meth:`residuals_frames`.
        """
        for F, name in ((F_e, "F_e"), (F_trial, "F_trial")):
            _check_F(F, name)
        one = lambda t: None if t is None else t[None]  # noqa: E731
        return self.residuals_frames(elasticity, plasticity, F_e[None], F_trial[None], one(tau), one(F_next))

    def residuals_frames(self, elasticity: Callable, plasticity: Callable, F_e: torch.Tensor, F_trial: torch.Tensor,
                         tau: Optional[torch.Tensor] = None, F_next: Optional[torch.Tensor] = None):
        """Sum of the CPR residuals of B time steps (Algorithm 2 on each), in one batched pass with one
        host synchronisation (the finiteness check of the inputs and the neural outputs).

        Equal to B calls of :meth:`residuals` in frame order, ``refit_every`` included: frame b is call
        ``c + b`` of the run; frames due for a refit are fitted (all at once, each on its own S),
        the others reuse the most recent refit before them (earlier in the batch, or cached).

        Args:
            elasticity: neural elasticity, ``forward(F[M,3,3]) -> tau[M,3,3]`` (Kirchhoff, Pa).
            plasticity: neural plasticity, ``forward(F_trial[M,3,3]) -> F_e[M,3,3]``.
            F_e: [B, N, 3, 3] elastic deformation gradients of the states.
            F_trial: [B, N, 3, 3] trial deformation gradients after each state's Euler step.
            tau, F_next: optional precomputed [B, N, 3, 3] ``elasticity(F_e)`` / ``plasticity(F_trial)``
                (they keep whatever graph they carry, so ``detach_F`` then applies only to the
                hypotheses' side).

        Returns:
            ``(R_e, R_p, info)``: scalar tensors (summed over the B frames; dimensionless,
            differentiable w.r.t. the laws' parameters) and a dict with the last frame's fits (see
            :meth:`log_dict`; its numbers are [] tensors).
        """
        for F, name in ((F_e, "F_e"), (F_trial, "F_trial")):
            if F.ndim != 4 or F.shape[2:] != (3, 3) or F.shape[:2] != F_e.shape[:2]:
                raise ValueError(f"gca/align/cpr.py: {name} must be [B, N, 3, 3] like F_e, got {tuple(F.shape)}")
            if F.shape[1] != self.n_particles:
                raise ValueError(f"gca/align/cpr.py: {name} has {F.shape[1]} particles, CPR was built for "
                                 f"{self.n_particles}")
        B, N = F_e.shape[:2]
        flat = lambda t: None if t is None else t.reshape(B * N, 3, 3)  # noqa: E731
        outs = self._outputs(elasticity, plasticity, flat(F_e), flat(F_trial), flat(tau), flat(F_next))
        _check_finite(dict(zip(("F_e", "F_trial", "neural stress tau", "neural plastic F_e"), outs)))
        F_e, F_trial, tau, F_next = (t.reshape(B, N, 3, 3) for t in outs)
        S, cfg, dev = self._indices(F_e.device)[0], self.cfg, F_e.device
        idx, s_index = (S, slice(None)) if cfg.residual_on == "subset" else (slice(None), S)
        scale_e = tau.detach()[:, S].double().square().sum((-2, -1)).mean(1).clamp(min=cfg.stress_floor ** 2)  # [B]
        eye = torch.eye(3, dtype=torch.float64, device=dev)
        scale_p = (F_trial.detach()[:, S].double() - eye).square().sum((-2, -1)).mean(1).clamp(min=cfg.strain_floor ** 2)
        plan = _RefitPlan(self._calls, B, cfg.refit_every, self._fits is not None, dev)
        self._calls += B
        cached = self._fits or {"elastic": None, "plastic": None, "lam_over_mu": None}
        r = plan.refit
        e_new = self.fit_elastic(F_e[r][:, S], tau.detach()[r][:, S]) if plan.n_refit else None
        R_e, e_fits = self._weighted_residual(
            e_new, cached["elastic"], tau[:, idx],
            lambda name, theta: _per_frame(elastic_tau, name, F_e[:, idx], theta), scale_e, s_index, plan)
        lam_table = cached["lam_over_mu"]
        if plan.n_refit:
            lam_new = self._lam_over_mu(e_new, plan.n_refit, dev)
            lam_table = lam_new if lam_table is None else torch.cat([lam_table, lam_new])
        lam_b = lam_table.index_select(0, plan.source)  # [B]
        p_new = self.fit_plastic(F_trial[r][:, S], F_next.detach()[r][:, S], lam_new) if plan.n_refit else None
        dp = lambda name, F, theta, lam: plastic_map(name, F, theta, lam, cfg.dp_cohesion)  # noqa: E731
        R_p, p_fits = self._weighted_residual(
            p_new, cached["plastic"], F_next[:, idx],
            lambda name, theta: _per_frame(dp, name, F_trial[:, idx], theta, lam_b), scale_p, s_index, plan)
        last = plan.source[-1:]  # the table row of the last frame: the most recent refit
        self._fits = {"elastic": {n: f.rows(last) for n, f in e_fits.items()},
                      "plastic": {n: f.rows(last) for n, f in p_fits.items()},
                      "lam_over_mu": lam_table.index_select(0, last)}
        R_e, R_p = cfg.lambda_e * R_e, cfg.lambda_p * R_p
        info = {"elastic": {n: f.squeeze() for n, f in self._fits["elastic"].items()},
                "plastic": {n: f.squeeze() for n, f in self._fits["plastic"].items()},
                "scale_e": scale_e[-1], "scale_p": scale_p[-1], "lam_over_mu": lam_b[-1],
                "refit": plan.last_refit, "refit_frames": plan.n_refit, "frames": B,
                "R_e": R_e.detach(), "R_p": R_p.detach()}
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


class _RefitPlan:
    """Which of B consecutive CPR calls refit, and which fit each one uses (host arithmetic only).

    Call ``c0 + b`` refits when it is a multiple of ``every`` (the first call ever always is: c0 = 0).
    Refit frames form the slice ``refit`` (an arithmetic progression, so indexing needs no index copy).
    The fits table has the cached rows (1, when there are cached fits) then one row per refit frame;
    ``source`` [B] (device) gives each frame's row: its own refit, or the most recent one before it.
    """

    def __init__(self, c0: int, B: int, every: int, has_cache: bool, device):
        r0 = (-c0) % every
        self.refit = slice(r0, B, every)
        self.n_refit = len(range(r0, B, every))
        if not has_cache and r0 != 0:
            raise RuntimeError("gca/align/cpr.py: CPR has no fits to reuse before its first refit")
        b = torch.arange(B, device=device)
        refits_so_far = torch.where(b >= r0, torch.div(b - r0, every, rounding_mode="floor") + 1, torch.zeros_like(b))
        self.source = refits_so_far - 1 + int(has_cache)
        self.last_refit = (B - 1 - r0) % every == 0 and B - 1 >= r0


def _per_frame(fn: Callable, name: str, F: torch.Tensor, theta: torch.Tensor, *per_frame: torch.Tensor) -> torch.Tensor:
    """``fn(name, F [B*n, 3, 3], params, *extra)`` with frame b's parameters on its n particles.

    Args:
        F: [B, n, 3, 3]. theta: [B, P] parameters per frame. per_frame: further [B] values per frame.

    Returns:
        [B, n, 3, 3].
    """
    B, n = F.shape[:2]
    expand = lambda t: t[:, None].expand(B, n).reshape(B * n)  # noqa: E731
    params = [expand(theta[:, j]) for j in range(theta.shape[1])]
    return fn(name, F.reshape(B * n, 3, 3), params, *(expand(t) for t in per_frame)).reshape(B, n, 3, 3)
