"""gca.report: the paper's tables and figures, regenerated from the ``evaluate`` stage's metrics JSON only.

``build_reports(metrics_dir, out_dir)`` writes, atomically as one folder::

    <out_dir>/table1_synthetic_cd.{md,csv}  ... table6_ood.{md,csv}, table_law_level.{md,csv}, table_render_metrics.{md,csv}
    <out_dir>/claims.{md,csv}   each claim of the paper: measured effect, bootstrap interval, verdict (gca.report.claims)
    <out_dir>/figures/cd_time_<scene>.png, render_metrics.png, law_curves.png, strip_<scene>.png
    <out_dir>/captures/<scene>.md   one page per capture scene (gca.report.captures)
    <out_dir>/README.md   one line per file

Published numbers live in :mod:`gca.report.paper`; seeds are reduced in :mod:`gca.report.runs`.
"""

from __future__ import annotations

import os
import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

from gca.io import atomic_path
from gca.report import claims as claims_mod, figures, paper
from gca.report.claims import ClaimsConfig
from gca.report.nuisance import write_nuisance_table
from gca.report.tuning import write_tuning_tables
from gca.report.runs import DivergenceRule, Runs, load_runs, mark_divergence
from gca.report.tables import build_tables, markdown_table, provenance, scene_average, write_table

__all__ = ["ReportConfig", "build_reports", "summary"]


@dataclass(frozen=True)
class ReportConfig:
    """Knobs of the ``report`` stage (params.yaml section ``report``)."""

    dpi: int = 120  # resolution of every figure [dots per inch]; the same at both profiles
    # a run whose CD exceeds this multiple of the prior's (nclaw) on its scene is diverged (0 = off); fixed
    # before the runs, never moved after seeing a table scene (gca.report.runs.DivergenceRule)
    divergence_cd_ratio: float = 10.0
    claims: ClaimsConfig = ClaimsConfig()  # the claims table's bootstrap and verdict rules

    @property
    def divergence(self) -> DivergenceRule:
        return DivergenceRule(cd_ratio=self.divergence_cd_ratio)


def _run_root(metrics_dir: Path) -> Path:
    """The folder the runs' relative media paths (``strip_png``: ``metrics/eval/<scene>/<method>/strip.png``)
    start from: the root above ``<root>/metrics/eval``, else the metrics folder's parent. Never the current
    folder: a report of results kept elsewhere must not pick up this checkout's own (CI-profile) strips."""
    resolved = metrics_dir.resolve()
    return resolved.parents[1] if resolved.parts[-2:] == ("metrics", "eval") else resolved.parent


def _write_figures(runs: Runs, fig_dir: Path, cfg: ReportConfig, search_dirs: Sequence[Path]) -> list[Path]:
    """Every figure the metrics allow; figures without data are skipped."""
    scenes = sorted({scene for scene, _ in runs})
    paths = [figures.plot_cd_over_time(runs, s, fig_dir / f"cd_time_{s}.png", cfg.dpi) for s in scenes]
    paths.append(figures.plot_render_metrics(runs, fig_dir / "render_metrics.png", cfg.dpi))
    paths.append(figures.plot_law_curves(runs, fig_dir / "law_curves.png", cfg.dpi))
    paths += [figures.compose_strips(runs, s, fig_dir / f"strip_{s}.png", cfg.dpi, search_dirs) for s in scenes]
    return [p for p in paths if p is not None]


def write_claims(runs: Runs, out_dir: Path, cfg: ReportConfig) -> list[Path]:
    """``claims.md`` and ``claims.csv``: every claim of :func:`gca.report.claims.paper_claims` judged on ``runs``
    (already marked by the divergence rule)."""
    judgements = claims_mod.judge_all(runs, cfg.claims)
    df = claims_mod.claims_frame(judgements)
    info = {**provenance(runs, runs.keys()), "divergence": cfg.divergence.describe()}
    md, csv = out_dir / "claims.md", out_dir / "claims.csv"
    md.write_text(claims_mod.claims_markdown(df, info, cfg.claims, markdown_table), encoding="utf-8")
    csv.write_text(df.to_csv(index=False, lineterminator="\n"), encoding="utf-8")
    return [md, csv]


