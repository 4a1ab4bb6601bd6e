"""The methods registry: one name per row of the paper's tables.

Every method is trained from the same monocular data (the ``train0`` view) unless it says
``views = "multi"`` (the paper's multi-view reference rows use three training cameras).

Each method declares its loss terms (:data:`TERMS`); nothing else switches a term on or off.

| name                | law      | adapt | terms                                    | paper row |
| ------------------- | -------- | ----- | ---------------------------------------- | --------- |
| gca                 | neural   | lora  | silhouette, global, anchor, cpr (eq. 8)  | Ours |
| neuma               | neural   | lora  | color (NeuMA's recipe)                   | NeuMA (monocular) |
| neuma_multiview     | neural   | lora  | color, 3 views (NeuMA's recipe)          | NeuMA multi-view (Table 5) |
| nclaw               | neural   | none  | - (prior as is)                          | NCLaw |
| gca_full_ft         | neural   | full  | as gca                                   | Ours (Full F.T.) (Table 4) |
| pacnerf_depth       | explicit*| -     | color, depth_l1 (raw)                    | PAC-NeRF + Depth (Table 5) |
| pacnerf_depth_aligned | explicit*| -   | color, depth_l1_aligned                  | ours: Table 5's row with aligned depth |
| pacnerf_multiview   | explicit*| -     | color, 3 views                           | PAC-NeRF multi-view (Table 5) |
| no_global           | neural   | lora  | silhouette, anchor, cpr                  | Table 3 |
| no_anchor           | neural   | lora  | silhouette, global, cpr                  | Table 3 |
| rank_to_l1          | neural   | lora  | silhouette, global, anchor_l1, cpr       | Table 3 |
| no_rdga             | neural   | lora  | cpr                                      | Table 3 |
| no_cpr              | neural   | lora  | silhouette, global, anchor               | Table 3 |
| cpr_target_removed  | neural   | lora  | as gca, the scene's true hypothesis removed from CPR | Table 6 |

explicit*: the PAC-NeRF-style rows are **told the scene's ground-truth material category** (elastic, plastic,
granular, viscoplastic: ``gca.laws.presets.material_category`` of the scene's material, from its plastic law's
name) and fit that category's law (``gca.train.law.CATEGORY_LAWS``: Neo-Hookean; Hencky + von Mises; Hencky +
Drucker-Prager; Hencky + viscoplastic), learning one E and one nu, the yield stress / friction angle / yield
stress and viscosity the category has, and the launch (v0, w0) from the shared estimate. PAC-NeRF itself picks
its constitutive model per scene and learns these; the category is knowledge the GCA and NeuMA rows are not given.
"""

from __future__ import annotations

import dataclasses


class UnknownMethodError(KeyError):
    """A method name that is not in the registry."""

    def __str__(self) -> str:  # KeyError quotes its message; keep it readable
        return self.args[0]


#: The loss terms a method may declare (its ``terms``); eq. numbers are the paper's.
TERMS: dict[str, str] = {
    "color": "pixel colour L2 over every training view, x train.lambda_color (NeuMA, PAC-NeRF)",
    "depth_l1": "L1 between rendered metric depth and the scale/shift-ambiguous estimated depth in the mask, raw "
                "(two different units compared as they come), x train.lambda_depth_l1 (PAC-NeRF + depth, raw)",
    "depth_l1_aligned": "L1 between rendered depth and the estimated depth mapped onto it by the per-frame "
                        "least-squares scale and shift in the mask (MiDaS-style, not detached), "
                        "x train.lambda_depth_l1 (PAC-NeRF + depth, aligned)",
    "silhouette": "L_mask = ||M_render - M_gt||_2^2 (eq. 3), x lambda_m",
    "global": "global alignment lambda_1 ||P_render - P_gt||_2 of L_geo (eq. 7), x lambda_g",
    "anchor": "anchor-level supervision lambda_2 sum_A (-gamma_i) of L_geo (eq. 7; Spearman ranks, eq. 5-6), x lambda_g",
    "anchor_l1": "the anchor term with an L1 depth difference in place of the rank correlation (Table 3 ablation)",
    "cpr": "R_e + R_p of the constitutive prior regularizer (Algorithm 2)",
}
RDGA_TERMS = ("silhouette", "global", "anchor", "anchor_l1")


