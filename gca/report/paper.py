"""The paper's published numbers, copied exactly from the LaTeX source (``seed/000_8f73cb432e903f9e.txt``,
section "Experiments"), plus the scene/method vocabulary the tables are built on.

Everything here is plain data. A published cell is a float, :data:`DIVERGED` (the paper's
``$>100$ (Diverged)``) or ``None`` (the paper prints ``--``: not reported). Keys are this project's ids:
methods as in the ``evaluate`` stage's ``metrics/<scene>/<method>.json`` and scenes as in ``params.yaml``.

Units as published: Chamfer distance in the paper's (unstated) units and scale; memory in GB, training in
minutes, inference in seconds (Table 4); law-level response error in percent.
"""

from __future__ import annotations

from typing import Final

DIVERGED: Final = "diverged"  # the paper's "> 100 (Diverged)"
PAPER_DEVICE: Final = "NVIDIA A800 80GB"  # "All experiments run on a single NVIDIA A800 80GB GPU."

# Scenes: id -> (material, object) as the paper names them.
SCENES: Final[dict[str, tuple[str, str]]] = {
    "ball": ("Elastomer", "Ball"),
    "duck": ("Gel", "Duck"),
    "pawn": ("Rubber", "Pawn"),
    "cat": ("Plasticine", "Cat"),
    "fish": ("Granular", "Fish"),
    "bottle": ("Non-Newt.", "Bottle"),
    "dragon": ("Plast.", "Dragon"),
    "wolf": ("Sand", "Wolf"),
    "pudding": ("Gel", "Pudding"),
    "composite": ("Composite", "(undefined)"),
}
SYNTHETIC_SCENES: Final = ("ball", "duck", "pawn", "cat", "fish", "bottle")
REAL_TO_SIM_SCENES: Final = ("dragon", "wolf", "pudding")
LAW_SCENE: Final = "duck"  # "analytic JellyDuck law as ground truth"

# Methods: id -> the row label the paper uses; the order is the canonical plotting/sorting order.
METHODS: Final[dict[str, str]] = {
    "nclaw": "NCLaw",
    "neuma": "NeuMA",
    "neuma_multiview": "NeuMA (multi-view)",
    "pacnerf_multiview": "PAC-NeRF (multi-view)",
    "pacnerf_depth": "PAC-NeRF + Depth (raw L1)",
    "pacnerf_depth_aligned": "PAC-NeRF + Depth (aligned L1)",
    "gca_full_ft": "Ours (Full F.T.)",
    "no_global": "w/o Global Align.",
    "no_anchor": "w/o Anchor Superv.",
    "rank_to_l1": "Replace Rank w/ L1",
    "no_rdga": "w/o RDGA",
    "no_cpr": "w/o CPR",
    "cpr_target_removed": "Ours (Target Removed)",
    "gca": "Ours",
}

# Table 1 (tab:chamfer_distance): synthetic Chamfer distance; "average" is the paper's own column.
TABLE1_SYNTHETIC_CD: Final[dict[str, dict[str, float]]] = {
    "nclaw": {"ball": 4.085, "duck": 2.934, "pawn": 2.031, "cat": 1.909, "fish": 0.536, "bottle": 1.631,
              "average": 2.188},
    "neuma": {"ball": 1.123, "duck": 1.863, "pawn": 0.517, "cat": 0.844, "fish": 0.322, "bottle": 1.056,
              "average": 0.954},
    "gca": {"ball": 0.922, "duck": 0.702, "pawn": 0.200, "cat": 0.318, "fish": 0.077, "bottle": 0.757,
            "average": 0.496},
}

# Table 2 (tab:realtosim_chamfer): real-to-sim Chamfer distance.
TABLE2_REAL_TO_SIM_CD: Final[dict[str, dict[str, float]]] = {
    "nclaw": {"dragon": 25.021, "wolf": 49.420, "pudding": 38.149},
    "neuma": {"dragon": 3.527, "wolf": 9.803, "pudding": 13.804},
    "gca": {"dragon": 2.081, "wolf": 5.842, "pudding": 0.906},
}