_FIGURE_LINES = {
    "cd_time": "Chamfer distance per frame of every method on scene `{}` (paper fig. cdnpy)",
    "strip": "qualitative frame strips of every method on scene `{}` (paper figs. realtosim_quality / gaus)",
    "render_metrics": "PSNR / SSIM (LPIPS where reported), training vs held-out view (paper fig. render_metrics)",
    "law_curves": "law-level response curves vs the analytic ground truth (paper fig. lawlevel)",
}


def _index_line(path: Path, root: Path, titles: dict[str, str]) -> str:
    """One README line describing ``path``."""
    rel = path.relative_to(root).as_posix()
    if path.suffix in (".md", ".csv"):
        kind = "Markdown" if path.suffix == ".md" else "CSV"
        return f"- [`{rel}`]({rel}): {titles[path.stem]} ({kind})"
    stem = path.stem
    for prefix, text in _FIGURE_LINES.items():
        if stem == prefix or stem.startswith(prefix + "_"):
            return f"- [`{rel}`]({rel}): {text.format(stem[len(prefix) + 1:])}"
    return f"- [`{rel}`]({rel})"


def _media_line(path: Path, root: Path) -> str:
    rel = path.relative_to(root).as_posix()
    what = "animation" if path.suffix == ".gif" else "frame strip"
    return f"- [`{rel}`]({rel}): generalization demo {what} ({path.parent.name}), copied from the `demo` stage"


def _write_index(paths: Sequence[Path], root: Path, titles: dict[str, str], n_records: int,
                 media: set[Path] = frozenset(), version: str = "") -> Path:
    """``README.md`` indexing every written file with one line each."""
    lines = ["# Reports", "",
             f"Benchmark version: {version or 'unknown'} (params `benchmark.version`; docs/benchmark.md).", "",
             f"Generated by the `report` stage from {n_records} metrics files only (`gca.report.build_reports`); "
             "do not edit by hand. Each table puts the measured numbers beside the paper's and states the "
             "benchmark version, profile, device and Chamfer definition they were made with.", ""]
    lines += [_media_line(p, root) if p in media else _index_line(p, root, titles) for p in paths]
    index = root / "README.md"
    index.write_text("\n".join(lines) + "\n", encoding="utf-8")
    return index


def _copy_media(media_dirs: Sequence[Path], dest: Path) -> list[Path]:
    """Copy GIF/PNG results of other stages (e.g. the generalization demos) under ``dest``, sorted."""
    copied = []
    for media in media_dirs:
        for src in sorted(p for p in Path(media).rglob("*") if p.suffix in (".gif", ".png")):
            target = dest / Path(media).name / src.relative_to(media)
            target.parent.mkdir(parents=True, exist_ok=True)
            shutil.copyfile(src, target)
            copied.append(target)
    return copied


