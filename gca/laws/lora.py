"""Low-rank adaptation (LoRA) of the neural constitutive laws: ``E_theta = E_0 + Delta E_theta``.

Every ``nn.Linear`` of a prior network is wrapped by :class:`LoRALinear`::

    y = W x + scale * (alpha / r) * B (A x),      A [r, in] Kaiming-uniform, B [out, r] = 0,

with the base weight ``W`` frozen. Because ``B = 0`` at creation the adapted law equals the prior bit
for bit, and because no layer has a bias the adapted law keeps zero stress at rest. ``scale`` is an
inference-time multiplier on the low-rank delta (0 = prior, 1 = trained adapter, >1 extrapolates: the
NeuMA "dynamics interpolation"). Hu et al. 2022 (LoRA), microsoft/loralib ``layers.py``; NeuMA uses
r = 16, alpha = 16 on all three layers of both networks.

Why our own module instead of ``peft``: ``peft`` is not installed, it pulls transformers, accelerate
and huggingface_hub (~170 MB, ~5 s import) for what is ~100 lines here, and its module-name targeting
and state-dict key rewriting would leak into our checkpoints. A LoRA layer with zero biases, a scale
knob and merge is all the paper needs.
"""

from __future__ import annotations

import contextlib
import dataclasses
import math
from typing import Iterator

import torch
from torch import nn
from torch.nn import functional as TF


@dataclasses.dataclass(frozen=True)
class LoRAConfig:
    """LoRA hyper-parameters (params.yaml ``laws.lora``).

    Attributes:
        rank: rank r of the update B A (paper/NeuMA: 16).
        alpha: LoRA alpha; the delta is scaled by alpha / r (paper/NeuMA: 16, i.e. scaling 1).
    """

    rank: int = 16  # rank r of every adapter [count]
    alpha: float = 16.0  # delta scaling numerator; scaling = alpha / rank [dimensionless]

    def __post_init__(self):
        if not (isinstance(self.rank, int) and self.rank > 0):
            raise ValueError(f"gca/laws/lora.py: LoRAConfig.rank must be a positive int, got {self.rank!r}")
        if not self.alpha > 0:
            raise ValueError(f"gca/laws/lora.py: LoRAConfig.alpha must be > 0, got {self.alpha!r}")


