"""One frame's steps (law + MPM) replayed from CUDA graphs, forward and backward.

A frame of ``n`` steps launches ~40 small kernels per step from Python (laws in torch, transfers in
warp); at MPM sizes the GPU then waits on the launches (benchmarks/NOTES.md: ~6 ms per step for 10k
and 100k particles alike). :class:`FrameGraphs` captures, once per (material, frame length, particle
count):

- a **forward graph**: static inputs (x, v, C, F) -> static outputs (x, v, C, F, F_trial), no autograd;
- a **backward graph**: the frame recomputed with autograd from static inputs, then
  ``torch.autograd.grad`` of its outputs against static output cotangents, giving the gradients of
  the frame-start state and of the material's trainable parameters.

With a grid stash (:func:`gca.sim.frame.stashable`: a material whose forward takes the generic step; the solver's
``stash_mib``) the forward graph also leaves each step's P2G grid (mv, m) in static buffers, which
:meth:`FrameGraphs.stashed` hands out for the caller to keep per frame, and a second backward graph (the
**replay**) recomputes the frame from such a stash: each step's grid update and G2P from its stashed grid, P2G
skipped (``MPMSolver.step``'s ``grid``), then the same differentiation. Same gradients (bitwise on the CPU).
Where the frame's neural networks run the fused Triton MLP and the solver's ``mlp_stash_mib`` is set, the forward
graph also leaves each step's MLP outputs in static buffers (``gca.laws.neural.frame_mlp_stash``), and a third
backward graph (the **MLP replay**) replays a frame from its grid and MLP stash together: no P2G and no MLP forward
in its recompute (a caller keeps the MLP stash for the frames its budget holds: ``gca.sim.rollout``).

:func:`graphed_frame` wraps them in a ``torch.autograd.Function`` that saves only the frame-start
state, i.e. the same memory profile as per-frame checkpointing (``gca.sim.rollout``), with both
passes replayed instead of launched. Parameters are read from their storage at replay time, so
in-place optimiser updates are seen; anything the law decides in Python (branches, shapes) is frozen
at capture, hence the cache key includes the material object and its trainable parameters.

CPU twin: on a CPU device (or with ``capture=False``) the very same static-buffer code runs eagerly
instead of replaying; the tests compare it with the checkpointed rollout in values and gradients.
If capture fails on a GPU (a law that synchronises with the host, e.g. validates a parameter with
``.item()``), the runner says so once and runs eagerly.
"""

from __future__ import annotations

import contextlib
import gc
import warnings

import torch
from torch import nn

from gca.laws.base import Material
from gca.laws.neural import frame_mlp_stash, fused_mlp_networks, neural_networks
from gca.laws.svd import warp_runs
from gca.sim.frame import simulate_frame_trial, stashable

_WHERE = "gca/sim/graph.py"
_STATE = ("x", "v", "C", "F")


def _trainable(material) -> list[torch.Tensor]:
    """The material's parameters that require gradients, in registration order."""
    return [p for p in material.parameters() if p.requires_grad]


class _Frame(nn.Module):
    """``n_steps`` steps of ``material`` as a module, so the parameters can be swapped for aliases."""

    def __init__(self, solver, material, n_steps: int):
        super().__init__()
        self.solver, self.material, self.n_steps = solver, material, n_steps

    def forward(self, x, v, C, F, vol, mass, grids=None):
        return simulate_frame_trial(self.solver, self.material, self.n_steps, x, v, C, F, vol, mass, grids)


@contextlib.contextmanager
def _collector_paused():
    """Python's cyclic garbage collector off while capturing (collected once before).

    A collection inside a capture can free warp-owned device memory of an unrelated, unreachable
    object (e.g. the grid buffers of an earlier solver, which sits in a reference cycle with its
    graph cache); warp does not know that torch is capturing and frees at once, which CUDA forbids
    during capture (``cudaErrorStreamCaptureUnsupported``): the capture then fails and the frame runs
    eagerly. torch >= 2.6 no longer collects on entering ``torch.cuda.graph``.
    """
    gc.collect()
    was_enabled = gc.isenabled()
    gc.disable()
    try:
        yield
    finally:
        if was_enabled:
            gc.enable()


