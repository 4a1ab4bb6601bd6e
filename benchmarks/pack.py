"""Packing several training runs onto one GPU: N concurrent copies of a harness run vs one alone.

Issue 8 asks for the six-scene Table 1 in a few commands of at most 10 minutes, packing scenes or
methods onto the GPU where that is what it takes. A single run leaves the GPU mostly idle (small
kernels, host syncs), so concurrent processes should add throughput until the GPU saturates. This
measures it side by side: the solo figures come from a harness run in ``--work`` (made first, same
command), then ``--copies`` copies of that work directory train and evaluate the same methods at once
(data and prior reused, so only training and evaluation run). Usage::

    python benchmarks/harness.py --work /tmp/h --methods gca neuma --set train.iterations=10 ... --out $OUT
    python benchmarks/pack.py --work /tmp/h --copies 3 --methods gca neuma --set train.iterations=10 ... --out $OUT

Writes ``pack_<scene>_x<N>.json`` and prints a table: per-copy seconds per iteration and peak memory,
and the packing gain = N x (solo train seconds) / (slowest packed train seconds).
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))
from harness import result_name  # noqa: E402
KEEP = ("assets", "prior", "scene", "gt", "prep", "m", "particles.npz")  # what the copies reuse (not runs/eval)


def copy_work(work: Path, dest: Path) -> None:
    """Copy the reusable part of a harness work directory (inputs, not training outputs)."""
    if dest.exists():
        shutil.rmtree(dest)
    dest.mkdir(parents=True)
    for name in KEEP:
        src = work / name
        if src.is_dir():
            shutil.copytree(src, dest / name)
        elif src.is_file():
            shutil.copy2(src, dest / name)


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--work", type=Path, required=True, help="a harness work directory (solo run done)")
    ap.add_argument("--scene", default="duck")
    ap.add_argument("--methods", nargs="+", default=["gca", "neuma"])
    ap.add_argument("--copies", type=int, default=3)
    ap.add_argument("--profile", default="paper")
    ap.add_argument("--set", dest="overrides", action="append", default=[])
    ap.add_argument("--solver", dest="solver", action="append", default=[], metavar="SWITCH=yaml_value",
                    help="an MPMSolver switch for every copy (harness.py --solver; session 51: a packed A/B of a kernel path)")
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--device", default="cuda", help="as given to the harness (names its JSON files)")
    args = ap.parse_args(argv)
    solo = {m: json.loads((args.out / result_name(args.profile, args.scene, m, args.device)).read_text())
            for m in args.methods}
    procs, works = [], []
    for i in range(args.copies):
        works.append(args.work.with_name(f"{args.work.name}_pack{i}"))
        copy_work(args.work, works[-1])
    t0 = time.perf_counter()
    for i, w in enumerate(works):
        cmd = [sys.executable, str(ROOT / "benchmarks" / "harness.py"), "--scene", args.scene, "--profile", args.profile,
               "--work", str(w), "--out", str(args.out), "--device", args.device, "--tag", f"_pack{i}", "--reuse-prior", "--reuse-data",
               "--methods", *args.methods] + [a for s in args.overrides for a in ("--set", s)] \
            + [a for s in args.solver for a in ("--solver", s)]
        log = open(args.out / f"pack_{args.scene}_copy{i}.log", "w")
        procs.append((subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT, cwd=ROOT), log))
    codes = []
    for p, log in procs:
        codes.append(p.wait())
        log.close()
    wall = time.perf_counter() - t0
    rows = []
    for i in range(args.copies):
        for m in args.methods:
            path = args.out / result_name(args.profile, args.scene, m, args.device, f"_pack{i}")
            if path.is_file():
                r = json.loads(path.read_text())
                rows.append({"copy": i, "method": m, "train_seconds": r["train_seconds"],
                             "seconds_per_iteration": r["seconds_per_iteration"], "peak_memory_gib": r["peak_memory_gib"],
                             "status": r["status"]})
    solo_train = sum(solo[m]["train_seconds"] for m in args.methods)
    packed_train = max((sum(r["train_seconds"] for r in rows if r["copy"] == i) for i in range(args.copies)), default=float("nan"))
    result = {"scene": args.scene, "methods": args.methods, "copies": args.copies, "exit_codes": codes,
              "overrides": args.overrides, "solver": args.solver, "device": solo[args.methods[0]]["device"], "wall_seconds": wall,
              "solo_train_seconds": solo_train, "packed_train_seconds_slowest": packed_train,
              "packing_gain": args.copies * solo_train / packed_train if rows else None, "rows": rows,
              "solo": {m: {k: solo[m][k] for k in ("seconds_per_iteration", "train_seconds", "peak_memory_gib")}
                       for m in args.methods}}
    (args.out / f"pack_{args.scene}_x{args.copies}.json").write_text(json.dumps(result, indent=2) + "\n")
    print(f"\n{'run':<16}{'s/it':>8}{'train s':>9}{'peak GiB':>9}  status")
    for m in args.methods:
        s = solo[m]
        print(f"{'solo/' + m:<16}{s['seconds_per_iteration']:>8.2f}{s['train_seconds']:>9.1f}{s['peak_memory_gib']:>9.2f}  {s['status']}")
    for r in rows:
        print(f"{'copy' + str(r['copy']) + '/' + r['method']:<16}{r['seconds_per_iteration']:>8.2f}"
              f"{r['train_seconds']:>9.1f}{r['peak_memory_gib']:>9.2f}  {r['status']}")
    print(f"packing gain (N x solo train / slowest packed train): {result['packing_gain']}; exit codes {codes}")
    return result


if __name__ == "__main__":
    main(sys.argv[1:])
