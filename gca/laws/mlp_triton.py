"""The neural laws' MLP as one fused Triton kernel each way: ``mlp_kernel: triton_tf32`` (``NeuralElasticity.mlp_kernel``,
``train.mlp_kernel``). Its products are TF32, a precision change. It was decided on the calibration scenes only, never
on a table's result (``benchmarks/NOTES.md``, sessions 37 and 44), and is params.yaml's paper-profile default since
session 44 (the CI profile runs torch's MLP).

The MLP (``gca.laws.neural.make_mlp``: z [N, 13] -> 64 -> 64 -> 9, exact GELU, bias-free; the equations in
:mod:`gca.laws.mlp_kernel`) runs as (:class:`FusedMLP`):

- forward: one launch, a block of particles per program, the [BLOCK, 64] activations on chip, nothing stored but
  the inputs;
- backward: one persistent launch (``BWD_PROGRAMS_PER_SM`` programs of ``BWD_WARPS`` warps) that recomputes each
  tile's forward on chip, stores dz per
  particle and sums the three weight gradients over its tiles in registers, one partial per program, which torch sums
  in a fixed order (no atomics: deterministic), the three in one reduction (since session 45: the duck's profile
  had the three sums at 30.7 ms of a 563-ms iteration, 6.4 us each, latency-bound);
- or, within a frame (:func:`frame_weights`, ``MPMSolver.frame_mlp_grads``, on by default since session 58): each
  backward stores its programs' partials in its own block of the frame's rows (:class:`FrameSum`), and the rows are
  summed once a frame.

Measured (NVIDIA H200, graph-replayed, ``benchmarks/bench_mlp_triton.py`` and ``bench_mlp_packed.py``, session 37): at
30k particles TF32 forward 10.9 us alone against torch's FP32 33.2, forward + backward 87.3 against 123.9, at 8
processes under MPS 4.33x and 1.44x torch's throughput; at 100k alone 26.8 / 187.1 us against 98.1 / 303.3 (there
the backward's programs loop over two tiles or more). Session 39 swept the backward's launch (13 launches, H200):
4 warps x 2 programs per SM (the defaults since) took forward + backward to 58.2 us at 30k, 117.2 at 100k, and 2.28x
torch's throughput at 8 processes (43.3 against 98.5 us per call), although it spills 68 registers. The FP32
(``ieee``) kernels lose to torch (0.57x packed) and
are here for the float64 interpreter twin only.

The weights are the layers' effective (LoRA-merged) weights, so gradients reach the adapters through torch's autograd
of the merge. Triton reads ``TRITON_INTERPRET`` when this module is imported (its kernels are decorated then): on a
CPU it runs only in Triton's interpreter (``TRITON_INTERPRET=1`` before the import; the tests), where ``tf32`` dots are
computed in float32.
"""

from __future__ import annotations

import torch
import triton
import triton.language as tl
from triton.runtime.interpreter import InterpretedFunction

_WHERE = "gca/laws/mlp_triton.py"
BLOCK = 64  # particles per program (tl.dot needs >= 16; 64 measured fastest of 32 / 64 in TF32, session 36-37)


@triton.jit
def _gelu(x):
    """Exact GELU, x Phi(x) (torch's default ``nn.GELU()``)."""
    return 0.5 * x * (1.0 + tl.math.erf(x * 0.7071067811865476))