def mlp_stash_networks(solver, material, stashes: bool, n_steps: int, n: int) -> list:
    """The networks whose MLP outputs a frame runner of ``material`` (``n_steps`` steps of ``n`` particles) keeps
    (``MPMSolver.mlp_stash_mib``): those of :func:`gca.laws.neural.fused_mlp_networks`, where the frame keeps its grid
    stash (``stashes``), the budget holds one frame's outputs, the fused kernels (warp's features, Triton's MLP) run on
    the solver's device, and the material is a plain :class:`gca.laws.base.Material` whose neural networks are its own
    elasticity and plasticity (each called once a step on all n particles, the stash's layout); else none. A
    composite of parts (each network on its slice of the particles), batched runs' laws (``gca.laws.batched``, whose
    networks run outside ``run_mlp``) or one network in both roles keep none (session 57's review)."""
    if not stashes or getattr(solver, "mlp_stash_mib", 0.0) <= 0:
        return []
    nets = fused_mlp_networks(material)
    own = [getattr(material, "elasticity", None), getattr(material, "plasticity", None)]
    plain = (type(material).stress is Material.stress and type(material).project is Material.project
             and own[0] is not own[1] and all(any(net is o for o in own) for net in neural_networks(material)))
    if not nets or not plain:
        return []
    width = sum(net.mlp[-1].out_features for net in nets)
    if n_steps * n * width * torch.empty(0, dtype=solver.dtype).element_size() > solver.mlp_stash_mib * 2 ** 20:
        return []  # not one frame in budget: no buffers, no third graph
    from gca.laws import mlp_triton  # triton: needed only where a network runs the fused MLP

    probe = torch.empty(0, dtype=solver.dtype, device=solver.device)
    return nets if warp_runs(probe) and mlp_triton.runs_here(probe) else []


def _mlp_kernels(material) -> tuple[str, ...]:
    """The MLP kernel of each neural network in ``material`` (``mlp_kernel``), in module order."""
    return tuple(net.mlp_kernel for net in neural_networks(material))


