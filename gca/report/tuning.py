"""The tuning record's tables (issue 22 items 1-2): the knobs chosen on the calibration scenes, and each RDGA
term's share of the gradient there (``tuning_calibration.md``), from ``tuning/record.json``
(:mod:`gca.pipeline.tuning` writes it; params ``tuning.record`` cites it)."""

from __future__ import annotations

import json
import math
from pathlib import Path

import pandas as pd

from gca.report.tables import markdown_table


def _fmt(value, digits: int = 3) -> str:
    return "n/a" if value is None or not math.isfinite(value) else f"{value:.{digits}g}"


def shares_frame(record: dict) -> pd.DataFrame:
    """One row per (method, trial shown, calibration scene): CD and each constrained term's norm share and cosine
    (trial 0, the frozen params before tuning, and the chosen trial)."""
    rows = []
    for method, entry in record.get("methods", {}).items():
        chosen = entry.get("chosen", {}).get("trial")
        for trial in entry["trials"]:
            if trial["trial"] not in (0, chosen):
                continue
            label = "chosen" if trial["trial"] == chosen else "frozen (trial 0)"
            if trial["trial"] == 0 == chosen:
                label = "frozen = chosen"
            by_scene: dict[str, list[dict]] = {}
            for unit in trial["units"]:
                by_scene.setdefault(unit["scene"], []).append(unit)
            for scene, units in sorted(by_scene.items()):
                row = {"method": method, "trial": f"{trial['trial']} ({label})", "scene": scene,
                       "seeds": str(len(units)),
                       "CD": _fmt(sum(u["chamfer_mean"] for u in units) / len(units)
                                  if all(u.get("chamfer_mean") is not None for u in units) else None)}
                for term in trial["score"]["shares"]:
                    norms, coss = [], []
                    for u in units:
                        sh = u.get("term_shares") or {}
                        if sh.get("share/total/norm") and f"share/{term}/norm" in sh:
                            norms.append(sh[f"share/{term}/norm"] / sh["share/total/norm"])
                            coss.append(sh[f"share/{term}/cos"])
                    row[f"{term} norm share"] = _fmt(sum(norms) / len(norms) if norms else None)
                    row[f"{term} cos"] = _fmt(sum(coss) / len(coss) if coss else None)
                rows.append(row)
    return pd.DataFrame(rows).fillna("—")


def write_tuning_tables(record_path: str | Path | None, out_dir: Path) -> list[Path]:
    """``tuning_calibration.md`` in ``out_dir``: the cited record's choices and the RDGA terms' shares on the
    calibration scenes, or a line saying no tuning record is cited yet."""
    md = out_dir / "tuning_calibration.md"
    head = ["# Tuning on the calibration scenes", ""]
    if not record_path or not Path(record_path).is_file():
        md.write_text("\n".join(head + [
            "No tuning record is cited (params `tuning.record` is empty): no knob has been moved by a tuning; the "
            "frozen values are the paper's / published ones. `python -m gca.pipeline.tune` (tuning/README.md) makes "
            "one on the calibration scenes only."]) + "\n", encoding="utf-8")
        return [md]
    record = json.loads(Path(record_path).read_text())
    budget, objective = record["budget"], record["objective"]
    lines = head + [
        f"- Record: `{record_path}` ({record['date']}, commit {record['commit']}, {record['device']}, profile "
        f"{record['profile']}, benchmark {record['benchmark_version']}).",
        f"- Budget, every method: {budget['trials']} trials x {budget['iterations']} iterations x seeds "
        f"{budget['seeds']} on {', '.join(budget['scenes'])} (calibration scenes only).",
        f"- Search: {record['search']['kind']} over log-ranges, seed {record['search']['sampler_seed']}; trial 0 = "
        "the frozen params.",
        f"- Objective: {objective['metric']}; constraint: {objective['constraint']} (floors "
        f"{objective['share_floor_norm']}, {objective['share_floor_cos']}).", "", "## Chosen values", ""]
    chosen = []
    for method, entry in record["methods"].items():
        c = entry.get("chosen")
        if c:
            chosen += [{"method": method, "trial": str(c["trial"]), "feasible": str(c["feasible"]), "key": key,
                        "value": f"{value:.6g}"} for key, value in c["params"].items()]
    lines.append(markdown_table(pd.DataFrame(chosen)) if chosen else "(incomplete record: nothing chosen)")
    lines += ["", "## Each RDGA term's share of the gradient on the calibration scenes", "",
              "norm share: the term's gradient norm |g_T| over the total's |g|; cos: its cosine with the total gradient "
              "(means over the measured iterations, `train.term_shares_every`, and the seeds).", ""]
    frame = shares_frame(record)
    lines.append(markdown_table(frame) if not frame.empty else "(no runs)")
    md.write_text("\n".join(lines) + "\n", encoding="utf-8")
    csv = out_dir / "tuning_calibration.csv"
    csv.write_text(frame.to_csv(index=False, lineterminator="\n"), encoding="utf-8")
    return [md, csv]
