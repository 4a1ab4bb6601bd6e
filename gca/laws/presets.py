"""Materials from preset mappings (the ``materials`` section of params.yaml).

A preset names one elastic and one plastic law and their constants::

    {elasticity: sigma, plasticity: von_mises, E: 3.0e+5, nu: 0.25, rho: 1000, yield_stress: 5.0e+3}

A composite preset lists parts, each with a ``fraction`` of the particles (contiguous index ranges,
in order; the caller orders the particles accordingly)::

    {parts: [{elasticity: corotated, ..., fraction: 0.5}, {elasticity: volume, ..., fraction: 0.5}]}
"""

from __future__ import annotations

import dataclasses
from typing import Mapping

from gca.config import ConfigError, build
from gca.laws.base import CompositeMaterial, Elasticity, Material, Plasticity
from gca.laws.elastic import CorotatedElasticity, SigmaElasticity, StVKElasticity, VolumeElasticity
from gca.laws.ood import NeoHookeanElasticity, ViscoplasticPlasticity
from gca.laws.plastic import DruckerPragerPlasticity, IdentityPlasticity, SigmaPlasticity, VonMisesPlasticity

ELASTICITIES = ("corotated", "stvk", "volume", "sigma", "neo_hookean")
PLASTICITIES = ("identity", "sigma", "von_mises", "drucker_prager", "viscoplastic")
HYPOTHESES_ELASTIC = ("corotated", "stvk", "volume", "sigma")  # CPR's H_e
HYPOTHESES_PLASTIC = ("identity", "sigma", "von_mises", "drucker_prager")  # CPR's H_p


#: A preset's material *category*, from its plastic law's name: what a PAC-NeRF-style explicit row is told
#: (PAC-NeRF picks its constitutive model per scene: elastic, plasticine, sand, non-Newtonian; the category is
#: ground-truth knowledge it assumes given). identity -> elastic, von Mises -> plastic, Drucker-Prager ->
#: granular, viscoplastic (Herschel-Bulkley) -> viscoplastic. A fluid (sigma) or composite preset has none here.
CATEGORIES = {"identity": "elastic", "von_mises": "plastic", "drucker_prager": "granular",
              "viscoplastic": "viscoplastic"}


def material_category(preset: Mapping) -> str:
    """The category (:data:`CATEGORIES`) of a homogeneous material preset mapping, from its plasticity's name."""
    if not isinstance(preset, Mapping) or "parts" in preset:
        raise ConfigError("gca/laws/presets.py: a composite (or non-mapping) material preset has no single category")
    plasticity = preset.get("plasticity", "identity")
    if plasticity not in CATEGORIES:
        raise ConfigError(f"gca/laws/presets.py: plasticity {plasticity!r} has no material category; "
                          f"known: {CATEGORIES}")
    return CATEGORIES[plasticity]


@dataclasses.dataclass(frozen=True)
class MaterialPreset:
    """One homogeneous material (a ``materials.<scene>`` entry of params.yaml)."""

    elasticity: str  # elastic law, one of ELASTICITIES
    plasticity: str = "identity"  # plastic law, one of PLASTICITIES
    E: float = 1.0e5  # Young's modulus [Pa]
    nu: float = 0.2  # Poisson's ratio [1]
    rho: float = 1000.0  # density [kg/m^3]
    yield_stress: float | None = None  # von Mises / viscoplastic yield stress [Pa]
    friction_angle: float | None = None  # Drucker-Prager friction angle [deg]
    cohesion: float = 0.0  # Drucker-Prager cohesion, log-strain offset of the cone apex [1]
    viscosity: float | None = None  # viscoplastic consistency eta [Pa s^n] (viscosity [Pa s] for n = 1)
    flow_index: float = 1.0  # viscoplastic flow index n [1] (1 = Bingham, < 1 shear-thinning)
    fraction: float | None = None  # share of the particles, only inside a composite's parts [1]

    def __post_init__(self):
        for f in dataclasses.fields(self):  # YAML 1.1 reads "1e5" as a string: coerce numbers here
            value = getattr(self, f.name)
            if f.name not in ("elasticity", "plasticity") and value is not None:
                try:
                    object.__setattr__(self, f.name, float(value))
                except (TypeError, ValueError):
                    raise ConfigError(f"gca/laws/presets.py: material preset key {f.name}={value!r} "
                                      f"is not a number") from None