class FrameGraphs:
    """Forward and backward of ``n_steps`` steps of ``material`` on ``n`` particles, replayable.

    Args:
        solver: the :class:`gca.sim.solver.MPMSolver` (fixes dt, grid, device, dtype).
        material: law container with ``stress``/``project`` (an ``nn.Module``).
        n_steps: steps per frame.
        n: particle count.
        capture: capture CUDA graphs (default: when the solver runs on CUDA); False runs the same
            code eagerly (the CPU twin).
    """

    def __init__(self, solver, material, n_steps: int, n: int, capture: bool | None = None):
        self.solver, self.material, self.n_steps, self.n = solver, material, int(n_steps), int(n)
        trainable = [(f"material.{name}", p) for name, p in material.named_parameters() if p.requires_grad]
        self.param_names = [name for name, _ in trainable]  # as seen from self.frame (functional_call)
        self.params = [p for _, p in trainable]
        self.frame = _Frame(solver, material, self.n_steps)
        dev, dt = solver.device, solver.dtype
        self.capture = (dev.type == "cuda") if capture is None else bool(capture)
        self.capture_asked = self.capture  # as built (capture may later fall back to eager)
        # torch's float32 product precision (train.matmul_precision) is baked into a captured graph's kernels: a
        # runner made under one is never reused under another
        self.precision = torch.get_float32_matmul_precision()
        self.kernels = _mlp_kernels(material)  # likewise the neural networks' MLP kernels (train.mlp_kernel)
        # and whether their weight gradients are summed once a frame (MPMSolver.frame_mlp_grads)
        self.frame_sums = bool(getattr(solver, "frame_mlp_grads", False))
        if self.capture and dev.type != "cuda":
            raise ValueError(f"{_WHERE}: CUDA graph capture needs a CUDA solver, this one runs on {dev}")
        shapes = {"x": (n, 3), "v": (n, 3), "C": (n, 3, 3), "F": (n, 3, 3)}
        new = lambda: {k: torch.zeros(s, dtype=dt, device=dev) for k, s in shapes.items()}  # noqa: E731
        self.vol = torch.zeros(n, dtype=dt, device=dev)
        self.mass = torch.zeros(n, dtype=dt, device=dev)
        self.fwd_in, self.bwd_in = new(), new()
        self.bwd_cot = {**new(), "F_trial": torch.zeros(n, 3, 3, dtype=dt, device=dev)}
        # the grid stash: each step's (mv, m) as the forward left them, and the replay's copy of a frame's stash
        self.stashes = stashable(solver, material)
        shapes_g = solver.stash_shapes()
        grid = lambda: tuple(torch.zeros((self.n_steps, *s), dtype=dt, device=dev) for s in shapes_g)  # noqa: E731
        self.fwd_grids, self.bwd_grids = (grid(), grid()) if self.stashes else (None, None)
        # the MLP stash: each step's outputs X [n_steps, N, N_OUT] of each such network, as the forward left them,
        # and the MLP replay's copy of a frame's
        self.mlp_nets = mlp_stash_networks(solver, material, self.stashes, self.n_steps, self.n)
        outs = lambda: [torch.zeros(self.n_steps, n, net.mlp[-1].out_features, dtype=dt, device=dev)  # noqa: E731
                        for net in self.mlp_nets]
        self.fwd_mlp, self.bwd_mlp = (outs(), outs()) if self.mlp_nets else (None, None)
        self.fwd_out = self.bwd_grads = self.rep_grads = self.rpx_grads = None
        self._fwd_graph = self._bwd_graph = self._rep_graph = self._rpx_graph = None

    @property
    def stash_bytes(self) -> int:
        """Bytes of one frame's grid stash (0 where the frame cannot stash)."""
        return sum(t.numel() * t.element_size() for t in self.fwd_grids) if self.stashes else 0

    @property
    def mlp_stash_bytes(self) -> int:
        """Bytes of one frame's MLP stash (0 where the frame cannot keep one)."""
        return sum(t.numel() * t.element_size() for t in self.fwd_mlp) if self.mlp_nets else 0

    def matches(self, material, n_steps: int, n: int, capture: bool | None = None) -> bool:
        return (material is self.material and (self.n_steps, self.n) == (n_steps, n)
                and (capture is None or self.capture_asked == capture)
                and self.precision == torch.get_float32_matmul_precision()
                and self.kernels == _mlp_kernels(material)
                and self.frame_sums == bool(getattr(self.solver, "frame_mlp_grads", False))
                and self.stashes == stashable(self.solver, material)
                and [id(m) for m in self.mlp_nets] == [id(m) for m in mlp_stash_networks(
                    self.solver, material, self.stashes, self.n_steps, self.n)]
                and [id(p) for p in _trainable(material)] == [id(p) for p in self.params])

    def bind(self, vol: torch.Tensor, mass: torch.Tensor) -> None:
        """Copy the (constant) particle volumes and masses [N] into the static buffers."""
        self.vol.copy_(vol)
        self.mass.copy_(mass)

    # -- the two passes, as plain functions of the static buffers -----------------------------------

    def _run_forward(self):
        s = self.fwd_in
        with torch.no_grad(), frame_mlp_stash(self.material, self.fwd_mlp, replay=False):
            return self.frame(s["x"], s["v"], s["C"], s["F"], self.vol, self.mass, self.fwd_grids)

    def _run_backward(self, replay: bool = False, mlp: bool = False):
        """Recompute the frame and differentiate it (``replay``: from the stash in ``bwd_grids``, P2G skipped;
        ``mlp``: and the MLP outputs in ``bwd_mlp``, no MLP forward launched). The
        trainable parameters enter as fresh aliases
        (same storage, new autograd leaves): differentiating the parameters themselves would touch
        their accumulation nodes, which may belong to a live graph on another stream (e.g. a
        regulariser evaluated before the rollout) and then break the capture."""
        with torch.enable_grad(), frame_mlp_stash(self.material, self.bwd_mlp if mlp else None, replay=True):
            ins = [self.bwd_in[k].detach().requires_grad_(True) for k in _STATE]
            alias = {name: p.detach().requires_grad_(True) for name, p in zip(self.param_names, self.params)}
            outs = torch.func.functional_call(self.frame, alias, (*ins, self.vol, self.mass,
                                                                  self.bwd_grids if replay else None), strict=False)
            cots = [self.bwd_cot[k] for k in (*_STATE, "F_trial")]
            leaves = [*ins, *alias.values()]
            grads = torch.autograd.grad(outs, leaves, cots, allow_unused=True)
        return tuple(torch.zeros_like(t) if g is None else g for g, t in zip(grads, leaves))

    # -- capture ------------------------------------------------------------------------------------

    def _ensure_captured(self, backward: bool = True) -> None:
        """Capture the forward graph if not yet, and (``backward``) the backward graphs (the recompute and, where the
        frame stashes, the replay) if not yet, each after a warm-up run on a side stream (lazy inits, warp module
        loads, cuBLAS handles). A rollout without gradients (an evaluation's) captures the forward alone: the
        backward's warm-up and capture were ~3-4 s of an evaluation's ~20 s on the H200 (NOTES session 48)."""
        if not self.capture:
            return
        fwd, bwd = self._fwd_graph is None, backward and self._bwd_graph is None
        if not (fwd or bwd):
            return
        side = torch.cuda.Stream(self.solver.device)
        side.wait_stream(torch.cuda.current_stream(self.solver.device))
        try:
            with torch.cuda.stream(side):  # warm-up
                if fwd:
                    self._run_forward()
                if bwd:
                    self._run_backward()
                    if self.stashes:
                        self._run_backward(replay=True)
                    if self.mlp_nets:
                        self._run_backward(replay=True, mlp=True)
            torch.cuda.current_stream(self.solver.device).wait_stream(side)
            with _collector_paused():
                if fwd:
                    graph = torch.cuda.CUDAGraph()
                    with torch.cuda.graph(graph, capture_error_mode="thread_local"):
                        self.fwd_out = self._run_forward()
                    self._fwd_graph = graph
                if bwd:
                    graph, replay = torch.cuda.CUDAGraph(), torch.cuda.CUDAGraph() if self.stashes else None
                    rpx = torch.cuda.CUDAGraph() if self.mlp_nets else None
                    with torch.cuda.graph(graph, capture_error_mode="thread_local"):
                        self.bwd_grads = self._run_backward()
                    if self.stashes:  # the replays share the recompute's pool: only one runs at a time, on one
                        # stream, and each one's outputs are copied out at once (backward)
                        with torch.cuda.graph(replay, pool=graph.pool(), capture_error_mode="thread_local"):
                            self.rep_grads = self._run_backward(replay=True)
                    if self.mlp_nets:
                        with torch.cuda.graph(rpx, pool=graph.pool(), capture_error_mode="thread_local"):
                            self.rpx_grads = self._run_backward(replay=True, mlp=True)
                    self._bwd_graph, self._rep_graph, self._rpx_graph = graph, replay, rpx
        except RuntimeError as err:  # a host sync inside the law: run eagerly instead
            warnings.warn(f"{_WHERE}: CUDA graph capture of {type(self.material).__name__} failed, running "
                          f"eagerly ({str(err).splitlines()[0]})", RuntimeWarning, stacklevel=3)
            self.capture, self._fwd_graph, self._bwd_graph, self._rep_graph = False, None, None, None
            self._rpx_graph = None
            torch.cuda.synchronize(self.solver.device)

    # -- public passes ----------------------------------------------------------------------------

    def forward(self, x, v, C, F, backward: bool = True):
        """New (x, v, C, F, F_trial) after ``n_steps`` steps, without autograd (fresh tensors). ``backward``: a
        :meth:`backward` of this frame may follow (its graphs are captured with the forward's, before the caller's
        backward pass: a reverse sweep, autograd); False captures the forward's graph alone (no gradient asked)."""
        for k, t in zip(_STATE, (x, v, C, F)):
            self.fwd_in[k].copy_(t)
        self._ensure_captured(backward)
        if self.capture:
            self._fwd_graph.replay()
            out = self.fwd_out
        else:
            out = self._run_forward()
        return tuple(o.clone() for o in out)

    def stashed(self, mlp: bool = False) -> tuple[torch.Tensor, ...] | None:
        """The grid stash of the last :meth:`forward` (copies of each step's mv [n_steps, R G, G, G, 3] and m
        [n_steps, R G, G, G]), for :meth:`backward`'s ``grids``; None where the frame cannot stash. ``mlp`` (where the
        frame keeps one, :attr:`mlp_nets`): followed by copies of its MLP stash, one [n_steps, N, N_OUT] a network."""
        if not self.stashes:
            return None
        return tuple(t.clone() for t in (*self.fwd_grids, *(self.fwd_mlp if mlp and self.mlp_nets else ())))

    def backward(self, state, cotangents, grids=None):
        """Gradients of the frame-start ``state`` (x, v, C, F) and of the trainable parameters.

        Args:
            state: the frame's inputs (x, v, C, F).
            cotangents: gradients of the frame's outputs (x, v, C, F, F_trial).
            grids: the frame's grid stash from :meth:`stashed` after its :meth:`forward` from ``state`` (the
                replay: P2G not recomputed; with the MLP stash after it, the MLP replay: no MLP forward either), or
                None (the recompute).
        """
        if grids is not None and not self.stashes:
            raise ValueError(f"{_WHERE}: a grid stash given to a frame runner that cannot stash")
        mlp = grids is not None and len(grids) > len(self.bwd_grids)
        if mlp and len(grids) != len(self.bwd_grids) + len(self.mlp_nets or ()):
            raise ValueError(f"{_WHERE}: a stash of {len(grids)} tensors given to a frame runner that keeps "
                             f"{len(self.bwd_grids)} grid and {len(self.mlp_nets or ())} MLP tensors")
        for k, t in zip(_STATE, state):
            self.bwd_in[k].copy_(t)
        for k, g in zip((*_STATE, "F_trial"), cotangents):
            self.bwd_cot[k].copy_(g)
        if grids is not None:
            for buf, g in zip((*self.bwd_grids, *(self.bwd_mlp if mlp else ())), grids):
                buf.copy_(g)
        self._ensure_captured()
        if self.capture:
            graph, grads = ((self._bwd_graph, self.bwd_grads) if grids is None else
                            (self._rpx_graph, self.rpx_grads) if mlp else (self._rep_graph, self.rep_grads))
            graph.replay()
        else:
            grads = self._run_backward(replay=grids is not None, mlp=mlp)
        return tuple(g.clone() for g in grads)


