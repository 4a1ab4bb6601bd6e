"""gca.laws: constitutive laws F -> Kirchhoff stress tau = P F^T and plastic return maps F_trial -> F_e.

Analytic part (this package's modules): ``svd`` (rotation-valued SVD with safe gradients),
``elastic`` / ``plastic`` (the CPR hypothesis sets H_e, H_p as pure functions and modules),
``ground_truth`` (laws outside the hypothesis library), ``base`` (interfaces, Material,
CompositeMaterial), ``presets`` (materials from params). Neural laws live in ``neural`` / ``lora``.
"""

from gca.laws.base import CompositeMaterial, Elasticity, Material, Plasticity, lame
from gca.laws.elastic import ELASTIC_FORMS, corotated_tau, sigma_tau, stvk_tau, volume_tau
from gca.laws.ood import neo_hookean_tau, viscoplastic_plastic
from gca.laws.plastic import (PLASTIC_FORMS, drucker_prager_plastic, identity_plastic, sigma_plastic,
                              von_mises_plastic)
from gca.laws.presets import MaterialPreset, material_from_preset
from gca.laws.svd import polar_rotation, svd, svd_map

__all__ = ["CompositeMaterial", "Elasticity", "Material", "Plasticity", "lame", "ELASTIC_FORMS", "corotated_tau",
           "sigma_tau", "stvk_tau", "volume_tau", "neo_hookean_tau", "viscoplastic_plastic", "PLASTIC_FORMS",
           "drucker_prager_plastic", "identity_plastic", "sigma_plastic", "von_mises_plastic", "MaterialPreset",
           "material_from_preset", "polar_rotation", "svd", "svd_map"]
