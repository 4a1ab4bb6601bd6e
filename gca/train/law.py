"""The learnable law of a method: a neural prior (LoRA / full fine-tune / frozen) or an explicit law.

``build_law`` returns a :class:`LearnedLaw`: the material the simulator calls, the parameter groups
the optimiser trains, and ``state()`` / ``load_state()`` for checkpoints and evaluation.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Mapping

import torch
from torch import nn

from gca.laws.base import Material
from gca.laws.checkpoint import load_prior
from gca.laws.lora import LoRAConfig, apply_lora, full_finetune, lora_parameters, lora_state_dict
from gca.laws.presets import material_from_preset
from gca.train.methods import Method


@dataclasses.dataclass
class LearnedLaw:
    """A method's law.

    Attributes:
        material: what the simulator calls (``stress``, ``project``, ``wave_speed``).
        groups: optimiser parameter groups ``[{"params": [...], "lr": float, "name": str}]``.
        kind: ``lora``, ``full``, ``none`` or ``explicit``.
    """

    material: Material
    groups: list[dict]
    kind: str

    def trainable(self) -> list[nn.Parameter]:
        return [p for g in self.groups for p in g["params"]]

    def state(self) -> dict[str, torch.Tensor]:
        """Only what training changed (adapter weights, all weights, or explicit parameters)."""
        if self.kind == "lora":
            return {f"{n}.{k}": v.detach().clone() for n in ("elasticity", "plasticity")
                    for k, v in lora_state_dict(getattr(self.material, n)).items()}
        return {k: v.detach().clone() for k, v in self.material.state_dict().items()}

    def load_state(self, state: Mapping[str, torch.Tensor]) -> None:
        missing = self.material.load_state_dict(dict(state), strict=False)
        unexpected = [k for k in missing.unexpected_keys]
        if unexpected:
            raise KeyError(f"law state has keys the {self.kind} law does not: {unexpected[:5]}")


def explicit_preset(family_presets: Mapping, family: str) -> Mapping:
    """The analytic law a PAC-NeRF-style row assumes for a prior family (E, nu, plastic params fitted)."""
    if family not in family_presets:
        raise KeyError(f"no analytic preset for prior family {family!r}; have {sorted(family_presets)}")
    return family_presets[family]


def build_law(method: Method, prior_path: str | Path, family: str, rho: float, lora: LoRAConfig,
              lr_elasticity: float, lr_plasticity: float, lr_explicit: float,
              family_presets: Mapping | None = None, dt: float | None = None, seed: int = 0) -> LearnedLaw:
    """Build the law ``method`` trains, starting from the prior at ``prior_path`` (family ``family``).

    LoRA's A matrices are drawn from generators seeded by ``seed`` (``train.seed``; elasticity 2 seed,
    plasticity 2 seed + 1), so a run is reproducible; they were drawn from torch's unseeded global RNG until
    session 8, which made every training run (Table 1 of session 8 included) one random draw of them."""
    if method.law == "explicit":
        material = material_from_preset(explicit_preset(family_presets or {}, family), dt=dt)
        params = [p for p in material.parameters() if p.requires_grad]
        return LearnedLaw(material, [{"params": params, "lr": lr_explicit, "name": "explicit"}], "explicit")
    prior = load_prior(prior_path, family=family)
    e, p = prior.elasticity, prior.plasticity
    if method.adapt == "lora":
        for i, net in enumerate((e, p)):
            apply_lora(net, lora.rank, lora.alpha, generator=torch.Generator().manual_seed(2 * int(seed) + i))
        pe, pp = list(lora_parameters(e)), list(lora_parameters(p))
    elif method.adapt == "full":
        pe, pp = list(full_finetune(e).parameters()), list(full_finetune(p).parameters())
    else:
        for q in list(e.parameters()) + list(p.parameters()):
            q.requires_grad_(False)
        pe, pp = [], []
    groups = [g for g in ({"params": pe, "lr": lr_elasticity, "name": "elasticity"},
                          {"params": pp, "lr": lr_plasticity, "name": "plasticity"}) if g["params"]]
    return LearnedLaw(Material(e, p, rho), groups, method.adapt)
