"""Warp launches on torch's current CUDA stream (one place for the stream policy)."""

from __future__ import annotations

import contextlib

import torch
import warp as wp

_WARP_STREAMS: dict[int, wp.Stream] = {}


def on_torch_stream(device: torch.device):
    """Context in which warp launches on ``device`` go to torch's current stream; a no-op on the CPU.

    No event wait on entry (``sync_enter=False``): all our warp work is issued on torch's stream,
    and a cross-stream wait would break CUDA graph capture (``gca.sim.graph``). The warp wrapper of
    each torch stream is made once (creating one per launch costs host time).
    """
    device = torch.device(device)
    if device.type != "cuda":
        return contextlib.nullcontext()
    torch_stream = torch.cuda.current_stream(device)
    stream = _WARP_STREAMS.get(torch_stream.cuda_stream)
    if stream is None:
        wp.init()  # wrapping a torch stream needs warp's runtime (a caller's first launch may come before any init)
        stream = _WARP_STREAMS[torch_stream.cuda_stream] = wp.stream_from_torch(torch_stream)
    return wp.ScopedStream(stream, sync_enter=False)
