"""GPU slots for stage processes when several DVC queue workers share a machine.

`dvc queue start -j N` starts N workers that all inherit one environment, so they cannot be pinned to
GPUs from outside, and every stage would land on GPU 0. With ``GCA_GPU_PER_PROCESS=1`` in that
environment, importing :mod:`gca` makes each stage process claim a slot that no other gca process
holds (an exclusive lock on one file per slot, released when the process exits) and narrow
``CUDA_VISIBLE_DEVICES`` to the slot's GPU before CUDA starts; while every slot is held, it waits for one.
``GCA_RUNS_PER_GPU=K`` (default 1) gives each GPU K slots, so that K queue workers share a GPU, the
packing the grid's ``--slots`` gives its jobs (issue 20 item 3: under CUDA MPS, eight ball trainings on one H100
gave 2.4x the throughput of one; the daemon is started around the queue by whoever starts the queue, README).
A process takes a slot on the GPU with the most free slots, so the runs spread over the GPUs.
The same variable is the runs' record of their packing (``gca.pipeline.train``: ``runs_per_gpu``), as under the grid.
A process whose ``CUDA_VISIBLE_DEVICES`` is already set (``gca/pipeline/grid.py`` pins its jobs) is left alone.

Standard library only: this runs at ``import gca``, before torch or warp touch CUDA.
"""

from __future__ import annotations

import fcntl
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import IO

ENV = "GCA_GPU_PER_PROCESS"
RUNS_ENV = "GCA_RUNS_PER_GPU"  # slots per GPU (also read by gca.pipeline.train as the runs' packing)
LOCK_DIR_ENV = "GCA_GPU_LOCK_DIR"
_held: IO | None = None  # the open lock file of the claimed GPU, kept for the life of the process


def gpu_count() -> int:
    """GPUs on this machine as ``nvidia-smi -L`` lists them (CUDA is not initialised); 0 without it."""
    try:
        out = subprocess.run(["nvidia-smi", "-L"], capture_output=True, text=True, timeout=60)
    except (OSError, subprocess.TimeoutExpired):
        return 0
    return sum(line.startswith("GPU ") for line in out.stdout.splitlines()) if out.returncode == 0 else 0


def default_lock_dir() -> Path:
    return Path(os.environ.get(LOCK_DIR_ENV) or Path(tempfile.gettempdir()) / f"gca-gpu-{os.getuid()}")


def runs_per_gpu() -> int:
    """``GCA_RUNS_PER_GPU``: slots per GPU [count], default 1; anything but an integer >= 1 is refused in one line."""
    value = os.environ.get(RUNS_ENV) or "1"
    if not (value.isascii() and value.isdigit()) or int(value) < 1:
        raise ValueError(f"gca.gpu_slot: {RUNS_ENV}={value!r}: the runs per GPU must be an integer >= 1")
    return int(value)


MPS_ENV = "GCA_MPS"  # whether the runs shared their GPU under CUDA MPS ("1"/"0"; read by gca.pipeline.train)
MPS_PRIORITY_ENV = "CUDA_MPS_CLIENT_PRIORITY"  # CUDA's own (MPS docs, environment variables): a client's coarse
MPS_BELOW_NORMAL = "1"  # priority over every stream it makes, read when CUDA starts: "0" normal, "1" below normal
PRIORITY_GRID_ENV = "GCA_MPS_PRIORITY"  # "1": the grid that started the run gave its lighter units below-normal
# priority (gca.pipeline.grid.below_normal), so the run's time is no equal share of its GPU (read by gca.pipeline.train)


def mps_running() -> bool:
    """Whether a CUDA MPS control daemon serves this process: its ``control`` entry exists in
    ``CUDA_MPS_PIPE_DIRECTORY`` (default ``/tmp/nvidia-mps``, where ``nvidia-cuda-mps-control -d`` makes its pipes and
    sockets), and, where it is a named pipe, something reads it (a write-only open without blocking fails with ENXIO
    when no daemon does: one killed without its cleanup). Any other entry is taken at its word (a stale socket reads
    as on); an unreadable directory as off."""
    control = Path(os.environ.get("CUDA_MPS_PIPE_DIRECTORY") or "/tmp/nvidia-mps") / "control"
    try:
        if not control.exists():
            return False
        if control.is_fifo():
            os.close(os.open(control, os.O_WRONLY | os.O_NONBLOCK))
        return True
    except OSError:
        return False