@triton.jit(do_not_specialize=["n"])  # one compiled kernel for every particle count (:func:`_bwd_launch`)
def _fused_mlp_fwd(x_ptr, w1_ptr, w2_ptr, w3_ptr, out_ptr, n, K_IN: tl.constexpr, K_PAD: tl.constexpr,
                   H: tl.constexpr, N_OUT: tl.constexpr, OUT_PAD: tl.constexpr, BLOCK: tl.constexpr,
                   PRECISION: tl.constexpr):
    """One program: BLOCK particles' rows of out = W3 gelu(W2 gelu(W1 x)) (torch's weight layouts [out, in]); the
    inputs padded K_IN -> K_PAD and the outputs N_OUT -> OUT_PAD with zeros (tl.dot needs 16)."""
    rows = tl.program_id(0) * BLOCK + tl.arange(0, BLOCK)
    live = rows < n
    k = tl.arange(0, K_PAD)
    h = tl.arange(0, H)
    o = tl.arange(0, OUT_PAD)
    x = tl.load(x_ptr + rows[:, None] * K_IN + k[None, :], mask=live[:, None] & (k[None, :] < K_IN), other=0.0)
    w1t = tl.load(w1_ptr + h[None, :] * K_IN + k[:, None], mask=k[:, None] < K_IN, other=0.0)  # [K_PAD, H]
    a = _gelu(tl.dot(x, w1t, input_precision=PRECISION))
    w2t = tl.load(w2_ptr + h[None, :] * H + h[:, None])  # [H, H]
    a = _gelu(tl.dot(a, w2t, input_precision=PRECISION))
    w3t = tl.load(w3_ptr + o[None, :] * H + h[:, None], mask=o[None, :] < N_OUT, other=0.0)  # [H, OUT_PAD]
    y = tl.dot(a, w3t, input_precision=PRECISION)
    tl.store(out_ptr + rows[:, None] * N_OUT + o[None, :], y, mask=live[:, None] & (o[None, :] < N_OUT))



@triton.jit
def _gelu_and_grad(x):
    """(x Phi(x), its derivative Phi(x) + x phi(x)) with one erf written: the backward's recompute needs both
    (session 38; before, the source took erf twice per activation, which the compiler may already have merged; the
    same values)."""
    cdf = 0.5 * (1.0 + tl.math.erf(x * 0.7071067811865476))
    return x * cdf, cdf + x * 0.3989422804014327 * tl.exp(-0.5 * x * x)



@triton.jit(do_not_specialize=["n", "n_programs", "per_program"])  # one compiled kernel for every particle count
def _fused_mlp_bwd(x_ptr, g_ptr, w1_ptr, w2_ptr, w3_ptr, dx_ptr, dw1_ptr, dw2_ptr, dw3_ptr, part_stride, n,
                   n_programs, per_program, K_IN: tl.constexpr, K_PAD: tl.constexpr, H: tl.constexpr,
                   N_OUT: tl.constexpr, OUT_PAD: tl.constexpr, BLOCK: tl.constexpr, PRECISION: tl.constexpr,
                   INTERPRETED_PER: tl.constexpr):
    """One persistent program: for its per_program tiles (pid, pid + n_programs, ...) of BLOCK particles, the forward
    recomputed on chip, then the backward of out = W3 gelu(W2 gelu(W1 x)) for the output cotangent g: dx stored per
    particle; the weight gradients summed over the program's tiles in registers and stored once as this program's
    partial (at dw*_ptr + pid part_stride: the three partials of a program share one row of the caller's buffer,
    which it sums in one reduction, in a fixed order: no atomics, deterministic). The caller sizes the grid so that
    fewer than per_program iterations of all programs fall past the last tile.

    per_program is a runtime count, so one compiled kernel serves every particle count. Compiled, the loop runs to it
    (INTERPRETED_PER 0). Triton's interpreter cannot loop to a runtime bound, so there INTERPRETED_PER repeats it as a
    compile-time count (:func:`_bwd_launch`)."""
    pid = tl.program_id(0)
    k = tl.arange(0, K_PAD)
    h = tl.arange(0, H)
    o = tl.arange(0, OUT_PAD)
    w1 = tl.load(w1_ptr + h[:, None] * K_IN + k[None, :], mask=k[None, :] < K_IN, other=0.0)  # [H, K_PAD]
    w2 = tl.load(w2_ptr + h[:, None] * H + h[None, :])  # [H, H]
    w3 = tl.load(w3_ptr + o[:, None] * H + h[None, :], mask=o[:, None] < N_OUT, other=0.0)  # [OUT_PAD, H]
    dw1 = tl.zeros((H, K_PAD), dtype=w1.dtype)
    dw2 = tl.zeros((H, H), dtype=w1.dtype)
    dw3 = tl.zeros((OUT_PAD, H), dtype=w1.dtype)
    # tile pid + i programs (past the last tile: every row masked); the bound is chosen at compile time, inline (the
    # interpreter turns every assigned value into a tensor, which it cannot loop to)
    for i in range(0, INTERPRETED_PER if INTERPRETED_PER > 0 else per_program):
        rows = (pid + i * n_programs) * BLOCK + tl.arange(0, BLOCK)
        live = rows < n
        x = tl.load(x_ptr + rows[:, None] * K_IN + k[None, :], mask=live[:, None] & (k[None, :] < K_IN), other=0.0)
        g = tl.load(g_ptr + rows[:, None] * N_OUT + o[None, :], mask=live[:, None] & (o[None, :] < N_OUT), other=0.0)
        a1, s1 = _gelu_and_grad(tl.dot(x, tl.trans(w1), input_precision=PRECISION))  # [BLOCK, H], gelu' at h1
        a2, s2 = _gelu_and_grad(tl.dot(a1, tl.trans(w2), input_precision=PRECISION))
        dw3 += tl.dot(tl.trans(g), a2, input_precision=PRECISION)  # [OUT_PAD, H]
        d2 = tl.dot(g, w3, input_precision=PRECISION) * s2  # [BLOCK, H]
        dw2 += tl.dot(tl.trans(d2), a1, input_precision=PRECISION)
        d1 = tl.dot(d2, w2, input_precision=PRECISION) * s1
        dw1 += tl.dot(tl.trans(d1), x, input_precision=PRECISION)  # [H, K_PAD]
        dx = tl.dot(d1, w1, input_precision=PRECISION)  # [BLOCK, K_PAD]
        tl.store(dx_ptr + rows[:, None] * K_IN + k[None, :], dx, mask=live[:, None] & (k[None, :] < K_IN))
    tl.store(dw1_ptr + pid * part_stride + h[:, None] * K_IN + k[None, :], dw1, mask=k[None, :] < K_IN)
    tl.store(dw2_ptr + pid * part_stride + h[:, None] * H + h[None, :], dw2)
    tl.store(dw3_ptr + pid * part_stride + o[:, None] * H + h[None, :], dw3, mask=o[:, None] < N_OUT)



