"""NCLaw-style neural constitutive laws (``InvariantFullMeta``): objective, zero at rest by construction.

Both networks read the same 13 rest-shifted features of the deformation gradient F = U diag(sigma) V^T,

    z = [sigma - 1 (3), vec(F^T F - I) (9), det F - 1 (1)],

pass them through a bias-free MLP (13 -> widths -> 9), symmetrise the output into S (3x3) and act
through the polar rotation R = U V^T:

    elasticity   P = stress_scale * R S,   tau = P F^T          (Kirchhoff stress, Pa)
    plasticity   F_e = F_trial + alpha * R S                    (residual return map)

Zero at rest: F = I gives z = 0 exactly, and a bias-free MLP with act(0) = 0 maps 0 to 0, so
tau(I) = 0 and F_e(I) = I exactly, for any weights (also after training and with LoRA, whose layers
have no bias either). Objectivity: z is invariant to F -> Q F (Q a rotation) and R -> Q R, so
tau(Q F) = Q tau(F) Q^T and F_e(Q F) = Q F_e(F).

Output scaling (departure from NCLaw). NCLaw's networks emit Pa directly (weights of std 5-10, lr 1.0;
reference notes 4.3). Here the MLP emits O(1) numbers and ``stress_scale`` (Pa) multiplies them, so
standard learning rates and Xavier init work for materials with E ~ 1e5-1e6 Pa (strains of a few
percent give tau ~ 1e3-1e4 Pa). The scale is a fixed constant, so zero-at-rest stays exact.

Reference: Ma et al. 2023 (NCLaw) ``nclaw/material/meta.py``; notes in shared/reference/nclaw-neuma.md §1.
"""

from __future__ import annotations

import contextlib
import dataclasses
import math

import torch
from torch import nn

from gca.laws import fused, mlp_kernel
from gca.laws.base import Elasticity, Plasticity
from gca.laws.lora import effective_weight
from gca.laws.svd import bmm3, check_F, det3, svd, warp_runs

# Activations allowed in the MLP: all satisfy act(0) = 0 exactly (needed for zero-at-rest).
ACTIVATIONS = {"gelu": nn.GELU, "tanh": nn.Tanh, "silu": nn.SiLU, "elu": nn.ELU, "relu": nn.ReLU}
N_FEATURES = 13  # [sigma - 1 (3), vec(F^T F - I) (9), det F - 1 (1)]
MLP_KERNELS = ("torch", "warp", "simt", "triton_tf32")  # _InvariantNetwork.mlp_kernel


@dataclasses.dataclass(frozen=True)
class NeuralLawConfig:
    """Architecture and output scaling of the neural elasticity and plasticity (params ``laws.neural``).

    Architecture fields (``widths``, ``activation``) are checked when a checkpoint is loaded.
    """

    widths: tuple[int, ...] = (64, 64)  # hidden layer widths of both MLPs (NCLaw: 64, 64) [count]
    activation: str = "gelu"  # hidden activation, one of ACTIVATIONS (NCLaw: gelu)
    stress_scale: float = 1.0e4  # Pa per unit network output of the elasticity (NCLaw: 1, i.e. raw Pa)
    alpha: float = 1.0e-3  # plastic correction step: F_e = F + alpha R S (NCLaw: 1e-3) [dimensionless]

    def __post_init__(self):
        object.__setattr__(self, "widths", tuple(int(w) for w in self.widths))
        if not self.widths or min(self.widths) < 1:
            raise ValueError(f"gca/laws/neural.py: NeuralLawConfig.widths must be positive ints, got {self.widths}")
        if self.activation not in ACTIVATIONS:
            raise ValueError(f"gca/laws/neural.py: NeuralLawConfig.activation={self.activation!r} is not one of "
                             f"{sorted(ACTIVATIONS)} (must satisfy act(0) = 0)")
        if not self.stress_scale > 0 or not self.alpha > 0:
            raise ValueError(f"gca/laws/neural.py: stress_scale and alpha must be > 0, got "
                             f"{self.stress_scale}, {self.alpha}")

    def architecture(self) -> dict:
        """The fields a checkpoint must match to be loadable into this network."""
        return {"widths": list(self.widths), "activation": self.activation}


