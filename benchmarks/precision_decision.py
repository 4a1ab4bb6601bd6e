"""Issue 20: the precision decision for ``train.mlp_kernel: triton_tf32`` (the neural laws' MLP with TF32 products,
session 37), on the calibration scenes only, by a rule fixed in session 38 before any of its runs.

The option is the one speed lever measured over its rule's line (1.22x on a 30k rollout, H200), and it changes the
numbers: TF32 keeps 10 of FP32's 23 mantissa bits in every product. It becomes the default only if GCA trained with it
is as good as with FP32 on scenes that are in no table, with the same budget (science rules: tune on calibration
scenes only). The runs are two tunings of one trial each, trial 0 being the frozen params (``gca.pipeline.tune``: the
calibration scenes, a table scene refused; GPU, paper profile; ``tuning/README.md`` for sharding and resuming)::

    python -m gca.pipeline.tune --work /tmp/prec_fp32 --profile paper --priors models/prior --methods gca \\
        --set "tuning.record=''" --set tuning.trials=1 --set "tuning.seeds=[0,1,2]" --set train.mlp_kernel=torch \\
        --record /tmp/prec_fp32/record.json
    python -m gca.pipeline.tune --work /tmp/prec_tf32 --profile paper --priors models/prior --methods gca \\
        --set "tuning.record=''" --set tuning.trials=1 --set "tuning.seeds=[0,1,2]" --set train.mlp_kernel=triton_tf32 \\
        --record /tmp/prec_tf32/record.json
    python benchmarks/precision_decision.py --reference /tmp/prec_fp32/record.json \\
        --candidate /tmp/prec_tf32/record.json --json /tmp/prec_decision.json

(3 scenes x 3 seeds x 2 settings = 18 GCA trainings of 200 iterations; evaluation runs torch's FP32 MLP on both, so
the CDs compare the laws, not the evaluation's arithmetic.)

**The rule** (fixed before the runs): adopt the candidate as the default only if

1. the two records are comparable: the same profile, benchmark version and budget, each complete (GCA's trial 0
   with a unit for every (scene, seed) of the budget), at least 2 seeds per scene, and overrides that differ by
   ``train.mlp_kernel`` alone, ``triton_tf32`` in the candidate, ``torch`` (or unset) in the reference;
   (since session 44 a tuning record also holds the ``mlp_kernel`` its runs used, which is what is compared: the
   paper profile's default became ``triton_tf32`` then, so a reference now sets ``train.mlp_kernel=torch``; the
   session's own records, made at the old default, hold no such field and read as above)
2. no unit of either record diverged or failed (a diverged FP32 seed would widen the spread the candidate is held
   to), and every CD is finite;
3. on every scene, the candidate's mean CD over the seeds differs from the reference's by no more than the
   reference's own seed spread there (the largest minus the smallest of its seeds' CDs).

Otherwise ``train.mlp_kernel`` stays ``torch`` (after session 44's adoption, a ``--method`` check that keeps torch would
need a per-method knob, not built). A record that is not comparable is refused (exit 2, one line), not decided. Tests: ``tests/test_bench_precision_decision.py``.

**Decided in session 44** (NVIDIA H200, the records in ``benchmarks/results/fast10_s44/precision/``): every scene's move
within its seed spread, no unit failed: **adopted**. params.yaml's paper profile runs ``triton_tf32`` since (the CI
profile torch's MLP).
"""

from __future__ import annotations

import argparse
import itertools
import json
import math
import sys
from pathlib import Path

import yaml

KNOB = "train.mlp_kernel"
CANDIDATE, REFERENCE = "triton_tf32", "torch"
METHOD = "gca"


class Refused(SystemExit):
    """A record the rule cannot decide on: one line on stderr, exit status 2."""

    def __init__(self, why: str):
        print(f"precision_decision.py: {why}", file=sys.stderr)
        super().__init__(2)


def _units(record: dict, where: str, method: str = METHOD) -> dict[tuple[str, int], dict]:
    """``method``'s trial-0 units of a tuning record, keyed by (scene, seed)."""
    try:
        trial = next(t for t in record["methods"][method]["trials"] if t["trial"] == 0)
    except (KeyError, StopIteration):
        raise Refused(f"{where}: no trial 0 of {method} in this tuning record") from None
    return {(u["scene"], int(u["seed"])): u for u in trial["units"]}


def _overrides(record: dict) -> dict:
    """A record's ``--set`` overrides as {key: value}, the values read as YAML (as ``grid.apply_overrides`` reads
    them: ``[0,1]`` and ``[0, 1]`` are one value)."""
    out = {}
    for item in record.get("overrides", []):
        key, _, value = item.partition("=")
        out[key.strip()] = yaml.safe_load(value)
    return out


def _kernel(record: dict) -> str:
    """The MLP kernel a record's runs trained with: its own ``mlp_kernel`` (tuning records since session 44), else its
    override, else torch. A record without either was made when params.yaml's default was torch (until session 44)."""
    return record.get("mlp_kernel") or _overrides(record).get(KNOB, REFERENCE)


