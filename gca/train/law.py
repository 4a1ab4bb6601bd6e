"""The learnable law of a method: a neural prior (LoRA / full fine-tune / frozen) or an explicit law.

``build_law`` returns a :class:`LearnedLaw`: the material the simulator calls, the parameter groups
the optimiser trains, and ``state()`` / ``load_state()`` for checkpoints and evaluation.

An explicit (PAC-NeRF-style) law takes the form of the scene's material *category* (:data:`CATEGORY_LAWS`,
the category from ``gca.laws.presets.material_category``: ground-truth knowledge PAC-NeRF assumes given) and
learns what PAC-NeRF learns: one Young's modulus E and one Poisson's ratio nu shared by the elastic and plastic
parts, the category's plastic constant (yield stress; friction angle; yield stress and viscosity), and the
launch velocity (v0, w0), initialised from the shared estimate (:class:`LaunchVelocity`).
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Mapping

import torch
from torch import nn
from torch.nn.utils import parametrize

from gca.laws.base import Material
from gca.laws.checkpoint import load_prior
from gca.laws.lora import LoRAConfig, apply_lora, full_finetune, lora_parameters, lora_state_dict
from gca.laws.presets import material_from_preset
from gca.scenes.world import initial_velocity
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
    launch: "LaunchVelocity | None" = None  # a learned launch velocity (explicit rows); None: the shared estimate

    def trainable(self) -> list[nn.Parameter]:
        return [p for g in self.groups for p in g["params"]]

    def initial_velocity(self, x0: torch.Tensor, shared: torch.Tensor) -> torch.Tensor:
        """The rollout's initial velocity field [P, 3]: the learned launch's, else ``shared`` (the estimate's)."""
        return shared if self.launch is None else self.launch.field(x0)

    def launch_velocity(self, shared: tuple[list, list]) -> tuple[list, list]:
        """(v0, w0) the law is evaluated from: the learned launch's, else the ``shared`` estimate."""
        if self.launch is None:
            return shared
        return self.launch.v0.detach().cpu().tolist(), self.launch.w0.detach().cpu().tolist()

    def state(self) -> dict[str, torch.Tensor]:
        """Only what training changed (adapter weights, all weights, or explicit parameters and launch)."""
        if self.kind == "lora":
            return {f"{n}.{k}": v.detach().clone() for n in ("elasticity", "plasticity")
                    for k, v in lora_state_dict(getattr(self.material, n)).items()}
        state = {k: v.detach().clone() for k, v in self.material.state_dict().items()}
        if self.launch is not None:
            state.update({f"launch.{k}": v.detach().clone() for k, v in self.launch.state_dict().items()})
        return state

    def load_state(self, state: Mapping[str, torch.Tensor]) -> None:
        state = dict(state)
        launch = {k[len("launch."):]: state.pop(k) for k in list(state) if k.startswith("launch.")}
        if self.launch is not None:
            self.launch.load_state_dict(launch)  # strict: a learned launch must be in the state
        elif launch:
            raise KeyError(f"law state has a launch velocity the {self.kind} law does not learn")
        missing = self.material.load_state_dict(state, strict=False)
        unexpected = [k for k in missing.unexpected_keys]
        if unexpected:
            raise KeyError(f"law state has keys the {self.kind} law does not: {unexpected[:5]}")
        if self.kind == "explicit" and missing.missing_keys:
            raise KeyError(f"explicit law state lacks {missing.missing_keys[:5]} (another category's law?)")


class LaunchVelocity(nn.Module):
    """A learnable rigid launch: v(x) = v0 + w0 x (x - com) (``gca.scenes.world.initial_velocity``).

    Args:
        v0: linear velocity [3] (m/s, sim frame); w0: angular velocity about the centre of mass [3] (rad/s).
    """

    def __init__(self, v0, w0):
        super().__init__()
        self.v0 = nn.Parameter(torch.as_tensor(v0, dtype=torch.get_default_dtype()).clone().reshape(3))
        self.w0 = nn.Parameter(torch.as_tensor(w0, dtype=torch.get_default_dtype()).clone().reshape(3))

    def forward(self, x0: torch.Tensor) -> torch.Tensor:
        """Initial velocity [P, 3] of particles at ``x0`` [P, 3]; differentiable in v0, w0."""
        return initial_velocity(x0, self.v0.to(x0.dtype), self.w0.to(x0.dtype))

    field = forward


#: The explicit law a PAC-NeRF-style row fits for each material category (PAC-NeRF's own models: Neo-Hookean
#: elasticity; plasticine = von Mises on Hencky strain; sand = Drucker-Prager; non-Newtonian = viscoplastic,
#: here Bingham, flow index 1), with the plastic constants it learns.
CATEGORY_LAWS: dict[str, dict] = {
    "elastic": {"elasticity": "neo_hookean", "plasticity": "identity", "learns": ()},
    "plastic": {"elasticity": "sigma", "plasticity": "von_mises", "learns": ("yield_stress",)},
    "granular": {"elasticity": "sigma", "plasticity": "drucker_prager", "learns": ("friction_angle",)},
    "viscoplastic": {"elasticity": "sigma", "plasticity": "viscoplastic", "learns": ("yield_stress", "viscosity")},
}
#: Initial plastic constants where the scene's prior family has none (NCLaw's presets: plasticine yield stress
#: 5e3 Pa, sand friction angle 25 deg). The viscosity has no reference value: 10 Pa s is this project's choice.
CATEGORY_INIT = {"yield_stress": 5.0e3, "friction_angle": 25.0, "viscosity": 10.0}
NU_RANGE = (0.0, 0.49)  # Poisson's ratio is learned inside this interval [1]
FRICTION_RANGE = (1.0, 60.0)  # friction angle is learned inside this interval [deg] (CPR's range)


class _Interval(nn.Module):
    """Parametrization: an unconstrained value -> (lo, hi) through a sigmoid (``right_inverse``: the logit)."""

    def __init__(self, lo: float, hi: float):
        super().__init__()
        self.lo, self.hi = lo, hi

    def forward(self, raw: torch.Tensor) -> torch.Tensor:
        return self.lo + (self.hi - self.lo) * torch.sigmoid(raw)

    def right_inverse(self, value: torch.Tensor) -> torch.Tensor:
        return torch.logit((value - self.lo) / (self.hi - self.lo))


class _Exp(nn.Module):
    """Parametrization: log value -> value (``right_inverse``: the log)."""

    def forward(self, raw: torch.Tensor) -> torch.Tensor:
        return torch.exp(raw)

    def right_inverse(self, value: torch.Tensor) -> torch.Tensor:
        return torch.log(value)


def _learn(module: nn.Module, name: str, parametrization: nn.Module) -> nn.Parameter:
    """Make ``module.<name>`` (a buffer or parameter) learnable through ``parametrization``; returns the raw
    parameter it is computed from."""
    value = getattr(module, name).detach().clone()
    module._buffers.pop(name, None)
    module._parameters.pop(name, None)
    module.register_parameter(name, nn.Parameter(value))
    parametrize.register_parametrization(module, name, parametrization)
    return getattr(module.parametrizations, name).original


def category_law(category: str, init: Mapping, rho: float, dt: float | None) -> Material:
    """The explicit law of a material ``category`` (:data:`CATEGORY_LAWS`), its constants from ``init`` (a preset
    mapping: E, nu and any plastic constant; missing plastic constants from :data:`CATEGORY_INIT`), with
    learnable log E and nu shared by the elastic and plastic parts, and learnable plastic constants."""
    if category not in CATEGORY_LAWS:
        raise KeyError(f"no explicit law for material category {category!r}; have {sorted(CATEGORY_LAWS)}")
    form = CATEGORY_LAWS[category]
    preset = {"elasticity": form["elasticity"], "plasticity": form["plasticity"], "E": float(init["E"]),
              "nu": float(init["nu"]), "rho": float(rho)}
    for key in form["learns"]:
        preset[key] = float(init[key]) if init.get(key) is not None else CATEGORY_INIT[key]
    material = material_from_preset(preset, dt=dt)
    e, p = material.elasticity, material.plasticity
    e.log_E.requires_grad_(True)
    raw_nu = _learn(e, "nu", _Interval(*NU_RANGE))
    if hasattr(p, "log_E"):  # one E and one nu for the whole material
        p.log_E = e.log_E
        _learn(p, "nu", _Interval(*NU_RANGE))
        p.parametrizations.nu.original = raw_nu
    if form["plasticity"] == "von_mises":
        p.log_yield_stress.requires_grad_(True)
    elif form["plasticity"] == "drucker_prager":
        _learn(p, "friction_angle", _Interval(*FRICTION_RANGE))
    elif form["plasticity"] == "viscoplastic":
        _learn(p, "yield_stress", _Exp())
        _learn(p, "viscosity", _Exp())
    return material


def explicit_preset(family_presets: Mapping, family: str) -> Mapping:
    """The prior family's analytic preset: where a PAC-NeRF-style row's E, nu (and plastic constants) start."""
    if family not in family_presets:
        raise KeyError(f"no analytic preset for prior family {family!r}; have {sorted(family_presets)}")
    return family_presets[family]


def build_law(method: Method, prior_path: str | Path, family: str, rho: float, lora: LoRAConfig,
              lr_elasticity: float, lr_plasticity: float, lr_explicit: float,
              family_presets: Mapping | None = None, dt: float | None = None, seed: int = 0,
              category: str | None = None, velocity: tuple | None = None) -> LearnedLaw:
    """Build the law ``method`` trains, starting from the prior at ``prior_path`` (family ``family``).

    LoRA's A matrices are drawn from generators seeded by ``seed`` (``train.seed``; elasticity 2 seed,
    plasticity 2 seed + 1), so a run is reproducible (the history of this choice: benchmarks/NOTES.md).

    An explicit method needs the scene's material ``category`` (:func:`category_law`; its E, nu and plastic
    constants start from the prior family's preset) and learns the launch from ``velocity`` = (v0, w0), the
    shared estimate (None: zeros, for a law whose trained state is loaded next). Both groups train at
    ``lr_explicit`` (Adam on log E, logit nu, log yield stress, ..., and on v0 [m/s], w0 [rad/s])."""
    if method.law == "explicit":
        if category is None:
            raise ValueError(f"method {method.name!r} fits an explicit law: pass the scene's material category")
        material = category_law(category, explicit_preset(family_presets or {}, family), rho, dt)
        params = [p for p in material.parameters() if p.requires_grad]  # deduplicated: E and nu are shared
        launch = LaunchVelocity(*(velocity if velocity is not None else ([0.0] * 3, [0.0] * 3)))
        groups = [{"params": params, "lr": lr_explicit, "name": "explicit"},
                  {"params": list(launch.parameters()), "lr": lr_explicit, "name": "launch"}]
        return LearnedLaw(material, groups, "explicit", launch)
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