class _GraphedFrame(torch.autograd.Function):
    """autograd bridge of :class:`FrameGraphs`: saves the frame-start state only (and the frame's grid stash where
    ``stash``, 1, with its MLP stash where 2)."""

    @staticmethod
    def forward(ctx, runner: FrameGraphs, stash: int, x, v, C, F, *params):
        ctx.runner = runner
        out = runner.forward(x, v, C, F)
        # saved, not kept on ctx: autograd frees the stash with the frame's backward (unless the graph is retained)
        ctx.save_for_backward(x, v, C, F, *(runner.stashed(mlp=stash == 2) if stash else ()))
        return out

    @staticmethod
    def backward(ctx, *cotangents):
        saved = ctx.saved_tensors
        grads = ctx.runner.backward(saved[:4], cotangents, saved[4:] or None)
        return (None, None, *grads)


def graphed_frame(runner: FrameGraphs, x, v, C, F, stash: bool = False, mlp: bool = False):
    """Differentiable frame through the runner: (x, v, C, F) -> (x, v, C, F, F_trial); ``stash``: its backward
    replays the forward's grid stash (the runner must stash: :attr:`FrameGraphs.stashes`); ``mlp``: and its MLP stash
    (where the runner keeps one: :attr:`FrameGraphs.mlp_nets`)."""
    if torch.is_grad_enabled():
        level = 0 if not (stash and runner.stashes) else 2 if mlp and runner.mlp_nets else 1
        return _GraphedFrame.apply(runner, level, x, v, C, F, *runner.params)
    return runner.forward(x, v, C, F, backward=False)  # no gradient: no backward graph captured


class GraphCache:
    """A few :class:`FrameGraphs` per solver, reused across rollouts (training iterations)."""

    def __init__(self, size: int = 4):
        self.size, self.runners = size, []

    def get(self, solver, material, n_steps: int, n: int, capture: bool | None = None) -> FrameGraphs:
        for r in self.runners:
            if r.matches(material, n_steps, n, capture):
                self.runners.remove(r)
                self.runners.append(r)
                return r
        runner = FrameGraphs(solver, material, n_steps, n, capture)
        self.runners.append(runner)
        del self.runners[:-self.size]
        return runner
