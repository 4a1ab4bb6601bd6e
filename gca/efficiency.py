"""Efficiency probes: wall time and peak memory of a block, parameter counts.

Peak memory on CUDA is ``torch.cuda.max_memory_allocated`` (reset on entry), i.e. tensor memory
only. On CPU torch's allocator is invisible to ``tracemalloc``, so the probe samples the process
resident set size (``/proc/self/statm``) from a background thread every ``interval_s`` and reports
the peak and its increase over the value at entry; where /proc is absent it falls back to
``resource.getrusage`` (lifetime peak, not resettable: the delta is then a lower bound).
"""

from __future__ import annotations

import contextlib
import os
import resource
import threading
import time
from dataclasses import dataclass, field
from typing import Iterator, Optional

import torch


@dataclass
class Usage:
    """Filled when the :func:`measure` block exits.

    Attributes:
        wall_s: wall-clock time of the block [s].
        peak_bytes: peak memory [bytes]: CUDA tensor memory, or the process RSS on CPU.
        delta_bytes: peak minus the value at entry [bytes].
        source: how memory was measured (``"cuda"``, ``"rss-sampled"``, ``"ru_maxrss"``).
    """

    wall_s: float = float("nan")
    peak_bytes: int = 0
    delta_bytes: int = 0
    source: str = ""
    extra: dict = field(default_factory=dict)

    def as_dict(self, prefix: str = "") -> dict[str, float]:
        """Log-friendly ``{prefix + name: value}`` with memory in MiB."""
        return {f"{prefix}wall_s": self.wall_s, f"{prefix}peak_mib": self.peak_bytes / 2 ** 20,
                f"{prefix}delta_mib": self.delta_bytes / 2 ** 20}


def _rss_bytes() -> Optional[int]:
    try:
        with open("/proc/self/statm") as fh:
            return int(fh.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")
    except (OSError, ValueError, IndexError):
        return None


def _maxrss_bytes() -> int:
    return int(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss) * 1024  # Linux reports KiB


class _RssSampler(threading.Thread):
    """Background thread keeping the largest RSS seen until stopped."""

    def __init__(self, interval_s: float):
        super().__init__(daemon=True)
        self.interval_s, self.peak = interval_s, _rss_bytes() or 0
        self._stop_event = threading.Event()

    def run(self) -> None:
        while not self._stop_event.wait(self.interval_s):
            self.peak = max(self.peak, _rss_bytes() or 0)

    def stop(self) -> int:
        self._stop_event.set()
        self.join()
        self.peak = max(self.peak, _rss_bytes() or 0)
        return self.peak


def synced_clock(device: str | torch.device) -> float:
    """``time.perf_counter()`` [s] once the device has finished its queued work (CUDA synchronised)."""
    device = torch.device(device)
    if device.type == "cuda":
        torch.cuda.synchronize(device)
    return time.perf_counter()


def best_time_us(fn, device: str | torch.device, iters: int, repeats: int) -> float:
    """The best of ``repeats`` rounds' mean wall time per call of ``fn`` over ``iters`` calls [us], after one untimed
    warm-up round; the device synchronised around each round (the benchmarks' kernel timings)."""
    rounds = []
    for _ in range(max(1, repeats) + 1):
        t0 = synced_clock(device)
        for _ in range(iters):
            fn()
        rounds.append((synced_clock(device) - t0) / iters)
    return min(rounds[1:]) * 1e6  # the first round warms up (JIT, caches) and is not counted


@contextlib.contextmanager
def measure(device: str | torch.device = "cpu", interval_s: float = 0.005) -> Iterator[Usage]:
    """Measure wall time and peak memory of a ``with`` block.

    Args:
        device: where the work runs; CUDA devices use the torch allocator statistics.
        interval_s: RSS sampling period on CPU [s].

    Yields:
        A :class:`Usage` filled in when the block exits.
    """
    usage, device = Usage(), torch.device(device)
    if device.type == "cuda":
        torch.cuda.synchronize(device)
        torch.cuda.reset_peak_memory_stats(device)
        start_mem, usage.source = torch.cuda.memory_allocated(device), "cuda"
    elif _rss_bytes() is not None:
        sampler, usage.source = _RssSampler(interval_s), "rss-sampled"
        start_mem = sampler.peak
        sampler.start()
    else:
        start_mem, usage.source = _maxrss_bytes(), "ru_maxrss"
    t0 = time.perf_counter()
    try:
        yield usage
    finally:
        if device.type == "cuda":
            torch.cuda.synchronize(device)
            usage.peak_bytes = torch.cuda.max_memory_allocated(device)
        else:
            usage.peak_bytes = sampler.stop() if usage.source == "rss-sampled" else _maxrss_bytes()
        usage.wall_s = time.perf_counter() - t0
        usage.delta_bytes = max(0, usage.peak_bytes - start_mem)


def count_parameters(module: torch.nn.Module, trainable_only: bool = True) -> int:
    """Number of (trainable) scalar parameters of ``module``."""
    return sum(p.numel() for p in module.parameters() if p.requires_grad or not trainable_only)