class LoRALinear(nn.Module):
    """A frozen linear layer plus a trainable low-rank delta ``(alpha / r) * B A``.

    The state-dict keys of the base layer (``weight``, ``bias``) are kept, so a LoRA-wrapped network
    still loads and exposes the prior's weights under the same names; the adapter adds ``lora_A``
    and ``lora_B``.

    Args:
        base: the layer to adapt; its weight (and bias) are shared, not copied, and frozen.
        rank: r.
        alpha: LoRA alpha (delta scaled by alpha / r).
        generator: optional RNG for A's Kaiming-uniform init (reproducible adapters).
    """

    def __init__(self, base: nn.Linear, rank: int, alpha: float, generator: torch.Generator | None = None):
        super().__init__()
        LoRAConfig(rank, alpha)  # validates
        self.in_features, self.out_features = base.in_features, base.out_features
        self.rank, self.alpha = int(rank), float(alpha)
        self.scaling = self.alpha / self.rank
        self.scale = 1.0  # inference multiplier on the delta (0 = prior)
        self.weight = base.weight
        self.bias = base.bias
        self.weight.requires_grad_(False)
        if self.bias is not None:
            self.bias.requires_grad_(False)
        factory = dict(dtype=base.weight.dtype, device=base.weight.device)
        self.lora_A = nn.Parameter(torch.empty(self.rank, self.in_features, **factory))
        self.lora_B = nn.Parameter(torch.zeros(self.out_features, self.rank, **factory))
        self._init_A(generator)
        self._merged: torch.Tensor | None = None  # W + delta while inside merged_weights() [out, in]

    def _init_A(self, generator: torch.Generator | None) -> None:
        """Kaiming-uniform(a=sqrt(5)) on A (nn.Linear's default, as in loralib)."""
        bound = 1.0 / math.sqrt(self.in_features)  # = gain * sqrt(3 / fan_in) for a = sqrt(5)
        with torch.no_grad():
            self.lora_A.uniform_(-bound, bound, generator=generator)

    def delta_weight(self) -> torch.Tensor:
        """The effective weight update ``scale * (alpha / r) * B A``, [out, in]."""
        return (self.scale * self.scaling) * (self.lora_B @ self.lora_A)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """``(W + scale * (alpha / r) * B A) x + b``; x [..., in] -> [..., out].

        The delta is merged into the weight first (an [out, r] x [r, in] product), so a batch of N
        particles costs one [N, in] x [in, out] product forward and two backward, instead of three
        and five through the low-rank path; A and B get their gradients from the merged weight's.
        Inside :func:`merged_weights` the merged weight is the one formed on entering the block.
        """
        return TF.linear(x, self.effective_weight(), self.bias)

    def effective_weight(self) -> torch.Tensor:
        """The weight this layer applies now [out, in]: the block's merge inside :func:`merged_weights`, else
        ``W + scale (alpha / r) B A`` (``W`` itself at scale 0)."""
        if self._merged is not None:
            return self._merged
        return self.weight if self.scale == 0.0 else self.weight + self.delta_weight()

    def forward_lowrank(self, x: torch.Tensor) -> torch.Tensor:
        """Reference of :meth:`forward` through the rank-r path ``W x + b + scale (alpha / r) B (A x)``
        (same values to rounding; three [N, .] products forward instead of one)."""
        y = TF.linear(x, self.weight, self.bias)
        return y + (self.scale * self.scaling) * TF.linear(TF.linear(x, self.lora_A), self.lora_B)

    def merge(self) -> nn.Linear:
        """A plain frozen ``nn.Linear`` with weight ``W + scale * (alpha/r) * B A`` (deployment)."""
        merged = nn.Linear(self.in_features, self.out_features, bias=self.bias is not None,
                           dtype=self.weight.dtype, device=self.weight.device)
        with torch.no_grad():
            merged.weight.copy_(self.weight + self.delta_weight())
            if self.bias is not None:
                merged.bias.copy_(self.bias)
        merged.requires_grad_(False)
        return merged

    def extra_repr(self) -> str:
        return (f"in_features={self.in_features}, out_features={self.out_features}, rank={self.rank}, "
                f"alpha={self.alpha}, scale={self.scale}")


def effective_weight(layer: nn.Module) -> torch.Tensor:
    """The weight a linear layer applies now [out, in]: a plain ``nn.Linear``'s, or
    :meth:`LoRALinear.effective_weight`."""
    return layer.effective_weight() if isinstance(layer, LoRALinear) else layer.weight


def _replace_children(module: nn.Module, make) -> int:
    """Recursively replace children for which ``make(child)`` is not None; returns the count."""
    count = 0
    for name, child in module.named_children():
        new = make(child)
        if new is not None:
            setattr(module, name, new)
            count += 1
        else:
            count += _replace_children(child, make)
    return count


def lora_layers(module: nn.Module) -> list[LoRALinear]:
    """All :class:`LoRALinear` layers of ``module`` in registration order."""
    return [m for m in module.modules() if isinstance(m, LoRALinear)]


