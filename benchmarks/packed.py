"""Throughput of P processes at once on one GPU (session 36): the driver and the worker's side of one start signal.

A packed grid (CUDA MPS, several runs per GPU) is bound by what the GPU gets through, not by one kernel's latency, so a
kernel that loses alone can win packed and the other way round. Each worker sets itself up, touches its ready file,
waits for the shared go file, does its timed work and writes ``{"start": t0, "end": t1, ...}`` (``time.monotonic``,
one clock for every process on Linux) to its result file; :func:`run_workers` starts them in a fresh folder, gives the
go once all are ready and returns the span from the first start to the last end with the workers' results. A worker
that fails stops the others; a worker whose driver is gone gives up waiting after ``--ready-timeout``.
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def add_arguments(ap: argparse.ArgumentParser) -> None:
    """The options every packed bench has: ``--mps``, ``--ready-timeout``, ``--run-timeout``, ``--json``, and the
    workers' hidden ``--worker``, ``--ready``, ``--go``, ``--result``."""
    ap.add_argument("--mps", action="store_true", help="start the CUDA MPS daemon (root) for the runs, stop it after")
    ap.add_argument("--ready-timeout", type=float, default=240.0, help="seconds for every worker to be ready [s]")
    ap.add_argument("--run-timeout", type=float, default=600.0, help="seconds for the workers' timed work [s]")
    ap.add_argument("--json", default=None)
    ap.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    for name in ("--ready", "--go", "--result"):
        ap.add_argument(name, default=None, help=argparse.SUPPRESS)


def exit_on_sigterm() -> None:
    """A SIGTERM (``timeout``'s) raises SystemExit in the driver, so its cleanups run: the workers stopped, the MPS
    daemon it started quit (``gca.pipeline.grid.mps_daemon``'s ``finally``)."""
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(143))


def run_workers(cmds: list[list[str]], parent: Path, ready_timeout: float, what: str,
                run_timeout: float = 600.0, envs: list[dict] | None = None) -> tuple[float, list[dict]]:
    """Start one process per ``cmds[i]`` (``--ready``, ``--go``, ``--result`` and ``--ready-timeout`` are appended;
    ``envs[i]``: more of its environment) with its files in a fresh folder under ``parent``; go when all are ready.
    Returns (span [s], results). Exits with one line naming ``what`` when a worker fails, is not ready within
    ``ready_timeout`` [s] or not done within ``run_timeout`` [s] of the go; every worker still running is stopped on
    the way out."""
    parent.mkdir(parents=True, exist_ok=True)
    d = Path(tempfile.mkdtemp(prefix="run", dir=parent))  # fresh: an earlier run's ready and go files cannot count
    extra = os.environ.get("PYTHONPATH")
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT)] + ([extra] if extra else []))}
    procs = [subprocess.Popen([sys.executable, *cmd, "--ready", str(d / f"ready{i}"), "--go", str(d / "go"),
                               "--result", str(d / f"result{i}.json"), "--ready-timeout", str(ready_timeout)],
                              cwd=ROOT, env={**env, **(envs[i] if envs else {})}) for i, cmd in enumerate(cmds)]
    try:
        deadline = time.monotonic() + ready_timeout
        while sum((d / f"ready{i}").exists() for i in range(len(cmds))) < len(cmds):
            if any(q.poll() not in (None, 0) for q in procs) or time.monotonic() > deadline:
                raise SystemExit(f"{what}: a worker failed or was not ready in {ready_timeout:g} s (its stderr is "
                                 "above)")
            time.sleep(0.01)
        (d / "go").touch()
        deadline = time.monotonic() + run_timeout
        while any(q.poll() is None for q in procs):  # all at once: the first to fail stops the rest
            if any(q.poll() not in (None, 0) for q in procs):
                break
            if time.monotonic() > deadline:
                raise SystemExit(f"{what}: the workers were not done {run_timeout:g} s after the go")
            time.sleep(0.01)
        failed = [q.returncode for q in procs if q.poll() not in (None, 0)]
        if failed:
            raise SystemExit(f"{what}: a worker exited with status {failed[0]}")
    finally:
        for q in procs:
            if q.poll() is None:
                q.kill()
                q.wait()
    results = [json.loads((d / f"result{i}.json").read_text()) for i in range(len(cmds))]
    return max(r["end"] for r in results) - min(r["start"] for r in results), results


def ready_then_go(ready: str, go: str, timeout: float = 240.0) -> float:
    """The worker's side: say ready, wait for the go (at most ``timeout`` [s]: a driver that died gives none); returns
    the start time (``time.monotonic``)."""
    Path(ready).touch()
    deadline = time.monotonic() + timeout
    while not Path(go).exists():
        if time.monotonic() > deadline:
            raise SystemExit(f"packed worker: no go within {timeout:g} s of being ready ({go})")
        time.sleep(0.0005)
    return time.monotonic()


def repeat_after_go(call, times: int, device, a) -> float:
    """The worker's timed work: ``call()`` once to warm up (kernel loads, graph capture), then, after the go (``a``:
    the worker's parsed options, ``ready``, ``go``, ``ready_timeout``), ``times`` times, the device synchronised before
    and after; returns the start time (``time.monotonic``)."""
    import torch

    def sync():
        if device.type == "cuda":
            torch.cuda.synchronize(device)

    call()
    sync()
    t0 = ready_then_go(a.ready, a.go, a.ready_timeout)
    for _ in range(times):
        call()
    sync()
    return t0


def write_result(path: str, start: float, **extra) -> None:
    """The worker's result: its start, now as its end (``time.monotonic``), and ``extra``."""
    Path(path).write_text(json.dumps({"start": start, "end": time.monotonic(), **extra}))


def ratios(rows: list[dict], key: str, base, cost: str) -> None:
    """``row[key]`` = its baseline's ``cost`` over the row's (``base(row)``: the baseline row or None; ``cost``: lower
    is better), for every row once all were measured (a baseline listed later still counts); None without one."""
    for r in rows:
        b = base(r)
        r[key] = b[cost] / r[cost] if b else None