def comparable(ref: dict, cand: dict, method: str = METHOD) -> str | None:
    """Why the two records cannot be compared by the rule (its point 1), or None."""
    for key in ("profile", "benchmark_version", "budget"):
        if ref.get(key) != cand.get(key):
            return f"their {key} differ ({ref.get(key)!r} vs {cand.get(key)!r})"
    a, b = _overrides(ref), _overrides(cand)
    changed = sorted(k for k in set(a) | set(b) if a.get(k) != b.get(k))
    if changed != [KNOB]:
        return f"their overrides must differ by {KNOB} alone, they differ by {changed or 'nothing'}"
    kernels = _kernel(cand), _kernel(ref)
    if kernels != (CANDIDATE, REFERENCE):
        return (f"the rule compares {KNOB}: {CANDIDATE} (candidate) with {REFERENCE} (reference), got "
                f"{kernels[0]!r} and {kernels[1]!r} (a reference made since session 44 must set {KNOB}=torch: "
                f"the paper profile's default is {CANDIDATE})")
    budget = ref.get("budget") or {}
    expected = set(itertools.product(budget.get("scenes", []), [int(k) for k in budget.get("seeds", [])]))
    units = {name: set(_units(record, name, method)) for name, record in (("reference", ref), ("candidate", cand))}
    for name, held in units.items():
        missing = sorted(f"{s}@seed{k}" for s, k in expected - held)
        if not expected or missing:
            return f"the {name} is not complete: its budget's units {missing or '(none listed)'} are missing"
    if units["reference"] != units["candidate"]:
        return "they hold different (scene, seed) units"
    seeds: dict[str, set[int]] = {}
    for scene, seed in units["reference"]:
        seeds.setdefault(scene, set()).add(seed)
    few = sorted(s for s, k in seeds.items() if len(k) < 2)
    if few:
        return f"the rule needs >= 2 seeds per scene (a seed spread); {few} have fewer"
    return None


def decide(ref: dict, cand: dict, method: str = METHOD) -> dict:
    """The rule's verdict on two comparable tuning records of ``method`` (GCA, the rule's own; another method's
    trial 0, e.g. NeuMA's, checks that the knob, global to every method's training, does not hurt it either): per
    scene the reference's mean CD and seed spread, the candidate's mean CD, its move and whether it is within the
    spread; the units of either not ``ok``; ``adopt``."""
    why = comparable(ref, cand, method)
    if why is not None:
        raise Refused(f"the records are not comparable: {why}")
    ru, cu = _units(ref, "reference", method), _units(cand, "candidate", method)
    scenes = {}
    for scene in sorted({s for s, _ in ru}):
        keys = sorted(k for k in ru if k[0] == scene)
        r = [ru[k].get("chamfer_mean") for k in keys]
        c = [cu[k].get("chamfer_mean") for k in keys]
        finite = all(v is not None and math.isfinite(v) for v in r + c)
        row = {"seeds": [k[1] for k in keys], "reference_cd": r, "candidate_cd": c, "finite": finite}
        if finite:
            row.update(reference_mean=sum(r) / len(r), candidate_mean=sum(c) / len(c), spread=max(r) - min(r))
            row["move"] = row["candidate_mean"] - row["reference_mean"]
            row["within"] = abs(row["move"]) <= row["spread"]
        scenes[scene] = row
    bad = sorted(f"{name} {s}@seed{k}: {u.get('status')}" for name, units in (("candidate", cu), ("reference", ru))
                 for (s, k), u in units.items() if u.get("status") != "ok")
    adopt = not bad and all(r["finite"] and r["within"] for r in scenes.values())
    return {"knob": KNOB, "method": method, "candidate": _kernel(cand), "reference": _kernel(ref),
            "scenes": scenes, "not_ok": bad, "adopt": adopt}


def table(result: dict) -> str:
    """The verdict as markdown: a row per scene, then the decision."""
    lines = ["| scene | seeds | reference mean CD | seed spread | candidate mean CD | move | within |",
             "| --- | --- | --- | --- | --- | --- | --- |"]
    for scene, r in result["scenes"].items():
        if r["finite"]:
            lines.append(f"| {scene} | {len(r['seeds'])} | {r['reference_mean']:.6f} | {r['spread']:.6f} | "
                         f"{r['candidate_mean']:.6f} | {r['move']:+.6f} | {'yes' if r['within'] else 'no'} |")
        else:
            lines.append(f"| {scene} | {len(r['seeds'])} | non-finite CD | | | | no |")
    if result["not_ok"]:
        lines.append(f"\nUnits not ok: {', '.join(result['not_ok'])}")
    whose = "" if result.get("method", METHOD) == METHOD else f" ({result['method']}'s trial 0)"
    verdict = (f"adopt {KNOB}: {result['candidate']}{whose}" if result["adopt"] else
               f"keep {KNOB}: {result['reference']}{whose} (the rule is not met)")
    return "\n".join(lines) + f"\n\n**Decision: {verdict}.**"


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--reference", type=Path, required=True, help="the FP32 tuning record (train.mlp_kernel: torch)")
    ap.add_argument("--candidate", type=Path, required=True, help="the tuning record with the candidate's knob")
    ap.add_argument("--json", type=Path, help="write the verdict here too")
    ap.add_argument("--method", default=METHOD, help="whose trial 0 the records compare (default gca, the rule's)")
    args = ap.parse_args(argv)
    records = []
    for path in (args.reference, args.candidate):
        try:
            records.append(json.loads(path.read_text()))
        except (OSError, ValueError) as exc:
            raise Refused(f"{path}: not a readable tuning record ({exc})") from None
    result = decide(*records, method=args.method)
    print(table(result))
    if args.json:
        args.json.write_text(json.dumps(result, indent=1))
    return result


if __name__ == "__main__":
    main()
