"""The benchmark's measured nuisance statistics per scene (the ``nuisance`` stage's JSON) as one table."""

from __future__ import annotations

import json
from pathlib import Path

import pandas as pd

from gca.report.tables import markdown_table

COLUMNS = (("mask_iou_mean", "mask IoU mean"), ("mask_iou_min", "mask IoU min"),
           ("mask_false_positive_share", "mask FP share"), ("mask_false_negative_share", "mask FN share"),
           ("depth_spearman_mean", "depth Spearman mean"), ("depth_spearman_min", "depth Spearman min"),
           ("lighting_unexplained_share", "lighting unexplained share"))


def nuisance_frame(nuisance_dir: str | Path) -> pd.DataFrame:
    """One row per scene (sorted), the statistics rounded to 3 digits."""
    rows = []
    for path in sorted(Path(nuisance_dir).glob("*.json")):
        record = json.loads(path.read_text())
        if "skipped" in record:  # a capture scene: no ground truth to measure against
            continue
        row = {"scene": record.get("scene", path.stem), "benchmark": record.get("benchmark_version", "")}
        row.update({label: f"{record[key]:.3f}" if isinstance(record.get(key), (int, float)) else "n/a"
                    for key, label in COLUMNS})
        rows.append(row)
    return pd.DataFrame(rows, columns=["scene", "benchmark"] + [label for _, label in COLUMNS])


def write_nuisance_table(nuisance_dir: str | Path, out_dir: Path, version: str) -> list[Path]:
    """``benchmark_nuisance.{md,csv}`` in ``out_dir`` (nothing when the folder has no JSON)."""
    df = nuisance_frame(nuisance_dir) if Path(nuisance_dir).is_dir() else pd.DataFrame()
    if df.empty:
        return []
    md = out_dir / "benchmark_nuisance.md"
    md.write_text("\n".join([
        "# Benchmark nuisance statistics", "",
        "How far the monocular observations are from the truth, per scene (monocular view `train0`; the "
        "`nuisance` stage, gca/eval/nuisance.py). Measured on the videos, never on a method's result.", "",
        f"- Benchmark version: {version} (params `benchmark.version`; docs/benchmark.md).",
        "- mask IoU: the preprocess stage's segmented masks vs the true alpha > 0.5, per frame (mean, min); FP/FN "
        "share: false-positive pixels / predicted, false-negative pixels / true.",
        "- depth Spearman: the preprocess stage's relative depth vs the true depth inside the true object, per frame.",
        "- lighting unexplained share: in-object colour variance of the lit video that the best per-frame affine "
        "colour map of the unlit render cannot explain (0: lighting is a global colour change).", "",
    ]) + "\n" + markdown_table(df), encoding="utf-8")
    csv = out_dir / "benchmark_nuisance.csv"
    csv.write_text(df.to_csv(index=False, lineterminator="\n"), encoding="utf-8")
    return [md, csv]
