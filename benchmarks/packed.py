"""Throughput of P processes at once on one GPU (session 36): the driver and the worker's side of one start signal.

A packed grid (CUDA MPS, several runs per GPU) is bound by what the GPU gets through, not by one kernel's latency, so a
kernel that loses alone can win packed and the other way round. Each worker sets itself up, touches its ready file,
waits for the shared go file, does its timed work and writes ``{"start": t0, "end": t1, ...}`` (epoch seconds) to its
result file; :func:`run_workers` starts them, gives the go once all are ready and returns the span from the first
start to the last end with the workers' results.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def add_arguments(ap: argparse.ArgumentParser) -> None:
    """The options every packed bench has: ``--mps``, ``--ready-timeout``, ``--json``, and the workers' hidden
    ``--worker``, ``--ready``, ``--go``, ``--result``."""
    ap.add_argument("--mps", action="store_true", help="start the CUDA MPS daemon (root) for the runs, stop it after")
    ap.add_argument("--ready-timeout", type=float, default=240.0)
    ap.add_argument("--json", default=None)
    ap.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    for name in ("--ready", "--go", "--result"):
        ap.add_argument(name, default=None, help=argparse.SUPPRESS)


def run_workers(cmds: list[list[str]], d: Path, ready_timeout: float, what: str) -> tuple[float, list[dict]]:
    """Start one process per ``cmds[i]`` (``--ready``, ``--go``, ``--result`` are appended), in ``d``'s files; go when
    all are ready. Returns (span [s], results). Stops every worker and exits with one line naming ``what`` when one
    fails or is not ready within ``ready_timeout`` [s]."""
    d.mkdir(parents=True, exist_ok=True)
    env = {**os.environ, "PYTHONPATH": f"{ROOT}{os.pathsep}{os.environ.get('PYTHONPATH', '')}"}
    procs = [subprocess.Popen([sys.executable, *cmd, "--ready", str(d / f"ready{i}"), "--go", str(d / "go"),
                               "--result", str(d / f"result{i}.json")], cwd=ROOT, env=env)
             for i, cmd in enumerate(cmds)]
    deadline = time.monotonic() + ready_timeout
    while sum((d / f"ready{i}").exists() for i in range(len(cmds))) < len(cmds):
        if any(q.poll() not in (None, 0) for q in procs) or time.monotonic() > deadline:
            for q in procs:
                q.kill()
            raise SystemExit(f"{what}: a worker failed or was not ready in {ready_timeout:g} s (its stderr is above)")
        time.sleep(0.01)
    (d / "go").touch()
    for q in procs:
        if q.wait() != 0:
            raise SystemExit(f"{what}: a worker exited with status {q.returncode}")
    results = [json.loads((d / f"result{i}.json").read_text()) for i in range(len(cmds))]
    return max(r["end"] for r in results) - min(r["start"] for r in results), results


def ready_then_go(ready: str, go: str) -> float:
    """The worker's side: say ready, wait for the go; returns the start time (epoch seconds)."""
    Path(ready).touch()
    while not Path(go).exists():
        time.sleep(0.005)
    return time.time()


def repeat_after_go(call, times: int, device, ready: str, go: str) -> float:
    """The worker's timed work: ``call()`` once to warm up (kernel loads, graph capture), then, after the go,
    ``times`` times, the device synchronised before and after; returns the start time (epoch seconds)."""
    import torch

    def sync():
        if device.type == "cuda":
            torch.cuda.synchronize(device)

    call()
    sync()
    t0 = ready_then_go(ready, go)
    for _ in range(times):
        call()
    sync()
    return t0


def write_result(path: str, start: float, **extra) -> None:
    """The worker's result: its start, now as its end, and ``extra``."""
    Path(path).write_text(json.dumps({"start": start, "end": time.time(), **extra}))
