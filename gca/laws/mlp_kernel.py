"""The neural laws' MLP in warp kernels: one tile kernel each way (``mlp``), or a one-thread-per-particle forward with
torch's backward (``simt_mlp``). Options of the laws (``NeuralElasticity.mlp_kernel``, ``train.mlp_kernel``); torch's
``nn.Sequential`` is the default.

:class:`gca.laws.neural.NeuralElasticity` (and the plasticity) map the 13 features z of F to 9 numbers X through a
bias-free MLP with two hidden layers (NCLaw's ``InvariantFullMeta``: 13 -> 64 -> 64 -> 9, GELU):

    a1 = z W1^T,  h1 = act(a1),  a2 = h1 W2^T,  h2 = act(a2),  X = h2 W3^T            (forward)

    d3 = v_X,  v_W3 = d3^T h2,  d2 = (d3 W3) * act'(a2),  v_W2 = d2^T h1,
    d1 = (d2 W2) * act'(a1),  v_W1 = d1^T z,  v_z = d1 W1                           (backward)

In torch that is 3 products and 2 activation kernels forward and about 10 kernels backward per network and MPM step,
each streaming [N, 64] activations through memory (the largest share of a swept GCA iteration's kernel time on an
H100, ``benchmarks/NOTES.md`` session 33).

``mlp`` (tile kernels): one thread block takes ``tile`` particles through all layers with the activations in shared
memory; the backward recomputes the forward (nothing [N, 64] is stored) and runs persistent blocks, each summing its
tiles' weight gradients on chip and storing one partial, summed in a fixed order afterwards (deterministic). Measured
(H100, 30k particles, graph-replayed; ``benchmarks/bench_mlp.py``, NOTES session 34): **slower than torch**: forward
76 us against 37, forward + backward 215 us against 124; warp's scalar tile product reads both operands from shared
memory for every multiply-add. (The first version, one tile atomic per block and matrix, took 526 us; cuBLASDx
products compiled one module for 281 s.)

``simt_mlp``: one thread per particle, layer 2's pre-activations in registers, every weight a load the whole warp
shares; the backward is torch's from the stored pre-activations. Not measured yet (NOTES session 34).

The weights are the layers' effective (LoRA-merged) weights, so gradients reach the adapters through torch's autograd
of the merge, as on the torch path. Same values as ``nn.Sequential`` to rounding (float64 gradient checks in the
tests). Only the two-hidden-layer shape runs here (:func:`shape_of`).
"""

# no `from __future__ import annotations`: warp resolves the kernels' annotations (closure types) eagerly
import dataclasses
import functools
import types

import torch
import warp as wp
from torch.autograd.function import once_differentiable

from gca.laws.svd_kernel import WARP_FLOATS
from gca.warp_stream import on_torch_stream

_WHERE = "gca/laws/mlp_kernel.py"
ACTIVATIONS = ("gelu", "tanh", "silu", "elu", "relu")  # as gca.laws.neural.ACTIVATIONS (nn.GELU exact, nn.ELU alpha 1)


@dataclasses.dataclass(frozen=True)
class MLPShape:
    """A bias-free MLP n_in -> w1 -> w2 -> n_out with ``activation`` after both hidden layers."""

    n_in: int
    w1: int
    w2: int
    n_out: int
    activation: str


def shape_of(mlp: torch.nn.Sequential) -> MLPShape | None:
    """The fusable shape of an ``nn.Sequential`` [linear, act, linear, act, linear] without biases, else None.

    Linear layers are ``nn.Linear`` or anything with ``in_features``/``out_features`` and a ``bias`` of None (LoRA).
    """
    layers = list(mlp)
    if len(layers) != 5:
        return None
    lin, acts = layers[0::2], layers[1::2]
    if any(getattr(l, "bias", 0) is not None or not hasattr(l, "in_features") for l in lin):
        return None
    names = {type(a).__name__.lower() for a in acts}
    name = names.pop() if len(names) == 1 else None
    if name not in ACTIVATIONS:
        return None
    if any(isinstance(a, torch.nn.GELU) and a.approximate != "none" for a in acts):  # the kernels' GELU is exact
        return None
    if any(isinstance(a, torch.nn.ELU) and a.alpha != 1.0 for a in acts):  # and their ELU's alpha 1
        return None
    if not (lin[0].out_features == lin[1].in_features and lin[1].out_features == lin[2].in_features):
        return None
    return MLPShape(lin[0].in_features, lin[0].out_features, lin[1].out_features, lin[2].out_features, name)