def _lock_name(gpu: int, slot: int) -> str:
    """Slot 0 keeps the one-slot name (``gpu<k>.lock``), so one-slot and K-slot processes exclude each other there."""
    return f"gpu{gpu}.lock" if slot == 0 else f"gpu{gpu}.slot{slot}.lock"


def _free(path: Path) -> bool:
    """Whether nobody holds the lock at ``path`` now (taken and let go at once: a hint, another process may take it
    next)."""
    with open(path, "a") as handle:
        try:
            fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            return False
        fcntl.flock(handle, fcntl.LOCK_UN)
        return True


def claim(n_gpus: int, lock_dir: Path, poll_s: float = 2.0, timeout_s: float | None = None, per_gpu: int = 1) -> int:
    """Index in ``0 .. n_gpus - 1`` of the GPU of a slot this process now holds alone (until it exits).

    Tries the GPUs with the most free slots first (ties in index order), each GPU's slots in order, ``per_gpu`` slots
    per GPU, so the runs spread over the GPUs whatever order the others freed theirs in; while all are held, polls
    every ``poll_s`` seconds. Raises ``TimeoutError`` after ``timeout_s`` seconds (None: waits as long as it takes).
    """
    global _held
    if n_gpus < 1:
        raise ValueError(f"gca.gpu_slot: no GPU to claim (n_gpus={n_gpus})")
    if per_gpu < 1:
        raise ValueError(f"gca.gpu_slot: no slot to claim (per_gpu={per_gpu})")
    lock_dir.mkdir(parents=True, exist_ok=True)
    start = time.monotonic()
    while True:
        free = {k: sum(_free(lock_dir / _lock_name(k, j)) for j in range(per_gpu)) if per_gpu > 1 else 1
                for k in range(n_gpus)}
        for k, j in ((k, j) for k in sorted(range(n_gpus), key=lambda g: -free[g]) for j in range(per_gpu)):
            handle = open(lock_dir / _lock_name(k, j), "a")
            try:
                fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                handle.close()
                continue
            _held = handle
            return k
        if timeout_s is not None and time.monotonic() - start >= timeout_s:
            slots = f" x {per_gpu} slots" if per_gpu > 1 else ""
            raise TimeoutError(f"gca.gpu_slot: all {n_gpus} GPUs{slots} held by other gca processes for {timeout_s} s "
                               f"(locks in {lock_dir})")
        time.sleep(poll_s)


def pin_from_env(n_gpus: int | None = None) -> int | None:
    """Apply ``GCA_GPU_PER_PROCESS=1``: claim a slot (``GCA_RUNS_PER_GPU`` per GPU) and make its GPU the only one
    this process sees.

    Returns the claimed index, or None when the variable is not ``1``, ``CUDA_VISIBLE_DEVICES`` is
    already set, or the machine has no GPU (``n_gpus``: the count, default :func:`gpu_count`).
    """
    try:  # checked whether or not this process pins itself: the runs record it (train.json), after their training
        per_gpu = runs_per_gpu()
    except ValueError as exc:  # at `import gca`, before any stage's own error handling: one line, exit status 2
        print(exc, file=sys.stderr)
        raise SystemExit(2) from None
    if os.environ.get(ENV) != "1" or "CUDA_VISIBLE_DEVICES" in os.environ:
        return None
    n = gpu_count() if n_gpus is None else n_gpus
    if n == 0:
        return None
    k = claim(n, default_lock_dir(), per_gpu=per_gpu)
    os.environ["CUDA_DEVICE_ORDER"] = "PCI_BUS_ID"  # CUDA's order = nvidia-smi's, which the index counts in
    os.environ["CUDA_VISIBLE_DEVICES"] = str(k)
    os.environ.setdefault(MPS_ENV, "1" if mps_running() else "0")  # the run's record (a launcher's own value kept)
    shared = f", shared by up to {per_gpu} runs ({RUNS_ENV}, CUDA MPS {'on' if os.environ[MPS_ENV] == '1' else 'off'})" \
        if per_gpu > 1 else ""
    print(f"gca: {ENV}=1: this process uses GPU {k} of {n}{shared}", file=sys.stderr)
    return k
