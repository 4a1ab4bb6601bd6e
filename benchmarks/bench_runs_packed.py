"""MPS packing and batched runs together: P processes at once, each rolling out B runs in one launch per step
(a script, not a test; issue 20 item 3, session 36).

Session 13 measured the two ways to put several runs on one GPU apart: B runs batched in one process
(``bench_runs.py --laws batched``: 1.33x at B = 8 against one after another) and whole trainings packed as processes
under CUDA MPS (2.2x at 4, 2.4x at 8: ``pack_bundle.sh``, session 32). Whether they add up was not measured. Here the
total number of runs R = P x B is fixed and split between processes and batches: P workers
(``python -m benchmarks.bench_runs_packed --worker``) each build B LoRA-adapted neural laws on lattice blocks (as
``bench_runs.py``), warm up (graph capture), say ready, wait for one start signal, then roll out ``--rollouts`` times
(forward + backward, ``--steps`` steps in frames). Throughput = run-rollouts per second over the span from the first
worker's start to the last one's end; the table gives it against P = B = 1 (one run, one process).

Only the simulation and the law (the part batching covers, ~75 % of a swept training iteration's kernels, session 31);
rendering and the losses are not in it.

Session 47: ``PxB:K`` runs the last K of the P processes at CUDA MPS's below-normal client priority
(``gca.gpu_slot.MPS_PRIORITY_ENV``), the others at normal; the row gives each group's mean time from the go to its
own end, so whether the GPU serves the normal ones first while the low ones fill in (the grid's priority for its
longest trainings) shows against ``PxB`` (all normal). ``--rollouts-each`` fixes every process's work across configs,
``--short S N`` gives the last S processes N rollouts (a grid's short runs beside its long ones: whether the priority
shortens the span itself).

Usage (the GPU machine; ``--mps`` starts and stops the MPS daemon through ``gca.pipeline.grid.mps_daemon``)::

    python benchmarks/bench_runs_packed.py --device cuda --mps --configs 1x1 8x1 4x2 2x4 1x8 --json out.json
    python benchmarks/bench_runs_packed.py --device cuda --mps --configs 4x1 12x1 12x1:8 --rollouts-each 30
    python benchmarks/bench_runs_packed.py --device cuda --mps --configs 12x1 12x1:8 --rollouts-each 60 --short 8 30
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # run as a script from anywhere
from benchmarks.packed import (add_arguments, exit_on_sigterm, ratios, repeat_after_go, run_workers,  # noqa: E402
                               write_result)
from gca.gpu_slot import MPS_BELOW_NORMAL, MPS_PRIORITY_ENV  # noqa: E402 (standard library only)


def parse_config(text: str) -> tuple[int, int, int]:
    """``"PxB"`` or ``"PxB:K"`` -> (processes, runs per process, how many of the processes, the last ones, run at
    MPS's below-normal priority; 0 without ``:K``), P, B >= 1 and 0 <= K <= P."""
    try:
        shape, _, low = text.lower().partition(":")
        p, b = (int(t) for t in shape.split("x"))
        k = int(low) if low else 0
    except ValueError:
        raise argparse.ArgumentTypeError(f"a config is PxB or PxB:K (processes x runs per process, K of them at low "
                                         f"priority), got {text!r}") from None
    if p < 1 or b < 1 or not 0 <= k <= p:
        raise argparse.ArgumentTypeError(f"a config needs P >= 1, B >= 1 and 0 <= K <= P, got {text!r}")
    return p, b, k


def worker(a) -> None:
    """One process: B runs' batched rollout (``bench_runs.runs_setup`` with this worker's seed, ``as_batch``; one run
    alone on the plain solver); ready file, wait for the go file, ``--rollouts`` timed rollouts; writes
    ``{"start": t0, "end": t1}`` (``time.monotonic``) to ``--result``."""
    import torch
    import warp as wp

    from benchmarks.bench_runs import as_batch, one_rollout, runs_setup

    wp.config.quiet = True
    device = torch.device(a.device)
    if device.type == "cuda" and device.index is None:
        device = torch.device("cuda", torch.cuda.current_device())
    solver, x, vol, mass, laws, v0s = runs_setup(a.runs, a.particles, a.n_grid, device, a.seed)
    batch = (solver, laws[0], x, v0s[0], vol, mass) if a.runs == 1 else as_batch(solver, x, vol, mass, laws, v0s)
    write_result(a.result, repeat_after_go(lambda: one_rollout(*batch, a.steps, a.steps_per_frame), a.rollouts,
                                           device, a), particles_per_run=x.shape[0],
                 priority=os.environ.get(MPS_PRIORITY_ENV))


def run_config(p: int, b: int, rollouts: int, a, tmp: Path, low: int = 0, short: tuple[int, int] = (0, 0)) -> dict:
    """P workers of B runs at once, the last ``low`` of them at MPS's below-normal client priority, the last
    ``short[0]`` of them doing ``short[1]`` rollouts instead of ``rollouts`` (a grid's short runs beside its long
    ones); returns the config's row (throughput in run-rollouts per second; each priority group's mean seconds from
    the go to a worker's end, None for an empty group)."""
    each = [short[1] if i >= p - short[0] else rollouts for i in range(p)]
    cmds = [["-m", "benchmarks.bench_runs_packed", "--worker", "--device", a.device, "--runs", str(b),
             "--particles", str(a.particles), "--n-grid", str(a.n_grid), "--steps", str(a.steps),
             "--steps-per-frame", str(a.steps_per_frame), "--rollouts", str(each[i]), "--seed", str(i)]
            for i in range(p)]
    envs = [{MPS_PRIORITY_ENV: MPS_BELOW_NORMAL} if i >= p - low else {} for i in range(p)]
    span, rs = run_workers(cmds, tmp, a.ready_timeout, f"bench_runs_packed: config {p}x{b}" + (f":{low}" if low else ""),
                           a.run_timeout, envs)
    go = min(r["start"] for r in rs)
    took = [r["end"] - go for r in rs]

    def mean(group):
        return statistics.fmean(group) if group else None
    total = b * sum(each)
    return {"processes": p, "runs_per_process": b, "runs": p * b, "rollouts_per_process": rollouts,
            "short_processes": short[0], "short_rollouts": short[1] if short[0] else None,
            "low_priority": low, "particles_per_run": rs[0]["particles_per_run"], "span_s": span,
            "run_rollouts_per_s": total / span, "s_per_run_rollout": span / total,
            "mean_s_normal": mean(took[:p - low]), "mean_s_low": mean(took[p - low:]),
            "priorities": [r.get("priority") for r in rs]}


def main(argv=None) -> list[dict]:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", default="cuda")
    ap.add_argument("--configs", type=parse_config, nargs="+",
                    default=[(1, 1, 0), (8, 1, 0), (4, 2, 0), (2, 4, 0), (1, 8, 0)])
    ap.add_argument("--run-rollouts", type=int, default=64,
                    help="run-rollouts per config (P x B x rollouts per process, at least 2 per process)")
    ap.add_argument("--rollouts-each", type=int, default=None,
                    help="rollouts per process in every config instead (the same work per process)")
    ap.add_argument("--short", type=int, nargs=2, default=(0, 0), metavar=("S", "N"),
                    help="the last S processes of every config of more than S do N rollouts (short runs beside long)")
    ap.add_argument("--particles", type=int, default=30000)
    ap.add_argument("--n-grid", type=int, default=32)
    ap.add_argument("--steps", type=int, default=200)
    ap.add_argument("--steps-per-frame", type=int, default=20)
    add_arguments(ap)
    for name in ("--runs", "--rollouts", "--seed"):
        ap.add_argument(name, type=int, default=1, help=argparse.SUPPRESS)
    a = ap.parse_args(argv)
    if a.worker:
        worker(a)
        return []
    from gca.pipeline.grid import mps_daemon

    exit_on_sigterm()
    rows = []
    solo = lambda r: next((x for x in rows if x["runs"] == 1), None)  # noqa: E731
    print("| processes x runs each : low priority | runs | rollouts each | span s | run-rollouts / s | x (1 x 1) | "
          "mean s, normal / low |\n| --- | --- | --- | --- | --- | --- | --- |", flush=True)
    fmt = lambda v: "-" if v is None else f"{v:.2f}"  # noqa: E731
    with tempfile.TemporaryDirectory() as tmp, mps_daemon(a.mps, lambda m: print(m, flush=True)) as mps_on:
        for p, b, low in a.configs:
            each = a.rollouts_each if a.rollouts_each else max(2, a.run_rollouts // (p * b))
            r = run_config(p, b, each, a, Path(tmp), low, tuple(a.short) if p > a.short[0] else (0, 0))
            r["mps"] = mps_on
            rows.append(r)
            ratios(rows, "x_solo", solo, "s_per_run_rollout")
            print(f"| {p} x {b} : {low} | {p * b} | {r['rollouts_per_process']} | {r['span_s']:.2f} | "
                  f"{r['run_rollouts_per_s']:.2f} | " + (f"{r['x_solo']:.2f}x |" if r["x_solo"] else "- |")
                  + f" {fmt(r['mean_s_normal'])} / {fmt(r['mean_s_low'])} |", flush=True)
            if a.json:  # after every row: a command stopped by its limit keeps what it measured
                Path(a.json).write_text(json.dumps({"device": a.device, "mps": bool(a.mps), "rows": rows}, indent=2))
    return rows


if __name__ == "__main__":
    main()