# particles per thread block: the backward's tiles take 79 KiB of shared memory in float32 (114 at 32 particles, which
# ran at the same speed on the H100, session 34); warp's CPU tile arena is 256 KiB, float64 twice as wide
TILE = 16


@functools.cache
def make_mlp_kernels(dtype: torch.dtype, shape: MLPShape, tile: int, mathdx: bool = False) -> types.SimpleNamespace:
    """The forward and backward tile kernels of ``shape`` for float32 or float64, ``tile`` particles per block.

    Args:
        mathdx: let warp use cuBLASDx for the tile products on CUDA (a benchmark variant: it compiled one module for
            281 s on the H100 machine, session 34); False (default): warp's scalar tile product (~5 s).
    """
    wp.init()
    T = WARP_FLOATS[dtype]
    n_in, w1, w2, n_out, TP = shape.n_in, shape.w1, shape.w2, shape.n_out, int(tile)
    module = f"gca_laws_mlp_{T.__name__}_{n_in}x{w1}x{w2}x{n_out}_{shape.activation}_t{TP}{'' if mathdx else '_scalar'}"
    # enable_backward off for the module too: with it on, warp sized every tile twice (a gradient buffer beside it): the
    # first backward asked 272 KiB at 32 particles per block on the H100 where its tiles took 136 (session 34)
    wp.set_module_options({"enable_mathdx_gemm": bool(mathdx), "enable_backward": False}, module=module)
    act, act_vjp = _activation(shape.activation, T, module)

    @wp.kernel(module=module, enable_backward=False)
    def forward(z: wp.array2d(dtype=T), W1: wp.array2d(dtype=T), W2: wp.array2d(dtype=T), W3: wp.array2d(dtype=T),
                X: wp.array2d(dtype=T)):
        b = wp.tid()
        zt = wp.tile_load(z, shape=(TP, n_in), offset=(b * TP, 0))  # rows past N read as 0 (and map to 0)
        h1 = wp.tile_map(wp.static(act), wp.tile_matmul(zt, wp.tile_transpose(wp.tile_load(W1, shape=(w1, n_in)))))
        h2 = wp.tile_map(wp.static(act), wp.tile_matmul(h1, wp.tile_transpose(wp.tile_load(W2, shape=(w2, w1)))))
        x = wp.tile_matmul(h2, wp.tile_transpose(wp.tile_load(W3, shape=(n_out, w2))))
        wp.tile_store(X, x, offset=(b * TP, 0))  # rows past N are not written

    @wp.kernel(module=module, enable_backward=False)
    def backward(z: wp.array2d(dtype=T), W1: wp.array2d(dtype=T), W2: wp.array2d(dtype=T), W3: wp.array2d(dtype=T),
                 v_X: wp.array2d(dtype=T), n_tiles: int, n_blocks: int, v_z: wp.array2d(dtype=T),
                 P1: wp.array2d(dtype=T), P2: wp.array2d(dtype=T), P3: wp.array2d(dtype=T)):
        blk = wp.tid()  # a persistent block: tiles blk, blk + n_blocks, ...; its weight gradients summed on chip
        t1 = wp.tile_load(W1, shape=(w1, n_in))
        t2 = wp.tile_load(W2, shape=(w2, w1))
        t3 = wp.tile_load(W3, shape=(n_out, w2))
        g1 = wp.tile_zeros(shape=(w1, n_in), dtype=T)
        g2 = wp.tile_zeros(shape=(w2, w1), dtype=T)
        g3 = wp.tile_zeros(shape=(n_out, w2), dtype=T)
        for b in range(blk, n_tiles, n_blocks):
            zt = wp.tile_load(z, shape=(TP, n_in), offset=(b * TP, 0))
            a1 = wp.tile_matmul(zt, wp.tile_transpose(t1))
            h1 = wp.tile_map(wp.static(act), a1)
            a2 = wp.tile_matmul(h1, wp.tile_transpose(t2))
            d3 = wp.tile_load(v_X, shape=(TP, n_out), offset=(b * TP, 0))  # rows past N read as 0: they add nothing
            wp.tile_matmul(wp.tile_transpose(d3), wp.tile_map(wp.static(act), a2), g3)
            d2 = wp.tile_map(wp.static(act_vjp), wp.tile_matmul(d3, t3), a2)
            wp.tile_matmul(wp.tile_transpose(d2), h1, g2)
            d1 = wp.tile_map(wp.static(act_vjp), wp.tile_matmul(d2, t2), a1)
            wp.tile_matmul(wp.tile_transpose(d1), zt, g1)
            wp.tile_store(v_z, wp.tile_matmul(d1, t1), offset=(b * TP, 0))
        wp.tile_store(P1, g1, offset=(blk * w1, 0))  # one partial per block, summed in a fixed order afterwards
        wp.tile_store(P2, g2, offset=(blk * w2, 0))
        wp.tile_store(P3, g3, offset=(blk * n_out, 0))

    return types.SimpleNamespace(forward=forward, backward=backward, tile=TP, T=T)