@dataclasses.dataclass(frozen=True)
class Method:
    """How one table row is trained.

    Attributes:
        name: registry key.
        law: ``neural`` (NCLaw networks) or ``explicit`` (analytic law with fitted E, nu, ...).
        adapt: ``lora``, ``full`` (all network weights) or ``none`` (no training).
        views: ``mono`` (train0 only) or ``multi`` (train0..train2).
        terms: the loss terms it optimises, keys of :data:`TERMS` (empty: it does not train on video).
        cpr_remove_target: drop the scene's ground-truth hypothesis from CPR's library.
        tables: the paper tables this method appears in.
        recipe: ``gca`` (``train`` as params give it) or ``neuma`` (NeuMA's published optimiser, learning rates,
            schedule and rollout weighting at the same iteration budget: ``gca.train.config.neuma_recipe``).
    """

    name: str
    law: str = "neural"
    adapt: str = "lora"
    views: str = "mono"
    terms: tuple[str, ...] = ()
    cpr_remove_target: bool = False
    tables: tuple[str, ...] = ()
    recipe: str = "gca"

    def __post_init__(self) -> None:
        unknown = [t for t in self.terms if t not in TERMS]
        if unknown:
            raise ValueError(f"gca/train/methods.py: method {self.name!r}: unknown loss terms {unknown}; "
                             f"known: {sorted(TERMS)}")
        if {"anchor", "anchor_l1"} <= set(self.terms):
            raise ValueError(f"gca/train/methods.py: method {self.name!r}: anchor and anchor_l1 are two forms of one term")
        if {"depth_l1", "depth_l1_aligned"} <= set(self.terms):
            raise ValueError(f"gca/train/methods.py: method {self.name!r}: depth_l1 and depth_l1_aligned are two forms of one term")
        if self.recipe not in ("gca", "neuma"):
            raise ValueError(f"gca/train/methods.py: method {self.name!r}: unknown recipe {self.recipe!r}")
        if self.cpr_remove_target and "cpr" not in self.terms:
            raise ValueError(f"gca/train/methods.py: method {self.name!r}: cpr_remove_target needs the cpr term")

    @property
    def trains(self) -> bool:
        return self.adapt != "none" or self.law == "explicit"

    def uses(self, term: str) -> bool:
        """Whether the method optimises loss term ``term`` (a key of :data:`TERMS`)."""
        if term not in TERMS:
            raise KeyError(f"unknown loss term {term!r}; known: {sorted(TERMS)}")
        return term in self.terms

    def rdga_switches(self) -> dict | None:
        """The RDGA config fields its terms set (``gca.align.rdga.RDGAConfig``), or None without RDGA terms.

        A method with alignment terms but no ``silhouette`` weighs L_mask 0 (``lambda_mask``): RDGA still
        renders the mask, which the alignment terms need (only ``benchmarks/grad_terms.py`` does this).
        """
        if not any(t in self.terms for t in RDGA_TERMS):
            return None
        switches = {"enabled": True, "use_global": "global" in self.terms,
                    "use_anchor": "anchor" in self.terms or "anchor_l1" in self.terms,
                    "depth_term": "l1" if "anchor_l1" in self.terms else "rank"}
        return switches if "silhouette" in self.terms else {**switches, "lambda_mask": 0.0}


_GCA = ("silhouette", "global", "anchor", "cpr")  # eq. 8: lambda_m L_mask + lambda_g L_geo + R_e + R_p

METHODS: dict[str, Method] = {m.name: m for m in (
    Method("gca", terms=_GCA, tables=("table1", "table2", "table3", "table4", "table5", "table6", "law")),
    Method("neuma", terms=("color",), recipe="neuma", tables=("table1", "table2", "table3", "table4", "table5", "table6", "law")),
    Method("neuma_multiview", terms=("color",), views="multi", recipe="neuma", tables=("table5",)),
    Method("nclaw", adapt="none", tables=("table1", "table2")),
    Method("gca_full_ft", adapt="full", terms=_GCA, tables=("table4",)),
    Method("pacnerf_depth", law="explicit", adapt="none", terms=("color", "depth_l1"), tables=("table5",)),
    Method("pacnerf_depth_aligned", law="explicit", adapt="none", terms=("color", "depth_l1_aligned"), tables=("table5",)),
    Method("pacnerf_multiview", law="explicit", adapt="none", terms=("color",), views="multi", tables=("table5",)),
    Method("no_global", terms=("silhouette", "anchor", "cpr"), tables=("table3",)),
    Method("no_anchor", terms=("silhouette", "global", "cpr"), tables=("table3",)),
    Method("rank_to_l1", terms=("silhouette", "global", "anchor_l1", "cpr"), tables=("table3",)),
    Method("no_rdga", terms=("cpr",), tables=("table3",)),
    Method("no_cpr", terms=("silhouette", "global", "anchor"), tables=("table3",)),
    Method("cpr_target_removed", terms=_GCA, cpr_remove_target=True, tables=("table6",)),
)}


def get_method(name: str) -> Method:
    """Look a method up by name; unknown names list the valid ones."""
    if name not in METHODS:
        raise UnknownMethodError(f"unknown method {name!r}; valid methods: {', '.join(sorted(METHODS))}")
    return METHODS[name]