def invariant_features(F: torch.Tensor, sigma: torch.Tensor) -> torch.Tensor:
    """Rest-shifted, left-rotation-invariant features of F.

    Args:
        F: deformation gradients [N, 3, 3].
        sigma: singular values of F [N, 3] (as returned by ``gca.laws.svd.svd``).

    Returns:
        z [N, 13] = [sigma - 1, vec(F^T F - I), det F - 1]; exactly 0 at F = I.
    """
    eye = torch.eye(3, dtype=F.dtype, device=F.device)
    C = bmm3(F.transpose(1, 2), F)
    return torch.cat([sigma - 1.0, (C - eye).reshape(-1, 9), (det3(F) - 1.0)[:, None]], dim=1)


def make_mlp(cfg: NeuralLawConfig) -> nn.Sequential:
    """Bias-free MLP 13 -> widths -> 9 with Xavier-uniform weights (NCLaw ``init_weight``)."""
    sizes = (N_FEATURES, *cfg.widths, 9)
    layers: list[nn.Module] = []
    for i, (n_in, n_out) in enumerate(zip(sizes[:-1], sizes[1:])):
        linear = nn.Linear(n_in, n_out, bias=False)
        nn.init.xavier_uniform_(linear.weight)
        layers.append(linear)
        if i < len(sizes) - 2:
            layers.append(ACTIVATIONS[cfg.activation]())
    return nn.Sequential(*layers)


def _mlp_triton():
    """``gca.laws.mlp_triton``, imported where ``triton_tf32`` is used: triton is needed only by this option."""
    try:
        from gca.laws import mlp_triton
    except ImportError as exc:
        raise ImportError(f"gca/laws/neural.py: mlp_kernel='triton_tf32' needs triton ({exc}): a CUDA torch brings it; "
                          "on a CPU, pip install -e .[interp]") from exc
    return mlp_triton


def _triton_mlp(mlp: nn.Sequential, z: torch.Tensor, frame=None, stash: "MLPStash | None" = None) -> torch.Tensor:
    """``mlp_kernel: triton_tf32``: the MLP through ``gca.laws.mlp_triton`` with the layers' effective (LoRA-merged)
    weights (TF32 products for float32; a float64 law, the interpreter's gradient checks, runs FP64 products).
    ``frame``: the network's ``(sink, weights)`` of :func:`frame_mlp_sums` (the weights' gradients summed once a
    frame), or None. ``stash``: the network's :class:`MLPStash` of :func:`frame_mlp_stash` (this call's output kept
    in, or taken from, the frame's next entry), or None."""
    mlp_triton = _mlp_triton()
    layers = mlp_triton.check(mlp)
    precision = "tf32" if z.dtype == torch.float32 else "ieee"
    keep = {} if stash is None else {"given" if stash.replay else "out": stash.take()}
    if frame is not None:
        return mlp_triton.mlp(z, frame[1], precision, sink=frame[0], **keep)
    return mlp_triton.mlp(z, [effective_weight(layer) for layer in layers], precision, **keep)


class MLPStash:
    """One network's MLP outputs over a frame's ``n_steps`` calls (``MPMSolver.mlp_stash_mib``): ``buf`` [n_steps, N,
    N_OUT], entry i the frame's i-th call's X. Recording (``replay`` False: the frame's forward pass, no autograd),
    each call's fused forward writes its output into its entry; replaying (the frame's recompute for its backward),
    each call takes its entry as its output and launches no forward (the backward is unchanged: the fused backward
    recomputes the forward on chip from the inputs). Exact: the recompute's inputs are the forward pass's bit for bit
    (as the grid stash's, ``gca.sim.graph``), and the kernel is deterministic. ``calls`` counts the frame's calls; a
    frame that calls the network more than ``n_steps`` times raises, and :func:`frame_mlp_stash` checks on leaving
    that it called it exactly ``n_steps`` times."""

    def __init__(self, buf: torch.Tensor, replay: bool, name: str = "network"):
        self.buf, self.replay, self.name, self.calls = buf, bool(replay), name, 0

    def take(self) -> torch.Tensor:
        """The next call's entry [N, N_OUT]."""
        if self.calls >= self.buf.shape[0]:
            raise RuntimeError(f"gca/laws/neural.py: the {self.name}'s MLP stash holds {self.buf.shape[0]} calls a "
                               f"frame, and the frame called it again (one call a step expected)")
        self.calls += 1
        return self.buf[self.calls - 1]