def _activation(name: str, T, module: str):
    """(act, (g, x) -> g act'(x)) as warp functions of scalar type T in the kernels' ``module``, matching torch's
    modules. The kernels pass them to ``tile_map`` through ``wp.static``: warp 1.19 hashes the functions a kernel
    calls, not those it passes as arguments, so without it an edited activation reused the cached binary (seen)."""
    half, one = T(0.5), T(1.0)
    if name == "gelu":  # exact (erf) GELU, nn.GELU(approximate="none"); 1/sqrt(2), 1/sqrt(2 pi) as literals (warp
        # reads a literal at the kernel's precision; a Python expression of math calls came out in float32)
        @wp.func(module=module)
        def act(x: T):
            return half * x * (one + wp.erf(x * T(0.7071067811865476)))

        @wp.func(module=module)
        def act_vjp(g: T, x: T):
            cdf = half * (one + wp.erf(x * T(0.7071067811865476)))
            return g * (cdf + x * wp.exp(-half * x * x) * T(0.3989422804014327))
    elif name == "tanh":
        @wp.func(module=module)
        def act(x: T):
            return wp.tanh(x)

        @wp.func(module=module)
        def act_vjp(g: T, x: T):
            t = wp.tanh(x)
            return g * (one - t * t)
    elif name == "silu":
        @wp.func(module=module)
        def act(x: T):
            return x / (one + wp.exp(-x))

        @wp.func(module=module)
        def act_vjp(g: T, x: T):
            s = one / (one + wp.exp(-x))
            return g * (s + x * s * (one - s))
    elif name == "elu":  # alpha = 1
        @wp.func(module=module)
        def act(x: T):
            return wp.where(x > T(0.0), x, wp.exp(x) - one)

        @wp.func(module=module)
        def act_vjp(g: T, x: T):
            return wp.where(x > T(0.0), g, g * wp.exp(x))
    elif name == "relu":  # act'(0) = 0, as torch
        @wp.func(module=module)
        def act(x: T):
            return wp.max(x, T(0.0))

        @wp.func(module=module)
        def act_vjp(g: T, x: T):
            return wp.where(x > T(0.0), g, T(0.0))
    else:
        raise ValueError(f"{_WHERE}: activation {name!r} is not one of {ACTIVATIONS}")
    return act, act_vjp


def _a(t: torch.Tensor) -> wp.array:
    return wp.from_torch(t)


BLOCK_DIM = {"cuda": 128, "cpu": 32}  # threads per block (CPU: lanes run as fibers, fewer is faster)
BLOCKS_PER_SM = 4  # the backward's persistent blocks per multiprocessor (CPU: 4 blocks)


def _launch(kernel, blocks: int, device: torch.device, args: list) -> None:
    with on_torch_stream(device):
        wp.launch_tiled(kernel, dim=[blocks], inputs=args, device=wp.device_from_torch(device),
                        block_dim=BLOCK_DIM[device.type])


def backward_blocks(n_tiles: int, device: torch.device) -> int:
    """The backward's persistent block count: ``BLOCKS_PER_SM`` per multiprocessor (4 on the CPU), at most one per
    tile. Fixed per device and size, so the weight gradients sum in one order run after run."""
    sms = wp.get_device(wp.device_from_torch(device)).sm_count if device.type == "cuda" else 1
    return max(1, min(n_tiles, BLOCKS_PER_SM * sms))