# Table 3 (tab:detailed_ablation): ablation Chamfer distance, rows in the paper's order.
TABLE3_ABLATION_CD: Final[dict[str, dict[str, float | str]]] = {
    "neuma": {"ball": 1.123, "duck": 1.863, "pawn": 0.517, "cat": 0.844, "fish": 0.322, "bottle": 1.056},
    "no_global": {scene: DIVERGED for scene in SYNTHETIC_SCENES},
    "no_anchor": {"ball": 1.024, "duck": 0.963, "pawn": 0.637, "cat": 0.510, "fish": 0.164, "bottle": 1.166},
    "rank_to_l1": {"ball": 1.064, "duck": 1.098, "pawn": 0.846, "cat": 0.919, "fish": 0.147, "bottle": 0.989},
    "no_rdga": {"ball": 3.842, "duck": 3.045, "pawn": 1.975, "cat": 1.821, "fish": 0.559, "bottle": 1.531},
    "no_cpr": {"ball": 1.024, "duck": 0.694, "pawn": 0.243, "cat": 0.510, "fish": 0.084, "bottle": 0.769},
    "gca": {"ball": 0.922, "duck": 0.702, "pawn": 0.200, "cat": 0.318, "fish": 0.077, "bottle": 0.757},
}
TABLE3_LABELS: Final[dict[str, str]] = {"neuma": "NeuMA (Baseline)", "gca": "Ours (Full)"}
TABLE3_NOTES: Final[dict[str, str]] = {
    "neuma": "Prior best",
    "no_global": "Divergence",
    "no_anchor": "Loss of detail",
    "rank_to_l1": "Scale ambiguity",
    "no_rdga": "No geom. anchor",
    "no_cpr": "No physics prior",
    "gca": "Best performance",
}

# Table 4 (tab:efficiency): memory [GB], training [min], inference [s], Chamfer distance.
TABLE4_EFFICIENCY: Final[dict[str, dict[str, float]]] = {
    "neuma": {"memory_gb": 28.9, "train_min": 73.3, "infer_s": 32.4, "cd": 1.31},
    "gca_full_ft": {"memory_gb": 76.9, "train_min": 408.6, "infer_s": 32.5, "cd": 1.35},
    "gca": {"memory_gb": 30.5, "train_min": 51.2, "infer_s": 31.5, "cd": 0.50},
}
TABLE4_LABELS: Final[dict[str, str]] = {"neuma": "NeuMA", "gca_full_ft": "Ours (Full F.T.)", "gca": "Ours (LoRA)"}

# Table 5 (tab:explicit_comparison): explicit vs implicit methods, monocular vs multi-view supervision.
TABLE5_EXPLICIT: Final[dict[str, dict[str, float | str | None]]] = {
    "pacnerf_multiview": {"ball": 0.85, "cat": 0.29},
    "neuma_multiview": {"ball": 0.98, "cat": 0.35},
    "pacnerf_depth": {"ball": DIVERGED, "cat": DIVERGED},
    "pacnerf_depth_aligned": {"ball": None, "cat": None},  # not in the paper: our aligned-depth variant of its row
    "neuma": {"ball": 1.12, "cat": 0.84},
    "gca": {"ball": 0.92, "cat": 0.32},
}
TABLE5_LABELS: Final[dict[str, str]] = {
    "pacnerf_multiview": "PAC-NeRF", "neuma_multiview": "NeuMA", "pacnerf_depth": "PAC-NeRF + Depth (raw L1)",
    "pacnerf_depth_aligned": "PAC-NeRF + Depth (aligned L1)", "neuma": "NeuMA", "gca": "Ours",
}
TABLE5_SUPERVISION: Final[dict[str, str]] = {
    "pacnerf_multiview": "Multi-view", "neuma_multiview": "Multi-view", "pacnerf_depth": "Monocular",
    "pacnerf_depth_aligned": "Monocular", "neuma": "Monocular", "gca": "Monocular",
}
TABLE5_STATUS: Final[dict[str, str]] = {
    "pacnerf_multiview": "Reference", "neuma_multiview": "Reference", "pacnerf_depth": "Diverged",
    "pacnerf_depth_aligned": "not in paper", "neuma": "Suboptimal", "gca": "Robust",
}

# Table 6 (tab:ood): out-of-distribution materials. Elastomer = ball, Plasticine = cat with the target law
# excluded from the CPR library; Composite = the composite scene. None = the paper's "--".
TABLE6_OOD: Final[dict[str, dict[str, float | None]]] = {
    "neuma": {"ball": 1.123, "cat": 0.844, "composite": 3.628},
    "cpr_target_removed": {"ball": 0.976, "cat": 0.397, "composite": None},
    "gca": {"ball": 0.922, "cat": 0.318, "composite": 1.275},
}
TABLE6_LABELS: Final[dict[str, str]] = {
    "neuma": "NeuMA", "cpr_target_removed": "Ours (Target Removed)", "gca": "Ours (Full Library)",
}
TABLE6_COLUMNS: Final[dict[str, str]] = {
    "ball": "Elastomer (target excl.)", "cat": "Plasticine (target excl.)", "composite": "Composite (undefined)",
}

# Law-level validation (fig:lawlevel, inset table): response error [%] on held-out F, JellyDuck ground truth.
LAW_LEVEL_ERROR_PCT: Final[dict[str, dict[str, float]]] = {
    "neuma": {"uniaxial": 52.0, "shear": 27.1, "average": 39.6},
    "gca": {"uniaxial": 12.0, "shear": 3.9, "average": 8.0},
}
