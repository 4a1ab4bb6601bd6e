"""Paper figures from metrics JSON: CD over time, rendering metrics, law-level curves, qualitative strips.

Figures are drawn on ``matplotlib.figure.Figure`` objects (Agg canvas, no pyplot global state) at a fixed
dpi and saved without the ``Software`` PNG chunk, so the same metrics give the same bytes on one machine.
Each function returns the written path, or None when it had no data to draw (nothing is written then).
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Sequence

import matplotlib
import numpy as np
from matplotlib.figure import Figure
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.ticker import MaxNLocator

from gca.report import paper
from gca.report.runs import Runs, finite

matplotlib.rcParams["svg.hashsalt"] = "gca"  # only matters for SVG; PNG has no random ids
_CMAP = matplotlib.colormaps["tab20"]
MAIN_METHODS = ("nclaw", "neuma", "gca")  # the methods of Table 1 / the rendering-metrics figure


def method_color(method: str) -> tuple[float, float, float, float]:
    """A fixed colour per method (by its position in :data:`paper.METHODS`; unknown methods grey)."""
    order = list(paper.METHODS)
    return _CMAP(order.index(method) % 20) if method in order else (0.5, 0.5, 0.5, 1.0)


def method_label(method: str) -> str:
    return paper.METHODS.get(method, method)


def _save(fig: Figure, path: Path, dpi: int) -> Path:
    """Save ``fig`` as PNG at ``dpi`` with the ``Software`` metadata chunk removed."""
    FigureCanvasAgg(fig)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=dpi, format="png", metadata={"Software": None})
    return path


def _methods_sorted(methods: Sequence[str]) -> list[str]:
    order = list(paper.METHODS)
    return sorted(methods, key=lambda m: (order.index(m) if m in order else len(order), m))


def per_frame_mean(records: Sequence[dict]) -> np.ndarray | None:
    """Seed mean of ``chamfer_per_frame`` ``[T]`` (non-finite frames are NaN gaps; failed seeds skipped)."""
    series = [np.array([math.nan if finite(v) is None else float(v) for v in r["chamfer_per_frame"]])
              for r in records if r["status"] != "failed" and r.get("chamfer_per_frame")]
    if not series:
        return None
    length = min(len(s) for s in series)
    stacked = np.stack([s[:length] for s in series])
    with np.errstate(invalid="ignore"):
        counts = np.isfinite(stacked).sum(0)
        sums = np.where(np.isfinite(stacked), stacked, 0.0).sum(0)
    return np.where(counts > 0, sums / np.maximum(counts, 1), math.nan)


def plot_cd_over_time(runs: Runs, scene: str, path: Path, dpi: int) -> Path | None:
    """Chamfer distance per frame of every method that ran on ``scene`` (diverged runs dashed)."""
    methods = _methods_sorted([m for (s, m) in runs if s == scene])
    fig = Figure(figsize=(6.0, 3.6))
    ax = fig.add_subplot()
    drawn = 0
    for method in methods:
        records = runs[scene, method]
        curve = per_frame_mean(records)
        if curve is None:
            continue
        diverged = any(r["status"] == "diverged" for r in records)
        label = method_label(method) + (" (diverged)" if diverged else "")
        frames = np.arange(len(curve))
        ax.plot(frames, curve, color=method_color(method), lw=1.4, ls="--" if diverged else "-", label=label)
        if diverged and np.isfinite(curve).any():  # mark the last finite frame before the blow-up
            last = np.flatnonzero(np.isfinite(curve))[-1]
            ax.plot(frames[last], curve[last], "x", color=method_color(method), ms=8)
        drawn += 1
    if not drawn:
        return None
    ax.set(xlabel="frame", ylabel="Chamfer distance", title=f"CD over time: {scene} (x: last finite frame)")
    ax.xaxis.set_major_locator(MaxNLocator(integer=True))
    ax.legend(fontsize=7, ncol=2)
    ax.grid(alpha=0.3)
    fig.tight_layout()
    return _save(fig, path, dpi)


def _render_values(runs: Runs, scene: str, method: str, metric: str, split: str) -> float | None:
    """Seed mean of ``<metric>_<split>`` for one run (None when absent, failed or not finite)."""
    values = [finite(r.get(f"{metric}_{split}")) for r in runs.get((scene, method), []) if r["status"] != "failed"]
    values = [v for v in values if v is not None]
    return float(np.mean(values)) if values else None


def _render_panel(ax, runs: Runs, metric: str, scenes: Sequence[str], methods: Sequence[str]) -> bool:
    """Grouped bars (scene groups; per method a train bar and a hatched held-out bar). True if drawn."""
    width = 0.8 / (2 * len(methods))
    drawn = False
    for i, method in enumerate(methods):
        for j, split in enumerate(("train", "heldout")):
            values = [_render_values(runs, s, method, metric, split) for s in scenes]
            xs = [k + (2 * i + j - len(methods) + 0.5) * width for k, v in enumerate(values) if v is not None]
            ys = [v for v in values if v is not None]
            if ys:
                ax.bar(xs, ys, width, color=method_color(method), hatch="//" if j else None, edgecolor="k",
                       lw=0.3, label=f"{method_label(method)} ({'held-out' if j else 'train'})")
                drawn = True
    ax.set_xticks(range(len(scenes)), list(scenes))
    return drawn


def plot_render_metrics(runs: Runs, path: Path, dpi: int, scenes: Sequence[str] = paper.SYNTHETIC_SCENES,
                        methods: Sequence[str] = MAIN_METHODS) -> Path | None:
    """PSNR / SSIM (and LPIPS where reported) bars per scene and method, train view vs held-out view."""
    panels = (("psnr", "PSNR (dB) ↑"), ("ssim", "SSIM ↑"), ("lpips", "LPIPS ↓"))
    fig = Figure(figsize=(7.5, 7.0))
    axes = fig.subplots(len(panels), 1)
    drawn = [_render_panel(ax, runs, metric, scenes, methods) for ax, (metric, _) in zip(axes, panels)]
    if not any(drawn):
        return None
    for ax, (metric, label), ok in zip(axes, panels, drawn):
        ax.set_ylabel(label)
        if not ok:
            ax.text(0.5, 0.5, f"{metric.upper()}: not reported", ha="center", va="center", transform=ax.transAxes)
    axes[0].legend(fontsize=6, ncol=3)
    axes[0].set_title("Rendering metrics (solid: training view, hatched: held-out view)")
    fig.tight_layout()
    return _save(fig, path, dpi)


def _first_curves(records: Sequence[dict]) -> dict | None:
    """``law_curves`` of the lowest seed that has them."""
    return next((r["law_curves"] for r in records if isinstance(r.get("law_curves"), dict)), None)


_X_KEYS = ("stretch", "gamma", "strain")  # abscissa names accepted in ``law_curves[mode]``


def plot_law_curves(runs: Runs, path: Path, dpi: int, scene: str = paper.LAW_SCENE) -> Path | None:
    """Uniaxial and shear response of the learned laws vs the analytic reference (``law_curves``)."""
    curves = {m: c for m in _methods_sorted([m for (s, m) in runs if s == scene])
              if (c := _first_curves(runs[scene, m])) is not None}
    if not curves:
        return None
    fig = Figure(figsize=(7.5, 3.2))
    axes = fig.subplots(1, 2)
    for ax, (mode, xlabel) in zip(axes, (("uniaxial", "stretch λ"), ("shear", "shear γ"))):
        reference_drawn = False
        for method, curve in curves.items():
            xkey = next((k for k in _X_KEYS if k in curve.get(mode, {})), None)
            if xkey is None:
                continue
            x = np.asarray(curve[mode][xkey], float)
            if not reference_drawn:
                ax.plot(x, np.asarray(curve[mode]["reference"], float), "k--", lw=1.6, label="ground truth")
                reference_drawn = True
            ax.plot(x, np.asarray(curve[mode]["ours"], float), color=method_color(method), lw=1.4,
                    label=method_label(method))
        ax.set(xlabel=xlabel, ylabel="normalized response", title=f"{mode} ({scene})")
        ax.grid(alpha=0.3)
        if reference_drawn:
            ax.legend(fontsize=7)
    fig.tight_layout()
    return _save(fig, path, dpi)


def _find_png(name: str | None, search_dirs: Sequence[Path]) -> Path | None:
    """Resolve a ``strip_png`` path: absolute as is, relative against each of ``search_dirs``."""
    if not name:
        return None
    candidates = [Path(name)] if Path(name).is_absolute() else [d / name for d in search_dirs]
    return next((c for c in candidates if c.is_file()), None)


def compose_strips(runs: Runs, scene: str, path: Path, dpi: int, search_dirs: Sequence[Path]) -> Path | None:
    """Stack the qualitative frame strips (``strip_png``) of every method on ``scene``, one row each.

    Methods whose strip is not given or not found are skipped; None when no strip exists.
    """
    import matplotlib.image as mpimg

    strips = []
    for method in _methods_sorted([m for (s, m) in runs if s == scene]):
        found = next((p for r in runs[scene, method] if (p := _find_png(r.get("strip_png"), search_dirs))), None)
        if found is not None:
            strips.append((method, mpimg.imread(found)))
    if not strips:
        return None
    fig = Figure(figsize=(8.0, 1.4 * len(strips) + 0.3))
    axes = np.atleast_1d(fig.subplots(len(strips), 1))
    for ax, (method, image) in zip(axes, strips):
        ax.imshow(image, interpolation="nearest")
        ax.set_xticks([]), ax.set_yticks([])
        ax.set_ylabel(method_label(method), rotation=0, ha="right", va="center", fontsize=8)
    fig.suptitle(f"Qualitative comparison: {scene}", fontsize=9)
    fig.tight_layout()
    return _save(fig, path, dpi)
