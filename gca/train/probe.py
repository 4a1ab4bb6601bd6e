"""Where non-finite gradients enter: counters on intermediate tensors of one training step.

A non-finite gradient on the law's parameters says nothing about its origin: the losses, the
rasterizer's backward, the Gaussians-from-particles map or the simulator (law included). A
:class:`GradProbe` hooks the tensors between those stages and counts non-finite entries of the
gradient reaching each one, as device tensors (no host sync during backward); the counts are read
once, and the message then names the furthest-downstream stage whose gradient was already broken.
Training attaches it only to a replay of an iteration whose gradient came out non-finite
(``gca.train.loop._provenance``): on every iteration its hooks cost a large share of a host-bound
iteration (NOTES session 39).
"""

from __future__ import annotations

import torch

# stages from the loss back to the parameters, in the order autograd reaches them, and the backward
# that produced the gradient arriving at each
STAGES = ("render outputs", "gaussians", "particles")
CULPRIT = {"render outputs": "the losses' backward", "gaussians": "the rasterizer's backward",
           "particles": "the particles-to-Gaussians map's backward"}


class GradProbe:
    """Counts non-finite gradient entries per (stage, tensor name, frame)."""

    def __init__(self):
        self.counts: list[tuple[str, str, int, torch.Tensor]] = []

    def watch(self, stage: str, name: str, frame: int, t: torch.Tensor) -> None:
        """Count the non-finite entries of the gradient that will reach ``t`` [any shape]."""
        self._hook(stage, t, lambda g: self.record(stage, name, frame, g))

    def watch_frames(self, stage: str, name: str, frames: list[int], t: torch.Tensor) -> None:
        """:meth:`watch` for ``t`` [T, ...] holding the frames ``frames`` (T of them) along its first dim: each
        frame's non-finite entries counted apart."""
        def record_frames(g: torch.Tensor) -> None:
            counts = (~torch.isfinite(g)).reshape(len(frames), -1).sum(-1)
            self.counts.extend((stage, name, frame, counts[i]) for i, frame in enumerate(frames))
        self._hook(stage, t, record_frames)

    @staticmethod
    def _hook(stage: str, t, record) -> None:
        """``record`` the gradient that will reach ``t`` (a tensor that requires it; anything else: nothing)."""
        if stage not in STAGES:
            raise ValueError(f"gca/train/probe.py: unknown stage {stage!r}; one of {STAGES}")
        if isinstance(t, torch.Tensor) and t.requires_grad:
            t.register_hook(record)

    def record(self, stage: str, name: str, frame: int, g: torch.Tensor) -> None:
        """Count the non-finite entries of ``g``, a gradient that reached ``stage``'s tensor ``name`` at ``frame``
        (what :meth:`watch`'s hook does; called directly where the gradient is taken by hand)."""
        self.counts.append((stage, name, frame, (~torch.isfinite(g)).sum()))

    def report(self) -> str:
        """One line: per stage, the tensors with non-finite gradients and the frames where they were."""
        if not self.counts:
            return "no probed tensor received a gradient"
        bad: dict[str, dict[str, list[int]]] = {s: {} for s in STAGES}
        values = torch.stack([c for *_, c in self.counts]).tolist()  # one sync
        for (stage, name, frame, _), n in zip(self.counts, values):
            if n:
                bad[stage].setdefault(name, []).append(frame)
        parts = []
        for stage in STAGES:
            if bad[stage]:
                names = ", ".join(f"{k} at frames {sorted(set(v))[:5]}" for k, v in bad[stage].items())
                parts.append(f"{stage}: non-finite ({names})")
            else:
                parts.append(f"{stage}: finite")
        first = next((s for s in STAGES if bad[s]), None)
        origin = (f"first broken at '{first}': made by {CULPRIT[first]}" if first
                  else "every probed gradient finite: made by the simulator/law backward or a parameter-only "
                       "term (CPR)")
        return "; ".join(parts) + f"; {origin}"
