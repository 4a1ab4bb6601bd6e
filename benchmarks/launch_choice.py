"""The launch-estimate variant chosen on the calibration scenes, by the rule declared before the runs (NOTES s22).

    python benchmarks/launch_choice.py OUT     # OUT: benchmarks/launch_calib_bundle.sh's output folder

Reads each ``<scene>_seed<k>.log`` (the rows ``benchmarks/velocity_fit.py`` prints as each fit ends, so a call cut
off keeps the fits it finished) and ranks the variants by the median over the (scene, seed) units of the launch
error ``|v0 - v0_true|`` [m/s] (from its along-ray and in-plane parts). Rule: the lowest median among the variants
fitted on every unit; a variant within ``TIE`` [m/s] of a lower-ranked earlier one (simpler: fewer terms, fewer
frames) yields to it. Writes ``OUT/launch_choice.json``.
"""

from __future__ import annotations

import json
import math
import re
import statistics
import sys
from pathlib import Path

TIE = 0.05  # [m/s]
ROW = re.compile(r"^(?P<variant>.*?)\s+seed (?P<seed>\d+)\s+(?P<gt>[-+]\d+\.\d+)\s+(?P<along>[-+]\d+\.\d+)\s+"
                 r"(?P<plane>\d+\.\d+)\s+(?P<w0>\d+\.\d+)\s+(?P<loss>\S+)$")


def rows(out: Path) -> list[dict]:
    """Every fitted (variant, scene, seed) row of the logs, once."""
    seen = {}
    for log in sorted(out.glob("*_seed*.log")):
        scene = log.name.rsplit("_seed", 1)[0]
        for line in log.read_text(errors="replace").splitlines():
            m = ROW.match(line.strip())
            if m:
                along, plane = float(m["along"]), float(m["plane"])
                seen[(m["variant"].strip(), scene, int(m["seed"]))] = {
                    "variant": m["variant"].strip(), "scene": scene, "seed": int(m["seed"]), "along": along,
                    "in_plane": plane, "error": math.hypot(along, plane), "w0_error": float(m["w0"])}
    return list(seen.values())


def choose(table: list[dict]) -> dict:
    """Per variant (first-seen order): units, median |error|, median |along|, median in-plane; and the choice."""
    order = list(dict.fromkeys(r["variant"] for r in table))
    units = {(r["scene"], r["seed"]) for r in table}
    summary = []
    for v in order:
        mine = [r for r in table if r["variant"] == v]
        summary.append({"variant": v, "units": len(mine), "median_error": statistics.median(r["error"] for r in mine),
                        "median_abs_along": statistics.median(abs(r["along"]) for r in mine),
                        "median_in_plane": statistics.median(r["in_plane"] for r in mine),
                        "max_error": max(r["error"] for r in mine)})
    complete = [s for s in summary if s["units"] == len(units)]
    best = None
    for s in complete:  # earlier variants first: a later one must beat the best so far by more than TIE
        if best is None or s["median_error"] < best["median_error"] - TIE:
            best = s
    return {"units": len(units), "variants": summary, "choice": best and best["variant"], "tie_m_s": TIE}


def main(argv=None) -> dict:
    out = Path((argv or sys.argv[1:])[0])
    result = choose(rows(out))
    print(f"{'variant':60s} {'units':>5s} {'median |err|':>12s} {'|along|':>8s} {'in-plane':>8s} {'max':>6s}")
    for s in result["variants"]:
        print(f"{s['variant'] or '(params.yaml)':60s} {s['units']:5d} {s['median_error']:12.3f} "
              f"{s['median_abs_along']:8.3f} {s['median_in_plane']:8.3f} {s['max_error']:6.2f}")
    print(f"chosen (rule: lowest median over all {result['units']} units, ties within {TIE} m/s to the earlier): "
          f"{result['choice']!r}")
    (out / "launch_choice.json").write_text(json.dumps(result, indent=1))
    return result


if __name__ == "__main__":
    main()