def apply_lora(module: nn.Module, rank: int = 16, alpha: float = 16.0,
               generator: torch.Generator | None = None) -> nn.Module:
    """Wrap every ``nn.Linear`` of ``module`` (in place) with LoRA and freeze everything else.

    Args:
        module: a prior network (e.g. ``NeuralElasticity``); must contain at least one nn.Linear
            and no LoRA layer yet.
        rank: LoRA rank r.
        alpha: LoRA alpha (delta scaled by alpha / r).
        generator: optional RNG for the A matrices.

    Returns:
        ``module`` itself; only ``lora_A``/``lora_B`` require gradients afterwards.
    """
    if lora_layers(module):
        raise ValueError(f"gca/laws/lora.py: apply_lora: {type(module).__name__} already has LoRA layers")
    module.requires_grad_(False)

    def make(child):
        return LoRALinear(child, rank, alpha, generator) if type(child) is nn.Linear else None

    if _replace_children(module, make) == 0:
        raise ValueError(f"gca/laws/lora.py: apply_lora: {type(module).__name__} has no nn.Linear to adapt")
    return module


@contextlib.contextmanager
def merged_weights(module: nn.Module):
    """Within the block, every :class:`LoRALinear` of ``module`` uses ``W + scale (alpha/r) B A`` formed
    once on entry, instead of forming it on every call.

    A simulation frame evaluates each network once per MPM step (20 steps per frame at the paper profile):
    forming the merged weight per call costs three kernels per layer forward and about five backward, per
    step. Formed once per frame, autograd sums the steps' gradients of the merged weight and takes them
    through the product ``B A`` once. Values and gradients are those of the per-call merge (sums reordered).
    The merge is differentiable and happens inside the block's caller, so a checkpointed or CUDA-graphed
    frame that recomputes the block also recomputes it (with whatever parameters are bound then, e.g.
    ``torch.func.functional_call`` aliases). Nested blocks reuse the outermost merge. A module without
    LoRA layers (or any object that is not an ``nn.Module``) is left alone.
    """
    found = lora_layers(module) if isinstance(module, nn.Module) else []
    layers = [layer for layer in found if layer._merged is None and layer.scale != 0.0]
    for layer in layers:
        layer._merged = layer.weight + layer.delta_weight()
    try:
        yield module
    finally:
        for layer in layers:
            layer._merged = None


def lora_parameters(module: nn.Module) -> Iterator[nn.Parameter]:
    """The adapter parameters (``lora_A``, ``lora_B`` of every layer) of ``module``."""
    for layer in lora_layers(module):
        yield layer.lora_A
        yield layer.lora_B


def lora_state_dict(module: nn.Module) -> dict[str, torch.Tensor]:
    """Only the adapter entries of ``module.state_dict()`` (keys ending in lora_A / lora_B)."""
    return {k: v.detach().clone() for k, v in module.state_dict().items()
            if k.rsplit(".", 1)[-1] in ("lora_A", "lora_B")}


def set_lora_scale(module: nn.Module, scale: float) -> nn.Module:
    """Set the inference multiplier of every adapter (0 = prior, 1 = as trained); returns module."""
    layers = lora_layers(module)
    if not layers:
        raise ValueError(f"gca/laws/lora.py: set_lora_scale: {type(module).__name__} has no LoRA layers")
    for layer in layers:
        layer.scale = float(scale)
    return module


def merge_lora(module: nn.Module) -> nn.Module:
    """Replace every :class:`LoRALinear` by its merged plain ``nn.Linear`` (in place); returns module.

    The result has the prior's architecture and state-dict keys, so it can be saved as a prior.
    """
    if _replace_children(module, lambda c: c.merge() if isinstance(c, LoRALinear) else None) == 0:
        raise ValueError(f"gca/laws/lora.py: merge_lora: {type(module).__name__} has no LoRA layers")
    return module


def full_finetune(module: nn.Module) -> nn.Module:
    """Make every base weight of a (LoRA-free) network trainable: the paper's "Full F.T." row."""
    if lora_layers(module):
        raise ValueError("gca/laws/lora.py: full_finetune: module has LoRA layers; merge_lora() it first "
                         "or fine-tune a fresh prior")
    return module.requires_grad_(True)


def count_trainable(module: nn.Module) -> int:
    """Number of scalar parameters of ``module`` with ``requires_grad``."""
    return sum(p.numel() for p in module.parameters() if p.requires_grad)
