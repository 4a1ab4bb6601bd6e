"""Where a GPU code path synchronises with the host (a diagnostic script, CUDA only).

Runs one call of a code path under torch's sync debug mode, records the Python stack of every
"synchronizing CUDA operation" warning and prints them grouped by the innermost frame inside
``gca/`` (count, file:line, code), most frequent first. Torch's detector sees its own blocking ops
(``.item()``, ``float(t)``, boolean-mask indexing, ``nonzero``, blocking host<->device copies); warp
launches are not seen.

    python benchmarks/find_syncs.py cpr          # one CPR residual call (what the GCA loss does per frame)

Writes the full stacks to ``--out`` (default benchmarks/results/syncs_<path>.txt).
"""

from __future__ import annotations

import argparse
import collections
import traceback
import warnings
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]


def cpr_call():
    """A callable making one CPR residual call on 320 near-identity F (after a warm-up call)."""
    from gca.align.cpr import CPR
    from gca.pipeline.schema import load_section
    from gca.laws.neural import NeuralElasticity, NeuralPlasticity

    g = torch.Generator().manual_seed(0)
    F = (torch.eye(3) + 0.06 * torch.randn(320, 3, 3, generator=g)).cuda()
    Ftr = (torch.eye(3) + 0.06 * torch.randn(320, 3, 3, generator=g)).cuda()
    el, pl = NeuralElasticity().cuda(), NeuralPlasticity().cuda()
    cpr = CPR(load_section("align.cpr", ROOT / "params.yaml"), 320, 0)
    cpr.residuals(el, pl, F, Ftr)
    torch.cuda.synchronize()
    return lambda: cpr.residuals(el, pl, F, Ftr)


PATHS = {"cpr": cpr_call}


def record_syncs(fn) -> list[list[traceback.FrameSummary]]:
    """Stacks of the synchronising operations of one ``fn()`` call."""
    stacks = []

    def hook(message, category, filename, lineno, file=None, line=None):
        if "synchroniz" in str(message).lower() and "prototype" not in str(message).lower():
            stacks.append(traceback.extract_stack()[:-1])

    with warnings.catch_warnings():  # restores warnings.showwarning on exit
        warnings.simplefilter("always")
        warnings.showwarning = hook
        torch.cuda.set_sync_debug_mode("warn")
        try:
            fn()
        finally:
            torch.cuda.set_sync_debug_mode("default")
    return stacks


def innermost_gca_frame(stack: list[traceback.FrameSummary]) -> str:
    for frame in reversed(stack):
        if "/gca/" in frame.filename:
            return f"{Path(frame.filename).relative_to(ROOT)}:{frame.lineno}  {frame.line}"
    return "(outside gca)"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("path", choices=sorted(PATHS))
    ap.add_argument("--out", type=Path)
    args = ap.parse_args(argv)
    if not torch.cuda.is_available():
        raise SystemExit("find_syncs.py needs a CUDA device")
    stacks = record_syncs(PATHS[args.path]())
    sites = collections.Counter(innermost_gca_frame(s) for s in stacks)
    out = args.out or ROOT / "benchmarks" / "results" / f"syncs_{args.path}.txt"
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text("\n\n".join("".join(traceback.format_list(s)) for s in stacks))
    print(f"{len(stacks)} synchronising operations in one '{args.path}' call; by innermost gca frame:")
    for site, count in sites.most_common():
        print(f"{count:>4}  {site}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