def fused_mlp_networks(material) -> list["_InvariantNetwork"]:
    """The neural networks of ``material`` whose MLP runs the fused Triton kernels (``mlp_kernel: triton_tf32``) on the
    fast path, in module order: those a frame can sum the weight gradients of (:func:`frame_mlp_sums`) or keep the
    outputs of (:class:`MLPStash`)."""
    return [net for net in neural_networks(material) if net.mlp_kernel == "triton_tf32" and net.fast_path]


@contextlib.contextmanager
def frame_mlp_stash(material, bufs: list[torch.Tensor] | None, replay: bool):
    """Within the block, each network of :func:`fused_mlp_networks` keeps (``replay`` False) or takes (``replay``
    True) its MLP outputs in its buffer of ``bufs`` ([n_steps, N, N_OUT] each, in that order; :class:`MLPStash`). A
    no-op where ``bufs`` is None. On leaving without an error, every network must have been called once per entry: a
    frame whose law took another number of calls than its stash holds raises (its recompute would read another
    call's output)."""
    nets = [] if bufs is None else fused_mlp_networks(material)
    if len(nets) != (0 if bufs is None else len(bufs)):
        raise ValueError(f"gca/laws/neural.py: {len(bufs)} MLP stash buffers for {len(nets)} networks on the fused "
                         f"MLP")
    if any(net._mlp_stash is not None for net in nets):
        raise RuntimeError("gca/laws/neural.py: a frame's MLP stash entered inside another")
    stashes = [MLPStash(b, replay, type(net).__name__) for net, b in zip(nets, bufs or [])]
    try:
        for net, st in zip(nets, stashes):
            net._mlp_stash = st
        yield material
        for st in stashes:
            if st.calls != st.buf.shape[0]:
                raise RuntimeError(f"gca/laws/neural.py: the {st.name}'s MLP stash holds {st.buf.shape[0]} calls a "
                                   f"frame, and the frame called it {st.calls} times")
    finally:
        for net in nets:
            net._mlp_stash = None


@contextlib.contextmanager
def frame_mlp_sums(material, enabled: bool = True):
    """Within the block, every neural network of ``material`` whose MLP runs the fused Triton kernels
    (``mlp_kernel: triton_tf32`` on the fast path) and whose weights take a gradient sums its weight gradients
    over the block's calls once (``gca.laws.mlp_triton.frame_weights``; ``MPMSolver.frame_mlp_grads``): its
    effective (merged) weights formed once on entry, each call's backward storing its programs' partials in a block
    of the frame's, one reduction when autograd reaches the weights. Enter it inside :func:`gca.laws.lora.
    merged_weights` (the merge is then the frame's). The same gradient to float rounding; a no-op where
    ``enabled`` is False, autograd does not record, or no such network is there. A network evaluated on another
    device or dtype inside the block raises (the sum's rows are the frame's)."""
    nets = [] if not enabled or not torch.is_grad_enabled() else [
        net for net in fused_mlp_networks(material) if net._frame_mlp is None]
    formed = []
    try:
        mlp_triton = _mlp_triton() if nets else None
        for net in nets:
            weights = [effective_weight(layer) for layer in mlp_triton.check(net.mlp)]
            if not any(w.requires_grad for w in weights) or not mlp_triton.runs_here(weights[0]):
                continue
            net._frame_mlp = mlp_triton.frame_weights(weights)
            formed.append(net)
        yield material
    finally:
        for net in formed:
            net._frame_mlp = None


