"""One GPU per stage process when several DVC queue workers share a machine.

`dvc queue start -j N` starts N workers that all inherit one environment, so they cannot be pinned to
GPUs from outside, and every stage would land on GPU 0. With ``GCA_GPU_PER_PROCESS=1`` in that
environment, importing :mod:`gca` makes each stage process claim a GPU that no other gca process
holds (an exclusive lock on one file per GPU, released when the process exits) and narrow
``CUDA_VISIBLE_DEVICES`` to it before CUDA starts; while every GPU is held, it waits for one. A process
whose ``CUDA_VISIBLE_DEVICES`` is already set (``gca/pipeline/grid.py`` pins its jobs) is left alone.

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


def claim(n_gpus: int, lock_dir: Path, poll_s: float = 2.0, timeout_s: float | None = None) -> int:
    """Index in ``0 .. n_gpus - 1`` of a GPU this process now holds alone (until it exits).

    Tries the GPUs in order; while all are held, polls every ``poll_s`` seconds. Raises ``TimeoutError``
    after ``timeout_s`` seconds (None: waits as long as it takes).
    """
    global _held
    if n_gpus < 1:
        raise ValueError(f"gca.gpu_slot: no GPU to claim (n_gpus={n_gpus})")
    lock_dir.mkdir(parents=True, exist_ok=True)
    start = time.monotonic()
    while True:
        for k in range(n_gpus):
            handle = open(lock_dir / f"gpu{k}.lock", "a")
            try:
                fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                handle.close()
                continue
            _held = handle
            return k
        if timeout_s is not None and time.monotonic() - start >= timeout_s:
            raise TimeoutError(f"gca.gpu_slot: all {n_gpus} GPUs held by other gca processes for {timeout_s} s "
                               f"(locks in {lock_dir})")
        time.sleep(poll_s)


def pin_from_env(n_gpus: int | None = None) -> int | None:
    """Apply ``GCA_GPU_PER_PROCESS=1``: claim a GPU and make it the only one this process sees.

    Returns the claimed index, or None when the variable is not ``1``, ``CUDA_VISIBLE_DEVICES`` is
    already set, or the machine has no GPU (``n_gpus``: the count, default :func:`gpu_count`).
    """
    if os.environ.get(ENV) != "1" or "CUDA_VISIBLE_DEVICES" in os.environ:
        return None
    n = gpu_count() if n_gpus is None else n_gpus
    if n == 0:
        return None
    k = claim(n, default_lock_dir())
    os.environ["CUDA_DEVICE_ORDER"] = "PCI_BUS_ID"  # CUDA's order = nvidia-smi's, which the index counts in
    os.environ["CUDA_VISIBLE_DEVICES"] = str(k)
    print(f"gca: {ENV}=1: this process uses GPU {k} of {n}", file=sys.stderr)
    return k
