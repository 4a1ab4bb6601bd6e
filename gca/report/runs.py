"""Read the ``evaluate`` stage's metrics JSON and reduce seeds to one cell per (scene, method).

Layout read: ``<metrics_dir>/<scene>/<method>.json`` and optional ``<method>@seed<k>.json``. Files in a scene
folder that carry no ``method`` key (other stages' metrics) are ignored. A record's ``status`` is
``ok``, ``diverged`` (its last finite metrics are kept) or ``failed`` (no usable metrics).
"""

from __future__ import annotations

import math
import re
import statistics
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Mapping, Sequence

from gca.io import read_json

STATUSES = ("ok", "diverged", "failed")
MISSING = "—"  # a run that was not run (no metrics file)
DIVERGED_CELL = "> 100 (diverged)"  # a diverged run, marked as the paper marks divergence
FAILED_CELL = "failed"
NO_VALUE = "n/a"  # the run exists but did not report this metric
_NAME = re.compile(r"^(?P<method>[A-Za-z0-9_\-]+?)(?:@seed(?P<seed>\d+))?\.json$")

Runs = dict[tuple[str, str], list[dict]]  # (scene, method) -> records sorted by seed


def _check_record(path: Path, record: Any, scene: str, method: str) -> None:
    """Raise a ValueError naming ``path`` when a metrics record breaks the schema."""
    if not isinstance(record, Mapping):
        raise ValueError(f"{path}: metrics must be a JSON object, got {type(record).__name__}")
    if record.get("status") not in STATUSES:
        raise ValueError(f"{path}: status={record.get('status')!r} is not one of {STATUSES}")
    if record.get("scene") != scene or record.get("method") != method:
        raise ValueError(f"{path}: scene/method in the file ({record.get('scene')!r}, {record.get('method')!r}) "
                         f"do not match its path ({scene!r}, {method!r})")


def _read_scene(scene_dir: Path, runs: Runs) -> None:
    """Add every method record of one scene folder to ``runs`` (deduplicated by seed)."""
    seen: dict[tuple[str, int], Path] = {}
    for path in sorted(scene_dir.glob("*.json"), key=lambda p: (len(p.name), p.name)):
        match = _NAME.match(path.name)
        record = read_json(path)
        if match is None or not isinstance(record, Mapping) or "method" not in record:
            continue
        method, scene = match["method"], scene_dir.name
        _check_record(path, record, scene, method)
        seed = int(match["seed"] or 0)  # the file name says the run (gca.train.config.run_dir_name)
        if record.get("seed", seed) != seed:
            warnings.warn(f"{path}: the record says seed {record['seed']}, its name seed {seed}: read as seed {seed} "
                          "(records before train.seeds stored the global data seed)", RuntimeWarning, stacklevel=2)
        if (method, seed) in seen:
            warnings.warn(f"{path}: seed {seed} of {scene}/{method} already read from {seen[method, seed]}; "
                          "ignoring this duplicate", RuntimeWarning, stacklevel=2)
            continue
        seen[method, seed] = path
        runs.setdefault((scene, method), []).append({**record, "seed": seed, "_path": str(path)})


def load_runs(metrics_dir: str | Path) -> Runs:
    """Load all (scene, method) metrics records under ``metrics_dir``.

    Args:
        metrics_dir: the ``metrics`` folder (``<scene>/<method>[@seed<k>].json`` inside).

    Returns:
        ``{(scene, method): [record, ...]}`` with records sorted by seed; empty when nothing is there.
    """
    metrics_dir = Path(metrics_dir)
    if not metrics_dir.is_dir():
        raise FileNotFoundError(f"{metrics_dir}: metrics folder not found")
    runs: Runs = {}
    for scene_dir in sorted(p for p in metrics_dir.iterdir() if p.is_dir()):
        _read_scene(scene_dir, runs)
    for records in runs.values():
        records.sort(key=lambda r: r["seed"])
    return dict(sorted(runs.items()))


def finite(value: Any) -> float | None:
    """``value`` as a float when it is a finite number, else None (JSON null, NaN, strings)."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        return None
    return float(value) if math.isfinite(value) else None


@dataclass(frozen=True)
class Cell:
    """One (scene, method, metric) reduced over seeds.

    Attributes:
        status: ``missing`` (no file), ``failed``, ``diverged`` (any seed diverged), ``no_value`` or ``ok``.
        mean: mean over the seeds with a finite value (None when there is none).
        std: sample standard deviation over those seeds (None for fewer than two).
        n: number of seeds averaged.
    """

    status: str
    mean: float | None = None
    std: float | None = None
    n: int = 0


def reduce_seeds(records: Sequence[Mapping] | None, key: str) -> Cell:
    """Reduce the seeds of one (scene, method) to a :class:`Cell` for metric ``key``."""
    if not records:
        return Cell("missing")
    usable = [r for r in records if r["status"] != "failed"]
    if not usable:
        return Cell("failed")
    values = [v for v in (finite(r.get(key)) for r in usable) if v is not None]
    mean = statistics.fmean(values) if values else None
    std = statistics.stdev(values) if len(values) > 1 else None
    if any(r["status"] == "diverged" for r in usable):
        return Cell("diverged", mean, std, len(values))
    return Cell("ok" if values else "no_value", mean, std, len(values))


def format_cell(cell: Cell, decimals: int, mark_diverged: bool = True) -> str:
    """Render a :class:`Cell` with fixed decimals: ``0.422``, ``0.422 ± 0.010``, or a status marker."""
    if cell.status == "missing":
        return MISSING
    if cell.status == "failed":
        return FAILED_CELL
    if cell.status == "diverged" and mark_diverged:
        return DIVERGED_CELL
    if cell.mean is None:
        return NO_VALUE
    text = f"{cell.mean:.{decimals}f}"
    return f"{text} ± {cell.std:.{decimals}f}" if cell.std is not None else text