def build_reports(metrics_dir: str | os.PathLike, out_dir: str | os.PathLike,
                  cfg: ReportConfig | None = None, media_dirs: Sequence[str | os.PathLike] = (),
                  benchmark_version: str = "", nuisance_dir: str | os.PathLike | None = None,
                  capture_demos_dir: str | os.PathLike | None = None,
                  tuning_record: str | os.PathLike | None = None) -> list[Path]:
    """Write every table (Markdown + CSV), figure and the README index into ``out_dir``.

    The folder is replaced atomically as a whole (stale figures of an earlier run disappear).

    Args:
        metrics_dir: the ``metrics`` folder written by the ``evaluate`` stage.
        out_dir: the ``reports`` folder.
        cfg: figure knobs (defaults of :class:`ReportConfig` when None).
        media_dirs: folders of GIF/PNG results to include as they are (the ``demo`` stage's output);
            copied to ``out_dir/<folder name>/``.
        benchmark_version: params ``benchmark.version``, in the README header (each table states its metrics').
        nuisance_dir: the ``nuisance`` stage's folder (``metrics/nuisance``): the benchmark_nuisance table.
        capture_demos_dir: the ``demo_capture`` stages' folder (``metrics/demo_capture``): each capture page
            (``captures/<scene>.md``, :func:`gca.report.captures.write_capture_pages`) links its new-scene demo.
        tuning_record: params ``tuning.record`` (the cited tuning record; "": none yet): the tuning_calibration page
            (the chosen knobs and each RDGA term's gradient share on the calibration scenes); None: no page.

    Returns:
        The written paths (under ``out_dir``), README last (the capture scenes' pages and media, ``captures/``,
        are written inside the folder that replaces ``out_dir`` as a whole).
    """
    cfg = cfg or ReportConfig()
    metrics_dir, out_dir = Path(metrics_dir), Path(out_dir)
    runs = mark_divergence(load_runs(metrics_dir), cfg.divergence)
    search_dirs = [_run_root(metrics_dir)]
    with atomic_path(out_dir, is_dir=True) as tmp:
        tmp.chmod(0o755)  # mkdtemp makes it private; reports are for everyone
        tables = build_tables(runs, cfg.divergence)
        written = [p for table, info in tables for p in write_table(table, info, tmp)]
        written += write_claims(runs, tmp, cfg)
        written += _write_figures(runs, tmp / "figures", cfg, search_dirs)
        if nuisance_dir is not None:
            written += write_nuisance_table(nuisance_dir, tmp, benchmark_version or "unknown")
            titles_extra = {"benchmark_nuisance": "Benchmark nuisance statistics per scene"}
        else:
            titles_extra = {}
        from gca.report.captures import write_capture_pages  # here: `python -m gca.report.captures` runs it as main

        captures = write_capture_pages(metrics_dir, tmp, capture_demos_dir)  # captures/<scene>.md and media
        written += captures
        titles_extra |= {p.stem: f"capture `{p.stem}`: held-out PSNR, SSIM, mask IoU, silhouette CD, the learned "
                         "law's nearest classical law, re-simulation and new-scene demo"
                         for p in captures if p.suffix == ".md"}
        if tuning_record is not None:
            written += write_tuning_tables(tuning_record, tmp)
            titles_extra["tuning_calibration"] = "Tuning on the calibration scenes: chosen knobs, RDGA term shares"
        media = _copy_media([Path(m) for m in media_dirs], tmp)
        titles = {table.name: table.title for table, _ in tables} | titles_extra
        titles["claims"] = "each claim of the paper: measured effect, 95% bootstrap interval and verdict"
        written += media
        written.append(_write_index(written, tmp, titles, sum(len(r) for r in runs.values()), set(media),
                                    benchmark_version))
        result = [out_dir / p.relative_to(tmp) for p in written]
    return result


def summary(runs: Runs, cfg: ReportConfig | None = None) -> dict:
    """Headline numbers for ``metrics/report.json``: Table 1 averages (measured and paper) and run counts,
    after the divergence rule of ``cfg`` (default :class:`ReportConfig`)."""
    runs = mark_divergence(runs, (cfg or ReportConfig()).divergence)
    statuses = [r["status"] for records in runs.values() for r in records]
    averages = {}
    for method in paper.TABLE1_SYNTHETIC_CD:
        cell = scene_average(runs, method, paper.SYNTHETIC_SCENES)
        averages[method] = {"status": cell.status, "mean_cd": cell.mean, "n_scenes": cell.n,
                            "paper_mean_cd": paper.TABLE1_SYNTHETIC_CD[method]["average"]}
    info = provenance(runs, runs.keys())
    return {"n_runs": len(runs), "n_records": len(statuses),
            "status_counts": {s: statuses.count(s) for s in sorted(set(statuses))},
            "profile": info["profile"], "device": info["device"], "commit": info["commit"],
            "table1_average_cd": averages}
