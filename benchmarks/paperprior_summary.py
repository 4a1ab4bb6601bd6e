"""Summary of harness results in a folder: each finished run (``harness_*.json``) and each run stopped by a time
limit (``stopped_*.json``): status, iterations, s/it, CD, the divergence message, and every k-th iteration of its history
(horizon [frames], loss, gradient norm before clipping, the law's CFL wave-speed estimate [m/s], sim refinement) and
the rejected updates.

    python benchmarks/paperprior_summary.py RESULTS_DIR [--every 5]
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path


def history_lines(history: list[dict], every: int) -> list[str]:
    """One line per ``every``-th record (and the last): iteration, horizon, loss, grad norm, wave speed, refine."""
    picked = [h for h in history if h.get("iteration", 0) % every == 0] + history[-1:]
    seen, lines = set(), []
    for h in picked:
        if h.get("iteration") in seen:
            continue
        seen.add(h.get("iteration"))
        lines.append(f"    it {h.get('iteration'):>4}  horizon {h.get('horizon')}  loss {h.get('loss', float('nan')):.4g}  "
                     f"|g| {h.get('grad_norm', float('nan')):.3g}  c {h.get('wave_speed', float('nan')):.3g} m/s  "
                     f"refine {h.get('sim_refine')}")
    return lines


def summarize(folder: Path, every: int = 5) -> str:
    """Text summary of every harness JSON in ``folder`` (see the module docstring)."""
    out = []
    for path in sorted(folder.glob("harness_*.json")):
        r = json.loads(path.read_text())
        out.append(f"{r['scene']} {r['method']}: {r['status']}, {r['iterations']} its, "
                   f"{r['seconds_per_iteration']:.2f} s/it, peak {r['peak_memory_gib']:.2f} GiB, CD {r.get('chamfer_mean')}, "
                   f"{r['rejected_updates']} rejected; {r.get('message', '')[:300]}")
        out += history_lines(r.get("history", []), every)
        out += [f"    rejected at it {x.get('iteration')} (lr x{x.get('lr_scale')}): {x.get('message', '')[:160]}"
                for x in r.get("rejected", [])]
    for path in sorted(folder.glob("stopped_*.json")):
        r = json.loads(path.read_text())
        out.append(f"{path.stem}: stopped after {r['iterations_done']} iterations, {len(r.get('rejected', []))} rejected")
        out += history_lines(r.get("history", []), every)
    return "\n".join(out) if out else f"{folder}: no harness results"


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("folder", type=Path)
    ap.add_argument("--every", type=int, default=5)
    args = ap.parse_args()
    print(summarize(args.folder, args.every))