def check(net: torch.nn.Sequential) -> list[torch.nn.Module]:
    """The three bias-free linear layers (plain or LoRA-adapted: each has ``weight`` [out, in]) of a two-hidden-layer
    exact-GELU ``make_mlp`` network; anything else refused with one line."""
    layers, acts = list(net[0::2]), list(net[1::2])
    if len(layers) != 3 or len(acts) != 2 or any(not isinstance(a, torch.nn.GELU) or a.approximate != "none"
                                                 for a in acts):
        raise ValueError(f"{_WHERE}: fused MLP: three layers with two exact GELUs between them expected (the kernels "
                         f"compute x Phi(x)), got {net}")
    if any(getattr(m, "bias", None) is not None for m in layers):
        raise ValueError(f"{_WHERE}: fused MLP: bias-free layers (make_mlp's) expected")
    _check_weights([m.weight for m in layers], layers[0].weight.shape[1])
    return layers


def _check_weights(weights: list[torch.Tensor], k_in: int) -> None:
    """Three weights [H, K_IN], [H, H], [N_OUT, H] for inputs of width ``k_in``, H a power of two >= 16 (tl.dot); any
    other shape refused with one line (the kernels would read them with the wrong strides)."""
    if len(weights) != 3 or any(w.dim() != 2 for w in weights):
        raise ValueError(f"{_WHERE}: fused MLP: three 2-d weights expected, got {[tuple(w.shape) for w in weights]}")
    w1, w2, w3 = weights
    h = w1.shape[0]
    if w1.shape[1] != k_in or w2.shape != (h, h) or w3.shape[1] != h or h < 16 or h & (h - 1):
        raise ValueError(f"{_WHERE}: fused MLP: weights [H, K_IN], [H, H], [N_OUT, H] with H a power of two >= 16 "
                         f"expected for inputs of width {k_in}, got {tuple(w1.shape)}, {tuple(w2.shape)}, "
                         f"{tuple(w3.shape)}")


def _pad(v: int) -> int:
    """A dimension padded for tl.dot: a power of two, at least 16."""
    return max(16, triton.next_power_of_2(v))



#: whether the kernels were decorated under Triton's interpreter (TRITON_INTERPRET at this module's import, which
#: Triton reads then): how they run, on a CPU or on CUDA tensors alike (the interpreter copies those to the host)
INTERPRETED = isinstance(_fused_mlp_bwd, InterpretedFunction)