class _TileMLP(torch.autograd.Function):
    """z [N, n_in], W1 [w1, n_in], W2 [w2, w1], W3 [n_out, w2] -> X [N, n_out]."""

    @staticmethod
    def forward(ctx, z, W1, W2, W3, shape, tile, mathdx):
        z, Ws = z.detach().contiguous(), [W.detach().contiguous() for W in (W1, W2, W3)]
        k = make_mlp_kernels(z.dtype, shape, tile, mathdx)
        X = torch.empty(z.shape[0], shape.n_out, dtype=z.dtype, device=z.device)
        if z.shape[0]:
            _launch(k.forward, -(-z.shape[0] // k.tile), z.device, [_a(z), *map(_a, Ws), _a(X)])
        ctx.save_for_backward(z, *Ws)
        ctx.k = k
        return X

    @staticmethod
    @once_differentiable
    def backward(ctx, v_X):
        z, W1, W2, W3 = ctx.saved_tensors
        k = ctx.k
        v_z = torch.empty_like(z)
        n_tiles = -(-z.shape[0] // k.tile)
        blocks = backward_blocks(n_tiles, z.device)
        partials = [torch.empty(blocks * W.shape[0], W.shape[1], dtype=W.dtype, device=W.device) for W in (W1, W2, W3)]
        if z.shape[0]:
            _launch(k.backward, blocks, z.device, [_a(z), _a(W1), _a(W2), _a(W3), _a(v_X.contiguous()), n_tiles, blocks,
                                                   _a(v_z), *map(_a, partials)])
        v_W = [P.view(blocks, *W.shape).sum(0) if z.shape[0] else torch.zeros_like(W)
               for P, W in zip(partials, (W1, W2, W3))]
        need = ctx.needs_input_grad
        return (v_z if need[0] else None, *(g if n else None for g, n in zip(v_W, need[1:4])), None, None, None)


def _check(z: torch.Tensor, weights: list[torch.Tensor], shape: MLPShape) -> None:
    if z.dtype not in WARP_FLOATS or any(W.device != z.device for W in weights):
        raise ValueError(f"{_WHERE}: z and the weights must be float32 or float64 on one device, got z {z.dtype} on "
                         f"{z.device}, weights on {sorted({str(W.device) for W in weights})}")
    if z.dim() != 2 or z.shape[1] != shape.n_in:
        raise ValueError(f"{_WHERE}: z must be [N, {shape.n_in}], got {tuple(z.shape)}")
    expect = [(shape.w1, shape.n_in), (shape.w2, shape.w1), (shape.n_out, shape.w2)]
    if [tuple(W.shape) for W in weights] != expect or any(W.dtype != z.dtype for W in weights):
        raise ValueError(f"{_WHERE}: weights must be {expect} in {z.dtype}, got "
                         f"{[(tuple(W.shape), W.dtype) for W in weights]}")


def mlp(z: torch.Tensor, weights: list[torch.Tensor], shape: MLPShape, tile: int | None = None,
        mathdx: bool = False) -> torch.Tensor:
    """X [N, n_out] = the MLP of ``shape`` with ``weights`` [W1, W2, W3] ([out, in] each) on z [N, n_in], in one warp
    tile kernel (differentiable in z and the weights; ``tile`` particles per block, default ``TILE``)."""
    _check(z, weights, shape)
    tile = TILE if tile is None else int(tile)
    return _TileMLP.apply(z, *weights, shape, tile, bool(mathdx))


# ----------------------------------------------------------------------------- one thread per particle (``simt``)


@functools.cache
def make_simt_kernel(dtype: torch.dtype, shape: MLPShape):
    """The MLP's forward with one thread per particle: a runtime loop over layer 1's units, each added at once into
    layer 2's w2 pre-activations (registers: that inner loop is unrolled), then layer 2's activations into the n_out
    outputs; with ``save`` it also stores the pre-activations a1 [N, w1] and a2 [N, w2] for the backward
    (:class:`_SimtMLP`). The weights are read at addresses every thread of a warp shares (one broadcast load each).
    Only the w2- and n_out-wide loops are unrolled: unrolling layer 1 too made 61k lines of C++ (CPU build 17 s; on
    the H100 NVRTC had not finished after 2 min, session 34); this order is ~10x less code."""
    wp.init()
    T = WARP_FLOATS[dtype]
    n_in, w1, w2, n_out = shape.n_in, shape.w1, shape.w2, shape.n_out
    module = f"gca_laws_mlp_simt_{T.__name__}_{n_in}x{w1}x{w2}x{n_out}_{shape.activation}"
    wp.set_module_options({"enable_backward": False, "max_unroll": max(n_in, w2, n_out)}, module=module)
    act, _ = _activation(shape.activation, T, module)
    vec_in, vec_h2, vec_out = (wp.types.vector(length=k, dtype=T) for k in (n_in, w2, n_out))

    @wp.kernel(module=module, enable_backward=False)
    def forward(z: wp.array2d(dtype=T), W1: wp.array2d(dtype=T), W2: wp.array2d(dtype=T), W3: wp.array2d(dtype=T),
                n1: int, save: int, X: wp.array2d(dtype=T), A1: wp.array2d(dtype=T), A2: wp.array2d(dtype=T)):
        p = wp.tid()
        zp = vec_in()
        for i in range(wp.static(n_in)):
            zp[i] = z[p, i]
        a2 = vec_h2()
        for j in range(n1):  # a runtime loop (n1 = w1 passed at launch, so warp cannot unroll it): one unit of layer 1
            # at a time, added into layer 2's pre-activations
            a = T(0.0)
            for i in range(wp.static(n_in)):
                a += W1[j, i] * zp[i]
            if save != 0:
                A1[p, j] = a
            h = act(a)
            for k in range(wp.static(w2)):
                a2[k] += W2[k, j] * h
        x = vec_out()
        for k in range(wp.static(w2)):
            if save != 0:
                A2[p, k] = a2[k]
            h = act(a2[k])
            for m in range(wp.static(n_out)):
                x[m] += W3[m, k] * h
        for m in range(wp.static(n_out)):
            X[p, m] = x[m]

    return forward


class _SimtMLP(torch.autograd.Function):
    """z [N, n_in], W1, W2, W3 -> X [N, n_out]: the forward in one warp kernel (:func:`make_simt_kernel`); the backward
    in torch from the stored pre-activations (the activation's own backward, products by cuBLAS), so it is torch's
    backward without a recomputed forward."""

    @staticmethod
    def forward(ctx, z, W1, W2, W3, shape, activation, save):
        z, Ws = z.detach().contiguous(), [W.detach().contiguous() for W in (W1, W2, W3)]
        n = z.shape[0]
        X = torch.empty(n, shape.n_out, dtype=z.dtype, device=z.device)
        A1 = torch.empty(n if save else 0, shape.w1, dtype=z.dtype, device=z.device)
        A2 = torch.empty(n if save else 0, shape.w2, dtype=z.dtype, device=z.device)
        if n:
            with on_torch_stream(z.device):
                wp.launch(make_simt_kernel(z.dtype, shape), dim=n, device=wp.device_from_torch(z.device),
                          inputs=[_a(z), *map(_a, Ws), shape.w1, int(save), _a(X), _a(A1), _a(A2)])
        ctx.save_for_backward(z, *Ws, A1, A2)
        ctx.activation = activation
        return X

    @staticmethod
    @once_differentiable
    def backward(ctx, v_X):
        z, W1, W2, W3, A1, A2 = ctx.saved_tensors
        with torch.enable_grad():
            a1, a2 = A1.detach().requires_grad_(True), A2.detach().requires_grad_(True)
            h1, h2 = ctx.activation(a1), ctx.activation(a2)
        (d2,) = torch.autograd.grad(h2, a2, v_X @ W3)  # (v_X W3) * act'(a2)
        (d1,) = torch.autograd.grad(h1, a1, d2 @ W2)
        need = ctx.needs_input_grad
        return (d1 @ W1 if need[0] else None, d1.T @ z if need[1] else None, d2.T @ h1.detach() if need[2] else None,
                v_X.T @ h2.detach() if need[3] else None, None, None, None)


def wants_gradient(*tensors: torch.Tensor) -> bool:
    """Whether a call on ``tensors`` will be differentiated: grad mode on and one of them requires grad. (Inside a
    ``torch.autograd.Function``'s forward ``ctx.needs_input_grad`` says True under ``torch.no_grad()`` too, and grad
    mode is always off there, so the caller decides.)"""
    return torch.is_grad_enabled() and any(t.requires_grad for t in tensors)


def simt_mlp(z: torch.Tensor, weights: list[torch.Tensor], shape: MLPShape, activation: torch.nn.Module) -> torch.Tensor:
    """X [N, n_out] = the MLP of ``shape`` on z [N, n_in] with ``weights`` [W1, W2, W3], its forward one thread per
    particle (:func:`make_simt_kernel`), its backward torch's (``activation``: the network's activation module, so
    its derivative is torch's own). Differentiable in z and the weights."""
    _check(z, weights, shape)
    return _SimtMLP.apply(z, *weights, shape, activation, wants_gradient(z, *weights))