def mlp_kernel_problem(kind: str, device) -> str | None:
    """Why the MLP kernel ``kind`` cannot run on ``device`` (None: it can). Only ``triton_tf32`` has a condition: it
    needs triton, and CUDA or a CPU under Triton's interpreter (``gca.laws.mlp_triton.runs_here``)."""
    if kind != "triton_tf32":
        return None
    try:
        from gca.laws import mlp_triton
    except ImportError as exc:
        return f"needs triton ({exc})"
    if not mlp_triton.runs_here(torch.empty(0, device=device)):
        return (f"runs on CUDA, or on a CPU only under Triton's interpreter (TRITON_INTERPRET=1, far slower than torch), "
                f"not on {torch.device(device).type}")
    return None


class _InvariantNetwork(nn.Module):
    """Shared trunk: F -> (R, S) with R the polar rotation and S = sym(MLP(z(F))).

    ``fast_path`` (default True): the features and the output head run as warp kernels with
    hand-written adjoints (``gca.laws.fused``) where warp can run (CUDA, or a CPU with warp's
    compiler); False, or elsewhere, uses the torch reference below. Both give the same values and
    gradients to rounding; the flag is an implementation choice, not part of the checkpoint.

    ``mlp_kernel`` (on the fast path): ``torch`` (default) runs the MLP as torch's ``nn.Sequential``; ``warp`` as one
    warp tile kernel each way (``gca.laws.mlp_kernel.mlp``), ``simt`` its forward one thread per particle with torch's
    backward from the stored pre-activations (``gca.laws.mlp_kernel.simt_mlp``); both two hidden layers only.
    Measured on an H100 at 30k particles (``benchmarks/NOTES.md`` session 34) the tile kernel is slower (forward +
    backward 215 vs 124 us), and so is ``simt`` (forward 165.7 vs 34.5 us, session 35). ``triton_tf32``: one fused
    Triton kernel each way with TF32 products (``gca.laws.mlp_triton``; exact GELU only): faster (1.44x forward +
    backward, 4.3x forward at 8 processes, H200, session 37) but **not the same numbers** (TF32's 10-bit mantissa in
    every product): a precision change, which the calibration scenes decided for in session 44 (params.yaml's paper
    profile sets it through ``train.mlp_kernel``; this class's own default stays torch, as on the CI profile).
    """

    fast_path: bool = True
    mlp_kernel: str = "torch"
    _frame_mlp = None  # inside frame_mlp_sums(): (FrameSum, the frame's weights) of gca.laws.mlp_triton
    _mlp_stash = None  # inside frame_mlp_stash(): this network's MLPStash for the frame

    def __init__(self, cfg: NeuralLawConfig | None = None):
        super().__init__()
        self.cfg = cfg if cfg is not None else NeuralLawConfig()
        self.mlp = make_mlp(self.cfg)

    def _check_dtype(self, F: torch.Tensor) -> None:
        weight = self.mlp[0].weight
        if F.dtype != weight.dtype:
            raise TypeError(f"gca/laws/neural.py: {type(self).__name__}: F is {F.dtype} but the network is "
                            f"{weight.dtype}; call .to({F.dtype}) on the law")

    def _fused(self, F: torch.Tensor) -> bool:
        return self.fast_path and warp_runs(F)

    def fused_network(self, F: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Fast path: F -> (R [N,3,3], X [N,9] raw MLP output), features in one warp kernel."""
        self._check_dtype(F)
        R, z = fused.features(F)
        return R, self.run_mlp(z)

    def run_mlp(self, z: torch.Tensor) -> torch.Tensor:
        """X [N, 9] = MLP(z [N, 13]) with the layers' effective (LoRA-merged) weights, on the kernel ``mlp_kernel``
        picks."""
        if self.mlp_kernel not in MLP_KERNELS:
            raise ValueError(f"gca/laws/neural.py: {type(self).__name__}.mlp_kernel={self.mlp_kernel!r} is not one "
                             f"of {MLP_KERNELS}")
        if self.mlp_kernel == "torch":
            return self.mlp(z)
        if self.mlp_kernel == "triton_tf32":  # its own check: the exact GELU only (mlp_triton.check)
            return _triton_mlp(self.mlp, z, self._frame_mlp, self._mlp_stash)
        shape = mlp_kernel.shape_of(self.mlp)
        if shape is None:
            raise ValueError(f"gca/laws/neural.py: mlp_kernel={self.mlp_kernel!r} fuses two hidden layers with one of "
                             f"{mlp_kernel.ACTIVATIONS}, not {self.mlp}")
        weights = [effective_weight(layer) for layer in self.mlp[0::2]]
        if self.mlp_kernel == "simt":
            return mlp_kernel.simt_mlp(z, weights, shape, self.mlp[1])
        return mlp_kernel.mlp(z, weights, shape)

    def rotation_and_stretch(self, F: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """F [N,3,3] -> (R [N,3,3] polar rotation, S [N,3,3] symmetric network output) (torch reference)."""
        self._check_dtype(F)
        U, sigma, Vh = svd(F)
        R = bmm3(U, Vh)
        X = self.mlp(invariant_features(F, sigma)).reshape(-1, 3, 3)
        return R, 0.5 * (X + X.transpose(1, 2))


def neural_networks(material) -> list[_InvariantNetwork]:
    """The neural elasticity and plasticity networks inside ``material`` (an ``nn.Module``; none otherwise), in module
    order."""
    mods = material.modules() if isinstance(material, nn.Module) else ()
    return [m for m in mods if isinstance(m, _InvariantNetwork)]


class NeuralElasticity(_InvariantNetwork, Elasticity):
    """Neural elasticity: F_e [N,3,3] -> Kirchhoff stress tau = stress_scale * R S F^T [N,3,3] (Pa)."""

    def forward(self, F: torch.Tensor) -> torch.Tensor:
        """Kirchhoff stress of elastic deformation gradients.

        Args:
            F: elastic deformation gradients [N, 3, 3].

        Returns:
            tau [N, 3, 3] in Pa; exactly 0 where F = I.
        """
        check_F(F, "NeuralElasticity.forward")
        if self._fused(F):
            R, X = self.fused_network(F)
            return fused.elastic_head(X, R, F, self.cfg.stress_scale)
        R, S = self.rotation_and_stretch(F)
        P = self.cfg.stress_scale * bmm3(R, S)
        return bmm3(P, F.transpose(1, 2))

    def wave_speed(self, rho, strain: float = 1e-2) -> float:
        """Estimated largest wave speed sqrt(M / rho) [m/s] for the CFL check.

        M (Pa) is the largest |tau| entry per unit strain over six uniaxial (+-strain along x, y, z)
        and six simple-shear probes; for an isotropic linear law it is the P-wave modulus lam + 2 mu.

        Args:
            rho: density [kg/m^3], scalar or [N] (the smallest is used).
            strain: probe strain magnitude [1].
        """
        weight = self.mlp[0].weight
        eye = torch.eye(3, dtype=weight.dtype, device=weight.device)
        probes = [eye + sign * strain * torch.outer(eye[a], eye[b])
                  for sign in (1.0, -1.0) for a, b in ((0, 0), (1, 1), (2, 2), (0, 1), (1, 2), (2, 0))]
        with torch.no_grad():
            M = float(self(torch.stack(probes)).abs().max()) / strain
        rho_min = float(torch.as_tensor(rho).min())
        if not (rho_min > 0 and math.isfinite(M)):
            raise ValueError(f"gca/laws/neural.py: wave_speed: need rho > 0 and a finite stress, got "
                             f"rho_min={rho_min}, modulus={M}")
        return math.sqrt(M / rho_min)


class NeuralPlasticity(_InvariantNetwork, Plasticity):
    """Neural plasticity (residual return map): F_trial [N,3,3] -> F_e = F_trial + alpha R S [N,3,3]."""

    def forward(self, F: torch.Tensor) -> torch.Tensor:
        """Project trial deformation gradients.

        Args:
            F: trial deformation gradients [N, 3, 3].

        Returns:
            F_e [N, 3, 3]; exactly I where F = I.
        """
        check_F(F, "NeuralPlasticity.forward")
        if self._fused(F):
            R, X = self.fused_network(F)
            return fused.plastic_head(X, R, F, self.cfg.alpha)
        R, S = self.rotation_and_stretch(F)
        return F + self.cfg.alpha * bmm3(R, S)