def _bwd_launch(n: int, k_in: int, h: int, n_out: int, block: int, precision: str, programs: int,
                interpreted: bool) -> tuple[int, tuple[int, int, int], dict]:
    """The backward's launch for n particles: ``(p, (n, p, per_program), constexprs)``, p programs of per_program tiles
    of ``block`` particles each (p <= ``programs``; fewer than per_program tile iterations of all programs fall past
    the last tile).

    Compiled (``interpreted`` False), the constexprs do not depend on n, and the counts are runtime arguments that
    Triton does not specialise (``do_not_specialize``): one compiled kernel per network shape. Until session 44,
    per_program was a constexpr. CPR evaluates the law on 1-10 frames of particles at a time, so every new chunk size
    and every scene's particle count compiled a new kernel. That took 2.2-2.5 s each (sm_90, measured here on the CPU;
    the duck's training on the H200 stalled 2.4-2.8 s at each of 8 new sizes, ``benchmarks/NOTES.md``, session 44).
    Under Triton's interpreter (``interpreted``), the count is also passed as the constexpr INTERPRETED_PER, which the
    interpreter can loop to."""
    tiles = triton.cdiv(n, block)
    per = max(1, triton.cdiv(tiles, max(1, programs)))  # tiles per program: the grid then wastes < per tile iterations
    p = max(1, triton.cdiv(tiles, per))
    consts = dict(K_IN=k_in, K_PAD=_pad(k_in), H=h, N_OUT=n_out, OUT_PAD=_pad(n_out), BLOCK=block, PRECISION=precision,
                  INTERPRETED_PER=per if interpreted else 0)
    return p, (n, p, per), consts


BWD_PROGRAMS_PER_SM = 2  # the backward's persistent programs per SM (on a CPU: 8 programs in all)
BWD_WARPS = 4  # the backward's warps per program; both from session 39's sweep (the module docstring)


class FrameSum:
    """A frame's weight-gradient partials of the fused backward (``MPMSolver.frame_mlp_grads``): each backward of the
    frame stores its programs' partials in a block of its own (:meth:`block_for`, the kernel's plain store), and the
    blocks are summed in one reduction when autograd reaches :class:`_FrameWeights` (:meth:`sum_of`).

    Why: a training frame evaluates each network once a step (20 steps a frame at the paper profile), and each
    backward summed its ~264 programs' partials (one reduction launch, ~6.8 us on the duck, H200) before autograd added
    the step's three weight gradients to the frame's (three adds, ~1.5 us each): 1604 reductions and ~4800 adds of a
    full-horizon iteration. With the sum: one reduction per network a frame, no adds. Session 56's first form added
    each backward's partials to one set of rows in place (a read before each write): session 57 measured that backward
    +10 % (27.1 -> 29.8 us a call), which ate most of the gain (NOTES); a block per call keeps the plain store. The
    same gradient to float rounding (another summation order: every call's programs at once).

    ``calls`` counts the frame's forward calls (each backward takes one block); ``parts`` [calls, programs, |W1| +
    |W2| + |W3|] (the weights' dtype and device) is made at a pass's first backward and freed by its sum. A kept graph
    differentiated again (``retain_graph``: the term shares' per-term gradients) starts its blocks from the first
    (:meth:`block_for` names the pass by its autograd graph task): session 56's review found a double count of the
    first form without that. Memory: ~5.8 MB a call a network with the H200's 264 programs, ~0.1 GB a network while a
    20-step frame is differentiated (the sweep's and the CUDA graphs' forwards make none; their frames' graphs live
    within one backward). A pass that reaches the fused backwards but not the weights (a gradient w.r.t. the state
    alone, on a kept eager graph) leaves its blocks allocated until the frame's graph is freed or a later pass sums
    them."""

    FRESH = -2  # the task mark of a frame whose blocks no pass has taken yet

    def __init__(self, weights: list[torch.Tensor], programs: int):
        self.sizes = [w.numel() for w in weights]
        self.programs = int(programs)
        self.dtype, self.device = weights[0].dtype, weights[0].device
        self.calls = 0  # forward calls of the frame so far
        self.parts: torch.Tensor | None = None
        self.rows = self.programs  # rows [rows, programs) of every block are zero (see block_for)
        self.taken, self.task = 0, self.FRESH  # blocks taken by the pass of graph task ``task``

    def called(self) -> None:
        """One more forward call of the frame (one more block for each pass)."""
        self.calls += 1

    def block_for(self, task: int, rows: int) -> torch.Tensor:
        """The next block [programs, width] of graph task ``task``'s pass (a new pass starts from the first), whose
        call stores its rows [0, rows) (the programs it runs); its other rows enter the frame's sum as zeros. They are
        zeroed once a pass for every block (rows from the pass's first call's ``rows`` on: one launch), and in a block
        whose call stores fewer rows than that. Until session 58 each call zeroed its own tail: one fill launch a call
        (1600 a duck iteration, +1.8 ms, H200)."""
        rows = min(int(rows), self.programs)
        if self.task != task:
            self.task, self.taken = task, 0
            if self.parts is not None:  # a kept block set (an earlier pass that never summed): its tails re-zeroed
                self._zero(self.parts[:, self.rows:])
        if self.parts is None or self.parts.shape[0] < self.calls:
            if self.taken > 0:  # a pass's stored blocks would be lost
                raise RuntimeError(f"{_WHERE}: a frame's forward calls grew to {self.calls} during a backward pass")
            self.parts = self._new_parts()
            self.rows = rows
            self._zero(self.parts[:, rows:])
        if self.taken >= self.parts.shape[0]:
            raise RuntimeError(f"{_WHERE}: a frame's pass took more backward calls than its {self.calls} forward calls")
        self.taken += 1
        block = self.parts[self.taken - 1]
        if rows < self.rows:
            self._zero(block[rows:self.rows])
        return block

    def _new_parts(self) -> torch.Tensor:
        """A pass's blocks [calls, programs, width], uninitialised."""
        return torch.empty(self.calls, self.programs, sum(self.sizes), dtype=self.dtype, device=self.device)

    @staticmethod
    def _zero(rows: torch.Tensor) -> None:
        """Zero ``rows`` (a view of the blocks) in place; nothing where it is empty."""
        if rows.numel():
            rows.zero_()

    def sum_of(self, task: int) -> list[torch.Tensor] | None:
        """The three weights' gradients (flat) summed over task ``task``'s blocks, which are then freed; None where that
        pass took none."""
        if self.task != task or self.taken == 0:
            return None
        total = self.parts[:self.taken].reshape(-1, self.parts.shape[2]).sum(0)  # one reduction a network a frame
        self.parts, self.taken, self.task = None, 0, self.FRESH
        return list(total.split(self.sizes))


