"""Read the ``evaluate`` stage's metrics JSON and reduce seeds to one cell per (scene, method).

Layout read: ``<metrics_dir>/<scene>/<method>.json`` and optional ``<method>@seed<k>.json``. Files in a scene
folder that carry no ``method`` key (other stages' metrics) are ignored. A record's ``status`` is
``ok``, ``diverged`` (its last finite metrics are kept) or ``failed`` (no usable metrics).

Divergence is defined before the runs (:class:`DivergenceRule`, params ``report.divergence_cd_ratio``): a run
is diverged when a stage said so (a non-finite loss or state, particles leaving the domain, a CFL failure
past refinement) or when its Chamfer distance exceeds the stated multiple of the prior's (the ``nclaw`` row:
the prior as is) on the same scene. A diverged cell still prints the measured value, with the status beside
it (``0.0123 (diverged)``); every number has at least three significant digits (:func:`format_number`).
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
DIVERGED_MARK = "(diverged)"  # printed after a diverged cell's measured value
DIVERGED_CELL = "diverged (no finite value)"  # a diverged run that left no finite value of this metric
SIGNIFICANT = 3  # every printed number keeps at least this many significant digits
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
        if record.get("kind") == "capture":  # a capture scene: its own page (gca.report.captures), in no table
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


def decimals_for(value: float, decimals: int, significant: int = SIGNIFICANT) -> int:
    """At least ``decimals`` decimals, more where ``value`` would otherwise keep fewer than ``significant``
    significant digits (``0.00123`` at 2 decimals would print ``0.00``)."""
    if not math.isfinite(value) or value == 0:
        return decimals
    return max(decimals, significant - 1 - math.floor(math.log10(abs(value))))


def format_number(value: float, decimals: int, significant: int = SIGNIFICANT) -> str:
    """``value`` with fixed decimals, at least ``significant`` significant digits (:func:`decimals_for`)."""
    return f"{value:.{decimals_for(value, decimals, significant)}f}"


def format_cell(cell: Cell, decimals: int, mark_diverged: bool = True, seeds: int = 0) -> str:
    """Render a :class:`Cell`: ``0.422``, ``0.422 ± 0.010`` (the std with the mean's decimals), the measured
    value of a diverged cell with its status beside it (``0.0123 (diverged)``; ``mark_diverged=False``
    drops the mark), or a status marker. Numbers keep at least :data:`SIGNIFICANT` significant digits.
    ``seeds``: the table's seed count (:func:`table_seeds`); a mean over fewer says so, ``0.00548 ± 0.00071 (2 of 3
    seeds)`` (session 27: Table 3's duck Rank->L1 cell averaged two seeds beside cells of three, unmarked)."""
    text = _format_cell(cell, decimals, mark_diverged)
    if cell.mean is not None and 0 < cell.n < seeds:
        text += f" ({cell.n} of {seeds} seeds)"
    return text


def table_seeds(runs: Mapping, methods, scenes) -> int:
    """The most seeds of any (scene, method) among ``methods`` x ``scenes`` in ``runs`` (records, failed ones
    included): a table's seed count, against which a cell of fewer is marked (:func:`format_cell`)."""
    return max((len(runs.get((scene, method)) or ()) for method in methods for scene in scenes), default=0)


def _format_cell(cell: Cell, decimals: int, mark_diverged: bool) -> str:
    if cell.status == "missing":
        return MISSING
    if cell.status == "failed":
        return FAILED_CELL
    if cell.mean is None:
        return DIVERGED_CELL if cell.status == "diverged" else NO_VALUE
    places = decimals_for(cell.mean, decimals)
    text = f"{cell.mean:.{places}f}"
    if cell.std is not None:
        text += f" ± {cell.std:.{places}f}"
    return f"{text} {DIVERGED_MARK}" if cell.status == "diverged" and mark_diverged else text


@dataclass(frozen=True)
class DivergenceRule:
    """When a run counts as diverged, fixed before the runs (params ``report``).

    Attributes:
        cd_ratio: a run whose ``chamfer_mean`` exceeds ``cd_ratio`` x the prior's on the same scene is
            diverged (0 = off: only the stages' own verdicts count).
        prior_method: the row that is the prior as is (its seed-mean ok CD is the reference).
        key: the metric compared.
    """

    cd_ratio: float = 10.0
    prior_method: str = "nclaw"
    key: str = "chamfer_mean"

    def describe(self) -> str:
        """One sentence for the tables' headers."""
        text = ("a run is `diverged` when a stage said so (non-finite loss or state, particles leaving the domain, "
                "CFL failure past refinement)")
        if self.cd_ratio > 0:
            text += (f" or its CD exceeds {self.cd_ratio:g} x the prior's (`{self.prior_method}`) on the same "
                     f"scene (`report.divergence_cd_ratio`)")
        return text


def mark_divergence(runs: Runs, rule: DivergenceRule) -> Runs:
    """``runs`` with each record's ``status`` set by ``rule`` and its ``divergence`` reason: ``stage`` (the
    stage's own verdict), ``cd_ratio`` (CD above ``rule.cd_ratio`` x the prior's) or absent. Records are
    copied; the prior's own records are never re-marked. Scenes without an ok prior CD keep the stages'
    verdicts only."""
    out: Runs = {}
    for (scene, method), records in runs.items():
        prior = [v for v in (finite(r.get(rule.key)) for r in runs.get((scene, rule.prior_method), [])
                             if r["status"] == "ok") if v is not None]
        limit = rule.cd_ratio * statistics.fmean(prior) if prior and rule.cd_ratio > 0 else None
        marked = []
        for record in records:
            record = dict(record)
            value = finite(record.get(rule.key))
            if record["status"] == "diverged":
                record.setdefault("divergence", "stage")
            elif (record["status"] == "ok" and method != rule.prior_method and limit is not None
                  and value is not None and value > limit):
                record.update(status="diverged", divergence="cd_ratio", divergence_limit=limit)
            marked.append(record)
        out[scene, method] = marked
    return out
