"""The methods registry: one name per row of the paper's tables.

Every method is trained from the same monocular data (the ``train0`` view) unless it says
``views = "multi"`` (the paper's multi-view reference rows use three training cameras).

| name                | law      | adapt | losses                                  | paper row |
| ------------------- | -------- | ----- | --------------------------------------- | --------- |
| gca                 | neural   | lora  | mask + geo (RDGA) + CPR (eq. 8)          | Ours |
| neuma               | neural   | lora  | pixel colour L2                         | NeuMA (monocular) |
| neuma_multiview     | neural   | lora  | pixel colour L2, 3 views                | NeuMA multi-view (Table 5) |
| nclaw               | neural   | none  | - (prior as is)                         | NCLaw |
| gca_full_ft         | neural   | full  | as gca                                  | Ours (Full F.T.) (Table 4) |
| pacnerf_depth       | explicit | -     | colour + L1 monocular depth             | PAC-NeRF + Depth (Table 5) |
| pacnerf_multiview   | explicit | -     | colour, 3 views                         | PAC-NeRF multi-view (Table 5) |
| no_global           | neural   | lora  | gca without the global alignment term   | Table 3 |
| no_anchor           | neural   | lora  | gca without the anchor term             | Table 3 |
| rank_to_l1          | neural   | lora  | gca with L1 depth instead of ranks      | Table 3 |
| no_rdga             | neural   | lora  | gca without RDGA (mask, geo off)        | Table 3 |
| no_cpr              | neural   | lora  | gca without CPR                         | Table 3 |
| cpr_target_removed  | neural   | lora  | gca, the scene's true hypothesis removed from CPR | Table 6 |
"""

from __future__ import annotations

import dataclasses


class UnknownMethodError(KeyError):
    """A method name that is not in the registry."""

    def __str__(self) -> str:  # KeyError quotes its message; keep it readable
        return self.args[0]


@dataclasses.dataclass(frozen=True)
class Method:
    """How one table row is trained.

    Attributes:
        name: registry key.
        law: ``neural`` (NCLaw networks) or ``explicit`` (analytic law with fitted E, nu, ...).
        adapt: ``lora``, ``full`` (all network weights) or ``none`` (no training).
        views: ``mono`` (train0 only) or ``multi`` (train0..train2).
        color: pixel colour L2 loss.
        mask: silhouette loss (RDGA).
        geo: RDGA geometric loss L_geo.
        depth_l1: L1 loss on monocular depth (PAC-NeRF + depth baseline).
        cpr: constitutive prior regularizer.
        rdga: overrides of the RDGA config (ablation switches).
        cpr_remove_target: drop the scene's ground-truth hypothesis from CPR's library.
        tables: the paper tables this method appears in.
    """

    name: str
    law: str = "neural"
    adapt: str = "lora"
    views: str = "mono"
    color: bool = False
    mask: bool = False
    geo: bool = False
    depth_l1: bool = False
    cpr: bool = False
    rdga: tuple[tuple[str, object], ...] = ()
    cpr_remove_target: bool = False
    tables: tuple[str, ...] = ()

    @property
    def trains(self) -> bool:
        return self.adapt != "none" or self.law == "explicit"


_GCA = dict(mask=True, geo=True, cpr=True)

METHODS: dict[str, Method] = {m.name: m for m in (
    Method("gca", **_GCA, tables=("table1", "table2", "table3", "table4", "table5", "table6", "law")),
    Method("neuma", color=True, tables=("table1", "table2", "table3", "table4", "table5", "table6", "law")),
    Method("neuma_multiview", color=True, views="multi", tables=("table5",)),
    Method("nclaw", adapt="none", tables=("table1", "table2")),
    Method("gca_full_ft", adapt="full", **_GCA, tables=("table4",)),
    Method("pacnerf_depth", law="explicit", adapt="none", color=True, depth_l1=True, tables=("table5",)),
    Method("pacnerf_multiview", law="explicit", adapt="none", color=True, views="multi", tables=("table5",)),
    Method("no_global", **_GCA, rdga=(("use_global", False),), tables=("table3",)),
    Method("no_anchor", **_GCA, rdga=(("use_anchor", False),), tables=("table3",)),
    Method("rank_to_l1", **_GCA, rdga=(("depth_term", "l1"),), tables=("table3",)),
    Method("no_rdga", cpr=True, rdga=(("enabled", False),), tables=("table3",)),
    Method("no_cpr", mask=True, geo=True, tables=("table3",)),
    Method("cpr_target_removed", **_GCA, cpr_remove_target=True, tables=("table6",)),
)}


def get_method(name: str) -> Method:
    """Look a method up by name; unknown names list the valid ones."""
    if name not in METHODS:
        raise UnknownMethodError(f"unknown method {name!r}; valid methods: {', '.join(sorted(METHODS))}")
    return METHODS[name]