class _FrameWeights(torch.autograd.Function):
    """(W1, W2, W3) -> the same values, whose gradient is the frame's :class:`FrameSum` (summed over its rows) plus
    whatever other uses of the outputs contribute. Autograd runs this backward after every use's (the outputs were
    formed before all of them), so the sum is complete when it is read."""

    @staticmethod
    def forward(ctx, sink: FrameSum, w1, w2, w3):
        ctx.sink, ctx.shapes = sink, [w.shape for w in (w1, w2, w3)]
        ctx.set_materialize_grads(False)
        return w1.view_as(w1), w2.view_as(w2), w3.view_as(w3)

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, *grads):
        sums = ctx.sink.sum_of(torch._C._current_graph_task_id())
        if sums is None:  # no fused call of this pass stored partials in the frame's blocks
            return (None, *grads)
        out = [s.view(shape) if g is None else g + s.view(shape) for g, s, shape in zip(grads, sums, ctx.shapes)]
        return (None, *out)


def frame_weights(weights: list[torch.Tensor], programs: int | None = None) -> tuple[FrameSum, list[torch.Tensor]]:
    """A frame's weights for :func:`mlp` ``sink``: ``(sink, [W1', W2', W3'])``, W' the values of ``weights`` (torch's
    layouts, as :func:`mlp` takes them) through :class:`_FrameWeights`. Every :func:`mlp` call given both adds its
    weight gradients to ``sink`` instead of returning them; autograd takes the frame's sum to ``weights`` once.
    ``programs``: as :func:`mlp`'s (default ``BWD_PROGRAMS_PER_SM`` per SM; 8 on a CPU); the calls must use the same."""
    w = [t.contiguous() for t in weights]
    sink = FrameSum(w, _programs(w[0], programs))
    out = _FrameWeights.apply(sink, *w)
    return sink, list(out)