def _require(preset: MaterialPreset, *names: str) -> None:
    missing = [n for n in names if getattr(preset, n) is None]
    if missing:
        raise ConfigError(f"gca/laws/presets.py: plasticity {preset.plasticity!r} needs preset keys {missing}")


def make_elasticity(p: MaterialPreset) -> Elasticity:
    """Elastic module of a preset (analytic laws get a learnable log_E)."""
    table = {"corotated": CorotatedElasticity, "stvk": StVKElasticity, "volume": VolumeElasticity,
             "sigma": SigmaElasticity, "neo_hookean": NeoHookeanElasticity}
    if p.elasticity not in table:
        raise ConfigError(f"gca/laws/presets.py: unknown elasticity {p.elasticity!r}; valid: {list(ELASTICITIES)}")
    return table[p.elasticity](E=p.E, nu=p.nu)


def make_plasticity(p: MaterialPreset, dt: float | None) -> Plasticity:
    """Plastic module of a preset; ``dt`` [s] is needed by the rate-dependent viscoplastic law."""
    if p.plasticity == "identity":
        return IdentityPlasticity()
    if p.plasticity == "sigma":
        return SigmaPlasticity()
    if p.plasticity == "von_mises":
        _require(p, "yield_stress")
        return VonMisesPlasticity(E=p.E, nu=p.nu, yield_stress=p.yield_stress)
    if p.plasticity == "drucker_prager":
        _require(p, "friction_angle")
        return DruckerPragerPlasticity(E=p.E, nu=p.nu, friction_angle=p.friction_angle, cohesion=p.cohesion)
    if p.plasticity == "viscoplastic":
        _require(p, "yield_stress", "viscosity")
        if dt is None:
            raise ConfigError("gca/laws/presets.py: plasticity 'viscoplastic' is rate dependent: pass dt [s]")
        return ViscoplasticPlasticity(p.E, p.nu, p.yield_stress, p.viscosity, p.flow_index, dt)
    raise ConfigError(f"gca/laws/presets.py: unknown plasticity {p.plasticity!r}; valid: {list(PLASTICITIES)}")


def split_counts(fractions, n_particles: int) -> list[int]:
    """Particle counts per part from fractions summing to 1 (rounded; the last part takes the rest)."""
    if abs(sum(fractions) - 1.0) > 1e-6 or min(fractions) < 0:
        raise ConfigError(f"gca/laws/presets.py: composite part fractions must be >= 0 and sum to 1, got {fractions}")
    counts = [int(round(f * n_particles)) for f in fractions[:-1]]
    return counts + [n_particles - sum(counts)]


def material_from_preset(preset: Mapping, dt: float | None = None, n_particles: int | None = None) -> Material:
    """Build a :class:`Material` (or :class:`CompositeMaterial`) from a preset mapping.

    Args:
        preset: a :class:`MaterialPreset` mapping, or ``{parts: [mapping with fraction, ...]}``.
        dt: simulation time step [s]; required by the viscoplastic law.
        n_particles: total particle count; required for composite presets.

    Returns:
        The material (float32 parameters; call ``.to(dtype, device)`` as needed).
    """
    if not isinstance(preset, Mapping):
        raise ConfigError(f"gca/laws/presets.py: a material preset must be a mapping, got {type(preset).__name__}")
    if "parts" in preset:
        return _composite_from_preset(preset, dt, n_particles)
    p = build(MaterialPreset, preset, "material preset", partial=True)
    return Material(make_elasticity(p), make_plasticity(p, dt), p.rho)


def _composite_from_preset(preset: Mapping, dt: float | None, n_particles: int | None) -> CompositeMaterial:
    if set(preset) != {"parts"} or not isinstance(preset["parts"], list) or not preset["parts"]:
        raise ConfigError("gca/laws/presets.py: a composite preset is exactly {parts: [non-empty list]}")
    if n_particles is None:
        raise ConfigError("gca/laws/presets.py: a composite preset needs n_particles")
    parts = [build(MaterialPreset, part, f"material preset part {i}", partial=True) for i, part in enumerate(preset["parts"])]
    if any(p.fraction is None for p in parts):
        raise ConfigError("gca/laws/presets.py: every composite part needs a fraction")
    counts = split_counts([p.fraction for p in parts], n_particles)
    materials = [Material(make_elasticity(p), make_plasticity(p, dt), p.rho) for p in parts]
    return CompositeMaterial(materials, counts)
