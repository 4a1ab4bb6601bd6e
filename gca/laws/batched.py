"""Several runs' neural laws evaluated as one batch (issue 20's batched trainer: the laws of B runs in one launch).

B runs of the same neural architecture, each with its own weights (its LoRA adapters), on B equal contiguous
particle slices (run r owns rows r n .. (r + 1) n - 1). Per call, instead of B x (~20 kernels per network):

    R, z = features(F)                      one warp kernel (and one SVD kernel) over all B n particles
    h = z.reshape(B, n, 13)
    h = act(bmm(h, W_l^T))                  one batched product per layer, W_l = stack of the runs' merged weights
    tau = elastic_head(X, R, F)  |  F_e = plastic_head(X, R, F)   one warp kernel over all particles

Each run's rows see only its own weights, so run r's outputs and gradients are those of its law alone (to rounding:
a batched product may sum in another order; tested against :class:`gca.laws.base.CompositeMaterial`). Inside
:func:`gca.laws.lora.merged_weights` (a simulated frame) the merged weights are formed once per frame, as for one run.
"""

from __future__ import annotations

from typing import Sequence

import torch
from torch import nn

from gca.laws import fused
from gca.laws.base import CompositeMaterial, Elasticity, Material, Plasticity
from gca.laws.lora import LoRALinear, effective_weight
from gca.laws.neural import NeuralElasticity, NeuralPlasticity
from gca.laws.svd import warp_runs

_WHERE = "gca/laws/batched.py"


class _BatchedLinear(torch.autograd.Function):
    """h [B, n, in], W [B, out, in] -> h W^T [B, n, out] with the weights' gradient taken run by run.

    The weight gradient of run r is dY_r^T h_r, a [out, n] x [n, in] product with n ~ 3e4: cuBLAS splits that long
    sum over many thread blocks for one product (``mm``), but a batched product over B such runs (the autograd of
    ``bmm``) ran on a handful of blocks, 10x slower than the whole rest of a step on an H100 (session 13). So the
    forward and the input gradient are batched products, the weight gradient B plain ones.
    """

    @staticmethod
    def forward(ctx, h, W):
        ctx.save_for_backward(h, W)
        return torch.bmm(h, W.transpose(1, 2))

    @staticmethod
    def backward(ctx, dY):
        h, W = ctx.saved_tensors
        dh = torch.bmm(dY, W) if ctx.needs_input_grad[0] else None
        dW = torch.stack([dY[r].T @ h[r] for r in range(h.shape[0])]) if ctx.needs_input_grad[1] else None
        return dh, dW


def batched_linear(h: torch.Tensor, W: torch.Tensor) -> torch.Tensor:
    """h [B, n, in] times the runs' weights W [B, out, in]: [B, n, out] (differentiable in both)."""
    return _BatchedLinear.apply(h, W)


def batched_mlp(nets: Sequence[nn.Module], z: torch.Tensor) -> torch.Tensor:
    """The runs' MLPs on their row blocks of ``z`` [B n, in] -> [B n, out], one ``bmm`` per layer (torch's products
    whatever the networks' ``mlp_kernel``: the warp MLP kernels take one run's weights)."""
    B = len(nets)
    h = z.reshape(B, z.shape[0] // B, z.shape[1])
    for layers in zip(*(net.mlp for net in nets)):
        if isinstance(layers[0], (nn.Linear, LoRALinear)):
            h = batched_linear(h, torch.stack([effective_weight(layer) for layer in layers]))
            if layers[0].bias is not None:
                h = h + torch.stack([layer.bias for layer in layers])[:, None, :]
        else:  # the activation: the same parameter-free module in every run (checked at construction)
            h = layers[0](h)
    return h.reshape(z.shape[0], -1)


class _Batched(nn.Module):
    def __init__(self, nets: Sequence[nn.Module], count: int):
        super().__init__()
        nets = list(nets)
        if not nets or len({type(n) for n in nets}) != 1 or len({n.cfg for n in nets}) != 1 or count < 0:
            raise ValueError(f"{_WHERE}: batched laws need >= 1 networks of one class and one NeuralLawConfig and a "
                             f"count >= 0, got {[type(n).__name__ for n in nets]}, count {count}")
        self.nets, self.count = nn.ModuleList(nets), int(count)

    def _check(self, F: torch.Tensor) -> None:
        if F.shape[0] != self.count * len(self.nets):
            raise ValueError(f"{_WHERE}: {len(self.nets)} runs x {self.count} particles expected, got F of shape "
                             f"{tuple(F.shape)}")

    def forward(self, F: torch.Tensor) -> torch.Tensor:
        self._check(F)
        if not (all(n.fast_path for n in self.nets) and warp_runs(F)):  # reference: each run on its slice
            return torch.cat([net(Fk) for net, Fk in zip(self.nets, F.split(self.count))])
        R, z = fused.features(F)
        return self._head(batched_mlp(self.nets, z), R, F)


class BatchedElasticity(_Batched, Elasticity):
    """B runs' :class:`NeuralElasticity` on B equal particle slices: tau [B n, 3, 3] (Pa)."""

    def _head(self, X, R, F):
        return fused.elastic_head(X, R, F, self.nets[0].cfg.stress_scale)

    def wave_speed(self, rho) -> float:
        return max(net.wave_speed(rho) for net in self.nets)


class BatchedPlasticity(_Batched, Plasticity):
    """B runs' :class:`NeuralPlasticity` on B equal particle slices: F_e [B n, 3, 3]."""

    def _head(self, X, R, F):
        return fused.plastic_head(X, R, F, self.nets[0].cfg.alpha)


def runs_material(materials: Sequence[Material], counts: Sequence[int]) -> Material:
    """One material for B runs on contiguous particle slices: the neural laws batched (:class:`BatchedElasticity`,
    :class:`BatchedPlasticity`) when every run has a neural elasticity and plasticity of one architecture on slices
    of equal size, else a :class:`gca.laws.base.CompositeMaterial` (each run's law on its slice)."""
    counts = [int(c) for c in counts]
    neural = all(isinstance(m.elasticity, NeuralElasticity) and isinstance(m.plasticity, NeuralPlasticity)
                 for m in materials)
    if not (neural and len(set(counts)) == 1 and len({m.elasticity.cfg for m in materials}) == 1):
        return CompositeMaterial(materials, counts)
    rho = torch.cat([m.rho.reshape(-1).expand(c) for m, c in zip(materials, counts)])
    return Material(BatchedElasticity([m.elasticity for m in materials], counts[0]),
                    BatchedPlasticity([m.plasticity for m in materials], counts[0]), rho)