def _programs(z: torch.Tensor, programs: int | None) -> int:
    """The backward's persistent programs on ``z``'s device: ``programs``, or ``BWD_PROGRAMS_PER_SM`` per SM (8 on a
    CPU)."""
    if programs is not None:
        return int(programs)
    return BWD_PROGRAMS_PER_SM * torch.cuda.get_device_properties(z.device).multi_processor_count if z.is_cuda else 8


def _forward(x, w1, w2, w3, block: int, precision: str, out: torch.Tensor | None = None) -> torch.Tensor:
    """The forward kernel's launch: out [N, N_OUT] (a fresh tensor, or ``out``'s storage) for contiguous x and
    weights, no autograd."""
    if out is None:
        out = torch.empty(x.shape[0], w3.shape[0], device=x.device, dtype=x.dtype)
    _fused_mlp_fwd[(triton.cdiv(x.shape[0], block),)](x, w1, w2, w3, out, x.shape[0], K_IN=x.shape[1],
                                                     K_PAD=_pad(x.shape[1]), H=w2.shape[0], N_OUT=w3.shape[0],
                                                     OUT_PAD=_pad(w3.shape[0]), BLOCK=block, PRECISION=precision)
    return out


class FusedMLP(torch.autograd.Function):
    """out = W3 gelu(W2 gelu(W1 x)) for x [N, K_IN] and weights [H, K_IN], [H, H], [N_OUT, H] (torch's layout): the
    forward one launch with nothing stored but the inputs; the backward one persistent launch of ``programs`` programs
    of ``warps`` warps that recomputes the forward on chip and gives dx and the three weight gradients (partials per
    program summed by torch). float32 (``precision`` ieee or tf32) or float64 (ieee: the CPU interpreter's
    gradcheck)."""

    @staticmethod
    def forward(ctx, x, w1, w2, w3, block: int, precision: str, programs: int, warps: int,
                sink: FrameSum | None = None, given: torch.Tensor | None = None):
        ctx.save_for_backward(x, w1, w2, w3)
        ctx.cfg = (block, precision, programs, warps)
        ctx.sink = sink
        if sink is not None:
            sink.called()
        if given is not None:  # the forward's own output, kept by it (a frame's MLP stash): no launch
            return given.view_as(given)
        return _forward(x, w1, w2, w3, block, precision)

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, g):
        x, w1, w2, w3 = ctx.saved_tensors
        block, precision, programs, warps = ctx.cfg
        p, counts, consts = _bwd_launch(x.shape[0], x.shape[1], w2.shape[0], w3.shape[0], block, precision, programs,
                                        interpreted=INTERPRETED)
        dx = torch.empty_like(x)
        sizes = [w.numel() for w in (w1, w2, w3)]
        sink = ctx.sink
        if sink is not None:  # this call's block of the frame's partials, no sum here
            parts = sink.block_for(torch._C._current_graph_task_id(), p)  # rows from p on: zeros
        else:
            parts = torch.empty(p, sum(sizes), device=x.device, dtype=x.dtype)  # a program's three partials in a row
        _fused_mlp_bwd[(p,)](x, g.contiguous(), w1, w2, w3, dx, *parts.split(sizes, dim=1), parts.shape[1], *counts,
                             **consts, num_warps=warps)
        if sink is not None:
            return (dx, None, None, None, None, None, None, None, None, None)
        sums = parts.sum(0).split(sizes)  # one reduction launch, not three (session 45: 3 x 6.4 us per backward)
        return (dx, *(d.view_as(w) for d, w in zip(sums, (w1, w2, w3))), None, None, None, None, None, None)


def runs_here(z: torch.Tensor) -> bool:
    """Whether the fused kernels can run on ``z``'s device: CUDA, or a CPU under Triton's interpreter (decorated so at
    import: :data:`INTERPRETED`)."""
    return z.is_cuda or INTERPRETED


def mlp(z: torch.Tensor, weights: list[torch.Tensor], precision: str = "tf32", block: int = BLOCK,
        programs: int | None = None, warps: int = BWD_WARPS, sink: FrameSum | None = None,
        out: torch.Tensor | None = None, given: torch.Tensor | None = None) -> torch.Tensor:
    """X [N, N_OUT] = W3 gelu(W2 gelu(W1 z)) for z [N, K_IN] and ``weights`` [W1 [H, K_IN], W2 [H, H], W3 [N_OUT, H]]
    (torch's layouts; the shape :func:`check` accepts), differentiable in z and the weights. ``precision``: ``tf32``
    (TF32 products; float32 only) or ``ieee`` (FP32 or float64 products). ``programs``: the backward's persistent
    programs (default ``BWD_PROGRAMS_PER_SM`` per SM; 8 on a CPU); ``warps``: the backward's warps per program (a
    power of two, 1-16).
    ``block``, ``programs`` and ``warps`` change the launch, not the function: the products' tiles and the order in
    which the weight gradients' partials are summed change (float rounding only).
    ``sink``: a frame's :class:`FrameSum`, with ``weights`` the outputs of the :func:`frame_weights` that made it: the
    weight gradients go to the sink (summed once a frame), not back through this call; its programs are the call's.
    ``out`` / ``given`` (a frame's MLP stash, ``gca.laws.neural.frame_mlp_stash``): ``out`` [N, N_OUT] takes the
    forward's output (where no gradient is recorded: a frame's forward pass); ``given`` [N, N_OUT] *is* the output, no
    launch (a frame's recompute, whose forward pass left it in ``out``: the same kernel on the same inputs gives the
    same bits), returned as a view; the backward is the plain call's, which recomputes the forward on chip from z."""
    if not runs_here(z):
        raise ValueError(f"{_WHERE}: the fused MLP runs on CUDA, or on a CPU only in Triton's interpreter "
                         f"(TRITON_INTERPRET=1 before the import); got {z.device}")
    if block < 16 or block & (block - 1):
        raise ValueError(f"{_WHERE}: a block that is a power of two >= 16 (tl.dot) expected, got {block}")
    if warps < 1 or warps > 16 or warps & (warps - 1):
        raise ValueError(f"{_WHERE}: warps per program: a power of two from 1 to 16 expected, got {warps}")
    if z.dim() != 2:
        raise ValueError(f"{_WHERE}: z [N, K_IN] expected, got {tuple(z.shape)}")
    _check_weights(weights, z.shape[1])
    w1, w2, w3 = weights
    if z.dtype not in (torch.float32, torch.float64) or any(w.dtype != z.dtype for w in weights):
        raise ValueError(f"{_WHERE}: float32 or float64 input and weights alike expected, got {z.dtype}, "
                         f"{[w.dtype for w in weights]}")
    if precision == "tf32" and z.dtype != torch.float32:
        raise ValueError(f"{_WHERE}: TF32 products take float32, got {z.dtype} (use precision='ieee')")
    if programs is None and sink is not None:
        programs = sink.programs  # a frame's calls take its programs
    programs = _programs(z, programs)
    if sink is not None:
        if programs != sink.programs or sink.dtype != z.dtype or sink.device != z.device \
                or sink.sizes != [w.numel() for w in weights]:
            raise ValueError(f"{_WHERE}: a frame sum of {sink.programs} programs, {sink.dtype} on "
                             f"{sink.device}, weights of {sink.sizes} elements cannot take a call of {programs} "
                             f"programs, {z.dtype} on {z.device}, weights of {[w.numel() for w in weights]}")
    for name, t in (("out", out), ("given", given)):
        if t is not None and (tuple(t.shape) != (z.shape[0], w3.shape[0]) or t.dtype != z.dtype
                              or t.device != z.device or not t.is_contiguous()):
            raise ValueError(f"{_WHERE}: {name} must be a contiguous [{z.shape[0]}, {w3.shape[0]}] {z.dtype} tensor on "
                             f"{z.device}, got {tuple(t.shape)} {t.dtype} on {t.device}")
    if out is not None:
        if given is not None:
            raise ValueError(f"{_WHERE}: out and given together (a call either keeps its output or takes it)")
        if torch.is_grad_enabled() and (z.requires_grad or any(w.requires_grad for w in weights)):
            raise ValueError(f"{_WHERE}: out takes a forward's output where no gradient is recorded (no_grad)")
        return _forward(z.contiguous(), w1.contiguous(), w2.contiguous(), w3.contiguous(), block, precision, out)
    return FusedMLP.apply(z.contiguous(), w1.contiguous(), w2.contiguous(), w3.contiguous(), block, precision,
                          programs, warps, sink, given)
