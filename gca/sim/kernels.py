"""Warp kernels of one MLS-MPM step (APIC transfer, quadratic B-splines) on the unit cube.

Scheme (Hu et al. 2018, "A moving least squares material point method", eqs. 16-19 in the
Kirchhoff-stress form used by NCLaw; see ``docs/architecture.md``), per step of size ``dt``:

    P2G   affine_p = -dt * vol_p * 4 * inv_dx^2 * tau_p + m_p * C_p
          m_i  += w_ip * m_p
          mv_i += w_ip * (m_p * v_p + affine_p @ (x_i - x_p))
    grid  v_i = mv_i / (m_i + eps) + dt * g   (m_i > m_min; else 0), then the wall condition
    G2P   v_p' = sum_i w_ip v_i
          C_p' = 4 * inv_dx^2 * sum_i w_ip v_i (x_i - x_p)^T
          F_trial = (I + dt C_p') F_p
          x_p' = clamp(x_p + dt v_p', lo, hi)

Grid layout. The domain [0, 1]^3 has ``n_grid`` cells of size ``dx = 1 / n_grid``; node ``I`` (an
integer in [-PAD, n_grid + PAD]) sits at ``I * dx`` and is stored at index ``I + PAD`` of arrays of
shape ``[n_grid + 1 + 2 PAD]^3``. The stencil base is ``floor(x / dx - 0.5)`` (floor, not
truncation), so the three nodes ``base .. base + 2`` of a particle at ``x`` in [0, 1] lie in
[-1, n_grid + 1]: with ``PAD = 1`` no stencil reads or writes outside the arrays for any position
in the closed unit cube. G2P clamps positions to [lo, hi] with ``0 <= lo < hi <= 1`` (the solver
uses ``lo = clip * dx``, ``hi = 1 - clip * dx``) and the base index is additionally clamped as an
integer, so even a non-finite position cannot index out of bounds (it produces non-finite state,
which the rollout driver detects instead).

Interleaved grids (``MPMSolver.vec4_p2g``, ``vec4_step``, ``vec4_g2p_adj``). The forward-only scatter ``scatter4``
(``p2g4``, the fused analytic step's ``*4`` kernels) keeps a node's momentum and mass as one vec4 (mv in components
0-2, m in 3), so a node's share is one 16-byte vector atomic in float32 on sm_90+ (``atomic_add4``; component-wise
elsewhere); ``grid_update_unpack4`` moves it into a step's (mv, m). ``g2p4``'s adjoint adds each node's velocity
cotangent into a vec4 accumulator the same way (``node_read4``), which ``grid_unpack_adj4`` moves into the velocity
grid's gradient. Same layout and indices otherwise.

Runs. Several independent simulations (runs) can share one launch: ``run[p]`` is particle ``p``'s run, and
the runs' grids are stacked along the first axis (run ``r``'s node ``(I, J, K)`` at index ``I + PAD + r G``,
``G = n_grid + 1 + 2 PAD``), so no particle ever reaches another run's nodes. One run: ``run`` all zeros and
one grid, the plain step.

Walls. Nodes with ``I < bound`` or ``I > n_grid - bound`` on an axis are in that axis' wall
region; ``bound`` is in cells. The floor is the bottom wall y = 0. ``sticky`` zeroes the whole
node velocity in a wall region (whatever its direction); ``slip`` removes the normal component
v_n = v . n_out when it points out of the domain (v_n > 0); ``friction`` does the same and then
shrinks the tangential part by Coulomb friction, |v_t| -> max(0, |v_t| - mu_b v_n).

Float type. :func:`make_kernels` builds the kernels for ``wp.float32`` or ``wp.float64`` (one
module each), so gradients can be checked against finite differences in float64. The same
source runs on "cpu" and "cuda" devices. (No ``from __future__ import annotations`` here: warp
resolves the kernels' annotations, which name the closure's float types, as real objects.)
"""

import types

import warp as wp

PAD = 1  # padding nodes on each side of the grid [nodes]

STICKY = 0  # wall nodes get zero velocity
SLIP = 1  # wall nodes lose the velocity component pointing out of the domain
FRICTION = 2  # SLIP, then Coulomb friction with coefficient mu_b on the tangential part
BOUNDARY_KINDS = {"sticky": STICKY, "slip": SLIP, "friction": FRICTION}


BLOCK = 128  # particles per thread block of the block-summed P2G on a GPU (scatter_block) [count]
WINDOW = wp.constant(1024)  # nodes of a block's shared-memory window (scatter_block; 16 KiB in float32) [count]


# Warp-aggregated atomics (``p2g_agg``): the lanes of a warp whose particles share a stencil base ("peers", found with
# ``__match_any_sync``) sum their shares by shuffles and one of them (the lowest lane, the "leader") adds the sum to
# the grid, so a node takes one atomic add per distinct base in a warp instead of one per particle (Westphal, "Voting
# and shuffling to optimize atomic operations", NVIDIA Parallel Forall, 2015). Every intrinsic is masked with the
# lane's own peer set, so a warp split by divergence aggregates each part apart and stays correct. Off CUDA each
# thread is its own (only) peer: the kernel is ``p2g``'s, the same sums in the same order.
_PEERS = """
#if defined(__CUDA_ARCH__)
return (int)__match_any_sync(__activemask(), key);
#else
return 1;
#endif
"""
_IS_LEADER = "(((unsigned)peers & ((1u << (threadIdx.x & 31u)) - 1u)) == 0u)"  # no lower lane among the peers
_LEADER = f"""
#if defined(__CUDA_ARCH__)
return {_IS_LEADER};
#else
return true;
#endif
"""
def _peer_tree(value: str, n: int) -> str:
    """CUDA lines leaving in ``s`` (a copy of the ``n``-component vector ``value``), at the lowest lane of the int mask
    ``peers``, the sum of ``value`` over those lanes (other lanes: partial sums, unused). A tree over the peers in
    rank order: each round, a lane of even rank (among the peers left) adds the running sum of the next peer left
    above it, and the lanes of odd rank leave. Every intrinsic is masked with the lane's peers, all of which run it
    (``tests/test_sim_agg_p2g.py`` models it lane by lane)."""
    reads = "\n".join(f"    const auto t{c} = __shfl_sync(p, s.c[{c}], src);" for c in range(n))
    adds = " ".join(f"s.c[{c}] += t{c};" for c in range(n))
    return f"""const unsigned p = (unsigned)peers;
const unsigned lane = threadIdx.x & 31u;
unsigned rest = p & ~((2u << lane) - 1u);
unsigned rank = __popc(p & ((1u << lane) - 1u));
auto s = {value};
while (__any_sync(p, rest != 0u)) {{
    const int next = __ffs(rest);
    const int src = next ? next - 1 : (int)lane;
{reads}
    if (next) {{ {adds} }}
    rest &= ~__ballot_sync(p, rank & 1u);
    rank >>= 1;
}}
"""


_PEER_SUM4 = f"""
#if defined(__CUDA_ARCH__)
{_peer_tree("a", 4)}return s;
#else
return a;
#endif
"""
# a node's value read in G2P, whose adjoint adds the lanes' cotangents per peer set before one atomic add (warp's own
# adjoint of an array read, wp::adj_address, adds each lane's: the CPU branch)
_LOAD_AGG = "return wp::index(a, i, j, k);"
_LOAD_AGG_ADJ = f"""
#if defined(__CUDA_ARCH__)
{_peer_tree("adj_ret", 3)}if ({_IS_LEADER}) {{
    if (adj_a.data) wp::adj_atomic_add(&wp::index(adj_a, i, j, k), s);
    else if (a.grad) wp::adj_atomic_add(&wp::index_grad(a, i, j, k), s);
}}
#else
wp::adj_address(a, i, j, k, adj_a, adj_i, adj_j, adj_k, adj_ret);
#endif
"""


# One node's (mv, m) share as ONE vector atomic (``scatter4``; ``MPMSolver.vec4_p2g``): the grid's momentum and mass
# interleaved as a vec4 a node (16 bytes, aligned), added by Hopper's vector reduction (sm_90+, PTX ISA 8.1:
# ``red.global.add.v4.f32``: one instruction and one L2 request for the four floats, where warp's atomic_add of a vec3
# and a scalar are four). Float64, older GPUs and the CPU take warp's own atomic_add of the vec4 (component-wise, the
# same sums in the same order as the four scalar adds of ``scatter``).
_ATOMIC_ADD4 = "wp::atomic_add(&wp::index(a, i, j, k), v);"
_ATOMIC_ADD4_F32 = f"""
#if defined(__CUDA_ARCH__) && (__CUDA_ARCH__ >= 900)
float* ptr = &wp::index(a, i, j, k).c[0];
asm volatile("red.global.add.v4.f32 [%0], {{%1, %2, %3, %4}};" :: "l"(__cvta_generic_to_global(ptr)),
             "f"(v.c[0]), "f"(v.c[1]), "f"(v.c[2]), "f"(v.c[3]) : "memory");
#else
{_ATOMIC_ADD4}
#endif
"""

# G2P's node read whose adjoint adds the node's velocity cotangent into an interleaved accumulator ``acc`` (vec4 a
# node, the fourth component 0) with one vector reduction on sm_90+ in float32, instead of warp's three scalar atomics
# into the velocity grid's gradient (``MPMSolver.vec4_g2p_adj``; ``grid_unpack_adj4`` then adds it there). Elsewhere
# warp's component-wise atomic add of the vec4 (the same sums in the same order).
# ({zero}: a literal, as warp's headers define float(x) and double(x) as casts)
_READ4 = "return wp::index(a, i, j, k);"
_READ4_ADJ_ANY = ("wp::atomic_add(&wp::index(acc, i, j, k), "
                  "wp::vec_t<4, {c}>(adj_ret.c[0], adj_ret.c[1], adj_ret.c[2], {zero}));")
_READ4_ADJ_F32 = f"""
#if defined(__CUDA_ARCH__) && (__CUDA_ARCH__ >= 900)
float* ptr = &wp::index(acc, i, j, k).c[0];
asm volatile("red.global.add.v4.f32 [%0], {{%1, %2, %3, %4}};" :: "l"(__cvta_generic_to_global(ptr)),
             "f"(adj_ret.c[0]), "f"(adj_ret.c[1]), "f"(adj_ret.c[2]), "f"(0.0f) : "memory");
#else
{_READ4_ADJ_ANY.format(c="float", zero="0.0f")}
#endif
"""


@wp.func_native(_PEERS)
def warp_peers(key: int) -> int:
    """Bit mask of the lanes of this thread's warp (among those active) whose ``key`` equals this one's; 1 off CUDA."""
    ...


@wp.func_native(_LEADER)
def peer_leader(peers: int) -> bool:
    """Whether this lane is the lowest of ``peers`` (:func:`warp_peers`); True off CUDA."""
    ...


def block_dim(device) -> int:
    """Threads per block of the block-cooperative kernels on a warp ``device``: ``BLOCK`` on CUDA; on a CPU 1 (warp
    runs a CPU block as one thread) unless ``wp.config.enable_cpu_blocks`` (cooperative fibers, used by the tests)."""
    return BLOCK if (wp.get_device(device).is_cuda or wp.config.enable_cpu_blocks) else 1


def launch_blocks(kernel, n: int, inputs: list, device) -> None:
    """Launch a block-cooperative kernel (``p2g_block`` and the fused step's ``*_block``) over ``n`` particles:
    ``ceil(n / B)`` blocks of ``B = block_dim(device)`` threads, thread ``lane`` of block ``blk`` on particle
    ``blk B + lane`` (none past ``n``)."""
    B = block_dim(device)
    wp.launch_tiled(kernel, dim=[(n + B - 1) // B], inputs=inputs, block_dim=B, device=device)


def grid_size(n_grid: int) -> int:
    """Number of stored nodes per axis of the padded grid for ``n_grid`` cells."""
    return n_grid + 1 + 2 * PAD


def make_kernels(T: type) -> types.SimpleNamespace:
    """Build the P2G, grid-update and G2P kernels for one float type.

    Args:
        T: ``wp.float32`` or ``wp.float64``.

    Returns:
        Namespace with ``p2g``, ``grid_update``, ``g2p`` kernels and the ``vec3``/``mat33`` types.
    """
    if T not in (wp.float32, wp.float64):
        raise TypeError(f"gca/sim/kernels.py: float type must be wp.float32 or wp.float64, got {T}")
    vec3 = wp.types.vector(3, T)
    mat33 = wp.types.matrix((3, 3), T)
    module = f"gca_sim_mpm_{T.__name__}"
    block_module = f"gca_sim_mpm_block_{T.__name__}"  # block-cooperative (tile) kernels, compiled apart
    agg_module = f"gca_sim_mpm_agg_{T.__name__}"  # warp-aggregated kernels (options): compiled only where launched
    v4_module = f"gca_sim_mpm_v4_{T.__name__}"  # the vec4 grid's kernels (an option): compiled only where launched
    adj_module = f"gca_sim_mpm_adj_{T.__name__}"  # adjoints written out (options): compiled only where launched

    @wp.func
    def stencil(x: vec3, inv_dx: T, n_grid: int):
        """Floor-based base node [node] and quadratic B-spline weights W[k, axis] of node base+k."""
        X = x * inv_dx
        top = n_grid + PAD - 2
        base = wp.vec3i(
            wp.clamp(int(wp.floor(X[0] - T(0.5))), -PAD, top),
            wp.clamp(int(wp.floor(X[1] - T(0.5))), -PAD, top),
            wp.clamp(int(wp.floor(X[2] - T(0.5))), -PAD, top),
        )
        fx = X - vec3(T(int(base[0])), T(int(base[1])), T(int(base[2])))
        w0 = T(0.5) * wp.cw_mul(vec3(T(1.5)) - fx, vec3(T(1.5)) - fx)
        w1 = vec3(T(0.75)) - wp.cw_mul(fx - vec3(T(1.0)), fx - vec3(T(1.0)))
        w2 = T(0.5) * wp.cw_mul(fx - vec3(T(0.5)), fx - vec3(T(0.5)))
        return base, fx, wp.matrix_from_rows(w0, w1, w2)

    @wp.func
    def run_offset(run: wp.array(dtype=int), p: int, n_grid: int, n_first: int):
        """Index offset along the first grid axis of particle ``p``'s run: runs' grids are stacked there,
        ``n_grid + 1 + 2 PAD`` nodes each; the run index is clamped to the grids present."""
        G = n_grid + 1 + 2 * PAD
        return wp.clamp(run[p], 0, n_first // G - 1) * G

    @wp.func
    def scatter(x_p: vec3, v_p: vec3, C_p: mat33, tau_p: mat33, vol_p: T, m_p: T, off: int, dt: T, inv_dx: T,
                n_grid: int, grid_mv: wp.array3d(dtype=vec3), grid_m: wp.array3d(dtype=T)):
        """P2G of one particle (Kirchhoff stress ``tau_p``) onto its 27 nodes of the grid at offset ``off``: forward
        only (``gca.sim.fused_step``)."""
        base, fx, W = stencil(x_p, inv_dx, n_grid)
        affine = (-dt * vol_p * T(4.0) * inv_dx * inv_dx) * tau_p + m_p * C_p
        mv_p = m_p * v_p
        for i in range(3):
            for j in range(3):
                for k in range(3):
                    w = W[i, 0] * W[j, 1] * W[k, 2]
                    dpos = (vec3(T(int(i)), T(int(j)), T(int(k))) - fx) / inv_dx
                    I = base[0] + i + PAD + off
                    J = base[1] + j + PAD
                    K = base[2] + k + PAD
                    wp.atomic_add(grid_mv, I, J, K, w * (mv_p + affine @ dpos))
                    wp.atomic_add(grid_m, I, J, K, w * m_p)

    @wp.kernel(module=module)
    def p2g(  # the loop of `scatter` written out: warp's adjoint of atomic adds inside a func (into its array
        # arguments) is not reentrant (the step's float64 gradcheck fails), and this kernel's adjoint is the step's
        x: wp.array(dtype=vec3),
        v: wp.array(dtype=vec3),
        C: wp.array(dtype=mat33),
        tau: wp.array(dtype=mat33),
        vol: wp.array(dtype=T),
        mass: wp.array(dtype=T),
        run: wp.array(dtype=int),
        dt: T,
        inv_dx: T,
        n_grid: int,
        grid_mv: wp.array3d(dtype=vec3),
        grid_m: wp.array3d(dtype=T),
    ):
        p = wp.tid()
        base, fx, W = stencil(x[p], inv_dx, n_grid)
        off = run_offset(run, p, n_grid, grid_m.shape[0])
        m_p = mass[p]
        affine = (-dt * vol[p] * T(4.0) * inv_dx * inv_dx) * tau[p] + m_p * C[p]
        mv_p = m_p * v[p]
        for i in range(3):
            for j in range(3):
                for k in range(3):
                    w = W[i, 0] * W[j, 1] * W[k, 2]
                    dpos = (vec3(T(int(i)), T(int(j)), T(int(k))) - fx) / inv_dx
                    I = base[0] + i + PAD + off
                    J = base[1] + j + PAD
                    K = base[2] + k + PAD
                    wp.atomic_add(grid_mv, I, J, K, w * (mv_p + affine @ dpos))
                    wp.atomic_add(grid_m, I, J, K, w * m_p)

    vec4 = wp.types.vector(4, T)

    @wp.func_native(_PEER_SUM4)
    def peer_sum4(peers: int, a: vec4) -> vec4:
        """At the leader of ``peers`` (:func:`peer_leader`), the sum of ``a`` over them (other lanes: partial sums,
        unused); off CUDA ``a``. Every lane of ``peers`` must call it (they do: all call it 27 times)."""
        ...

    @wp.func
    def base_peers(base: wp.vec3i, off: int, G: int):
        """:func:`warp_peers` of the stencil base ``base`` in the run whose grid starts at ``off`` along the first
        axis: the key is the base node's index in the stacked grids (``G`` nodes a side), so two runs never merge."""
        return warp_peers(((base[0] + PAD + off) * G + base[1] + PAD) * G + base[2] + PAD)

    @wp.func
    def scatter_agg(x_p: vec3, v_p: vec3, C_p: mat33, tau_p: mat33, vol_p: T, m_p: T, off: int, dt: T, inv_dx: T,
                    n_grid: int, grid_mv: wp.array3d(dtype=vec3), grid_m: wp.array3d(dtype=T)):
        """:func:`scatter` with warp-aggregated atomics: the warp's lanes of one stencil base (the same 27 nodes,
        :func:`base_peers`) sum their shares by shuffles, and the lowest adds the sum: one atomic add per node and base
        (``_PEER_SUM4``). Forward only; off CUDA it is ``scatter``."""
        base, fx, W = stencil(x_p, inv_dx, n_grid)
        peers = base_peers(base, off, grid_m.shape[1])
        lead = peer_leader(peers)
        affine = (-dt * vol_p * T(4.0) * inv_dx * inv_dx) * tau_p + m_p * C_p
        mv_p = m_p * v_p
        for i in range(3):
            for j in range(3):
                for k in range(3):
                    w = W[i, 0] * W[j, 1] * W[k, 2]
                    dpos = (vec3(T(int(i)), T(int(j)), T(int(k))) - fx) / inv_dx
                    share = w * (mv_p + affine @ dpos)
                    s = peer_sum4(peers, vec4(share[0], share[1], share[2], w * m_p))
                    if lead:
                        I = base[0] + i + PAD + off
                        J = base[1] + j + PAD
                        K = base[2] + k + PAD
                        wp.atomic_add(grid_mv, I, J, K, vec3(s[0], s[1], s[2]))
                        wp.atomic_add(grid_m, I, J, K, s[3])

    @wp.kernel(module=agg_module)
    def p2g_agg(
        x: wp.array(dtype=vec3),
        v: wp.array(dtype=vec3),
        C: wp.array(dtype=mat33),
        tau: wp.array(dtype=mat33),
        vol: wp.array(dtype=T),
        mass: wp.array(dtype=T),
        run: wp.array(dtype=int),
        dt: T,
        inv_dx: T,
        n_grid: int,
        grid_mv: wp.array3d(dtype=vec3),
        grid_m: wp.array3d(dtype=T),
    ):
        """:func:`p2g` through :func:`scatter_agg`. Forward only, like ``p2g_nodes``: the step's backward uses the
        adjoint of ``p2g``. Off CUDA it is ``p2g``."""
        p = wp.tid()
        scatter_agg(x[p], v[p], C[p], tau[p], vol[p], mass[p], run_offset(run, p, n_grid, grid_m.shape[0]), dt, inv_dx,
                    n_grid, grid_mv, grid_m)

    @wp.func_native(_ATOMIC_ADD4_F32 if T is wp.float32 else _ATOMIC_ADD4)
    def atomic_add4(a: wp.array3d(dtype=vec4), i: int, j: int, k: int, v: vec4):
        """``a[i, j, k] += v`` atomically: one vector reduction on sm_90+ in float32, else component-wise."""
        ...

    @wp.func
    def scatter4(x_p: vec3, v_p: vec3, C_p: mat33, tau_p: mat33, vol_p: T, m_p: T, off: int, dt: T, inv_dx: T,
                 n_grid: int, grid: wp.array3d(dtype=vec4)):
        """:func:`scatter` onto the interleaved grid ``grid`` [.., .., ..] of vec4 (mv [kg m/s] in components 0-2, m
        [kg] in 3): a node's share is one :func:`atomic_add4`. Forward only."""
        base, fx, W = stencil(x_p, inv_dx, n_grid)
        affine = (-dt * vol_p * T(4.0) * inv_dx * inv_dx) * tau_p + m_p * C_p
        mv_p = m_p * v_p
        for i in range(3):
            for j in range(3):
                for k in range(3):
                    w = W[i, 0] * W[j, 1] * W[k, 2]
                    dpos = (vec3(T(int(i)), T(int(j)), T(int(k))) - fx) / inv_dx
                    share = w * (mv_p + affine @ dpos)
                    atomic_add4(grid, base[0] + i + PAD + off, base[1] + j + PAD, base[2] + k + PAD,
                                vec4(share[0], share[1], share[2], w * m_p))

    @wp.kernel(module=v4_module)
    def p2g4(
        x: wp.array(dtype=vec3),
        v: wp.array(dtype=vec3),
        C: wp.array(dtype=mat33),
        tau: wp.array(dtype=mat33),
        vol: wp.array(dtype=T),
        mass: wp.array(dtype=T),
        run: wp.array(dtype=int),
        dt: T,
        inv_dx: T,
        n_grid: int,
        grid: wp.array3d(dtype=vec4),
    ):
        """:func:`p2g` through :func:`scatter4` onto the interleaved (mv, m) grid. Forward only (``bench_p2g``'s
        ``p2g_v4``; the fused analytic step's kernels take the same ``scatter4``)."""
        p = wp.tid()
        scatter4(x[p], v[p], C[p], tau[p], vol[p], mass[p], run_offset(run, p, n_grid, grid.shape[0]), dt, inv_dx,
                 n_grid, grid)

    @wp.func
    def scatter_block(valid: bool, x_p: vec3, v_p: vec3, C_p: mat33, tau_p: mat33, vol_p: T, m_p: T, off: int,
                      lane: int, dt: T, inv_dx: T, n_grid: int, grid_mv: wp.array3d(dtype=vec3),
                      grid_m: wp.array3d(dtype=T), windows: wp.array(dtype=int)):
        """:func:`scatter` of a thread block's particles, summed in shared memory first (block-cooperative: every
        thread of the block calls it; ``valid`` False for a thread without a particle, whose inputs are ignored).

        The block's stencils span a box of nodes (min and max base index per axis, over its particles). If the box
        has at most ``WINDOW`` nodes, each particle adds its 27 shares (mv, m) into a shared-memory window of the box
        and the window's non-zero nodes are then added to the grid: one global atomic per node and component instead
        of one per particle, node and component (lattice-ordered particles, ~64 per cell at the paper profile, hit
        the same nodes ~1700 times per step, and P2G was bound by those contended atomics: NOTES session 31). A
        block whose box is larger (particles scattered, several runs' grids) scatters directly, as :func:`scatter`.
        Same sums to float rounding (the order of the additions differs; tested against ``p2g`` in float64).
        ``windows[0]`` counts the blocks that took the window."""
        base, fx, W = stencil(x_p, inv_dx, n_grid)
        b0 = base[0] + off
        big = 1 << 29
        l0, l1, l2, h0, h1, h2 = big, big, big, -big, -big, -big
        if valid:
            l0, l1, l2, h0, h1, h2 = b0, base[1], base[2], b0, base[1], base[2]
        lo0 = wp.tile_min(wp.tile(l0))[0]
        lo1 = wp.tile_min(wp.tile(l1))[0]
        lo2 = wp.tile_min(wp.tile(l2))[0]
        e0 = wp.tile_max(wp.tile(h0))[0] - lo0 + 3
        e1 = wp.tile_max(wp.tile(h1))[0] - lo1 + 3
        e2 = wp.tile_max(wp.tile(h2))[0] - lo2 + 3
        window = wp.tile_zeros(shape=WINDOW, dtype=vec4, storage="shared")
        affine = (-dt * vol_p * T(4.0) * inv_dx * inv_dx) * tau_p + m_p * C_p
        mv_p = m_p * v_p
        size = e0 * e1 * e2
        if size <= WINDOW:
            if lane == 0:
                wp.atomic_add(windows, 0, 1)
            for i in range(3):
                for j in range(3):
                    for k in range(3):
                        w = W[i, 0] * W[j, 1] * W[k, 2]
                        dpos = (vec3(T(int(i)), T(int(j)), T(int(k))) - fx) / inv_dx
                        share = w * (mv_p + affine @ dpos)
                        at = ((b0 - lo0 + i) * e1 + (base[1] - lo1 + j)) * e2 + (base[2] - lo2 + k)
                        wp.tile_scatter_add(window, at, vec4(share[0], share[1], share[2], w * m_p), valid)
            at = lane
            while at < size:
                node = window[at]
                if node[3] != T(0.0) or node[0] != T(0.0) or node[1] != T(0.0) or node[2] != T(0.0):
                    K = at % e2
                    J = (at // e2) % e1
                    I = at // (e1 * e2)
                    wp.atomic_add(grid_mv, lo0 + I + PAD, lo1 + J + PAD, lo2 + K + PAD, vec3(node[0], node[1], node[2]))
                    wp.atomic_add(grid_m, lo0 + I + PAD, lo1 + J + PAD, lo2 + K + PAD, node[3])
                at += wp.block_dim()
        elif valid:  # forward only, so the func's atomics are safe here (see p2g)
            scatter(x_p, v_p, C_p, tau_p, vol_p, m_p, off, dt, inv_dx, n_grid, grid_mv, grid_m)

    @wp.kernel(module=block_module)
    def p2g_block(
        x: wp.array(dtype=vec3),
        v: wp.array(dtype=vec3),
        C: wp.array(dtype=mat33),
        tau: wp.array(dtype=mat33),
        vol: wp.array(dtype=T),
        mass: wp.array(dtype=T),
        run: wp.array(dtype=int),
        dt: T,
        inv_dx: T,
        n_grid: int,
        grid_mv: wp.array3d(dtype=vec3),
        grid_m: wp.array3d(dtype=T),
        windows: wp.array(dtype=int),
    ):
        """:func:`p2g` summed per thread block in shared memory first (:func:`scatter_block`), launched by
        :func:`launch_blocks`; forward only, like ``p2g_nodes`` (the step's backward uses ``p2g``'s adjoint).
        ``windows[0]`` counts the blocks whose sums went through the shared window."""
        blk, lane = wp.tid()
        n = x.shape[0]
        p = blk * wp.block_dim() + lane
        q = wp.min(p, n - 1)
        scatter_block(p < n, x[q], v[q], C[q], tau[q], vol[q], mass[q], run_offset(run, q, n_grid, grid_m.shape[0]),
                      lane, dt, inv_dx, n_grid, grid_mv, grid_m, windows)

    @wp.kernel(module=module)
    def p2g_nodes(
        x: wp.array(dtype=vec3),
        v: wp.array(dtype=vec3),
        C: wp.array(dtype=mat33),
        tau: wp.array(dtype=mat33),
        vol: wp.array(dtype=T),
        mass: wp.array(dtype=T),
        run: wp.array(dtype=int),
        dt: T,
        inv_dx: T,
        n_grid: int,
        grid_mv: wp.array3d(dtype=vec3),
        grid_m: wp.array3d(dtype=T),
    ):
        """:func:`p2g` with one thread per (particle, stencil node) pair: thread ``27 p + 9 i + 3 j + k``
        scatters particle ``p``'s share to node ``base + (i, j, k)``. Same sums in the same order on a CPU
        (bitwise equal to ``p2g``); on a GPU 27x more threads carry the atomics, which a few tens of thousands
        of particles (a few warps per SM) cannot keep in flight. Forward only: the step's backward uses the
        adjoint of ``p2g``, which reads the same inputs and never the grid."""
        t = wp.tid()
        p = t // 27
        node = t - 27 * p
        i = node // 9
        j = (node // 3) % 3
        k = node % 3
        base, fx, W = stencil(x[p], inv_dx, n_grid)
        m_p = mass[p]
        affine = (-dt * vol[p] * T(4.0) * inv_dx * inv_dx) * tau[p] + m_p * C[p]
        w = W[i, 0] * W[j, 1] * W[k, 2]
        dpos = (vec3(T(int(i)), T(int(j)), T(int(k))) - fx) / inv_dx
        I = base[0] + i + PAD + run_offset(run, p, n_grid, grid_m.shape[0])
        J = base[1] + j + PAD
        K = base[2] + k + PAD
        wp.atomic_add(grid_mv, I, J, K, w * (m_p * v[p] + affine @ dpos))
        wp.atomic_add(grid_m, I, J, K, w * m_p)

    @wp.func
    def wall(v: vec3, n_out: vec3, inside: int, kind: int, mu_b: T):
        """Velocity of a node after the wall whose outward unit normal is ``n_out``."""
        if inside == 0:
            return v
        if kind == STICKY:
            return vec3(T(0.0))
        vn = wp.dot(v, n_out)
        if vn <= T(0.0):
            return v
        vt = v - vn * n_out
        if kind == SLIP:
            return vt
        # compare squares first: sqrt(0) would put 0 * inf = NaN into the adjoint
        vt2 = wp.dot(vt, vt)
        if vt2 <= (mu_b * vn) * (mu_b * vn):
            return vec3(T(0.0))
        return vt * (T(1.0) - mu_b * vn / wp.sqrt(vt2))

    @wp.func
    def node_velocity(mv: vec3, m: T, s0: int, s1: int, s2: int, gravity: vec3, dt: T, eps: T, m_min: T, n_grid: int,
                      bound: int, kind: int, mu_b: T):
        """Velocity of the stored node (s0, s1, s2) from its momentum and mass, gravity and the walls."""
        # empty node, or one whose mass comes from B-spline weights so small that the adjoint of
        # mv / m (ret / m, i.e. v / m) overflows float32 to inf and turns the gradients NaN
        if m <= m_min:
            return vec3(T(0.0))
        v = mv / (m + eps) + dt * gravity
        I = s0 % (n_grid + 1 + 2 * PAD) - PAD  # the node's index within its run's grid
        J = s1 - PAD
        K = s2 - PAD
        hi = n_grid - bound
        v = wall(v, vec3(T(-1.0), T(0.0), T(0.0)), int(I < bound), kind, mu_b)
        v = wall(v, vec3(T(1.0), T(0.0), T(0.0)), int(I > hi), kind, mu_b)
        v = wall(v, vec3(T(0.0), T(-1.0), T(0.0)), int(J < bound), kind, mu_b)
        v = wall(v, vec3(T(0.0), T(1.0), T(0.0)), int(J > hi), kind, mu_b)
        v = wall(v, vec3(T(0.0), T(0.0), T(-1.0)), int(K < bound), kind, mu_b)
        v = wall(v, vec3(T(0.0), T(0.0), T(1.0)), int(K > hi), kind, mu_b)
        return v

    @wp.kernel(module=module)
    def grid_update(
        grid_mv: wp.array3d(dtype=vec3),
        grid_m: wp.array3d(dtype=T),
        gravity: vec3,
        dt: T,
        eps: T,
        m_min: T,
        n_grid: int,
        bound: int,
        kind: int,
        mu_b: T,
        grid_v: wp.array3d(dtype=vec3),
    ):
        s0, s1, s2 = wp.tid()
        grid_v[s0, s1, s2] = node_velocity(grid_mv[s0, s1, s2], grid_m[s0, s1, s2], s0, s1, s2, gravity, dt, eps,
                                           m_min, n_grid, bound, kind, mu_b)

    @wp.kernel(module=v4_module)
    def grid_update_unpack4(
        grid: wp.array3d(dtype=vec4),
        grid_mv: wp.array3d(dtype=vec3),
        grid_m: wp.array3d(dtype=T),
        gravity: vec3,
        dt: T,
        eps: T,
        m_min: T,
        n_grid: int,
        bound: int,
        kind: int,
        mu_b: T,
        grid_v: wp.array3d(dtype=vec3),
    ):
        """``grid_update`` after :func:`p2g4`: the interleaved node (mv, m) of ``grid`` added to ``grid_mv`` and
        ``grid_m`` (as ``p2g``'s atomics would have added it: zero there, bitwise its sums), the node's velocity from
        them, and ``grid`` set back to zero for the next step (``MPMSolver.vec4_step``). Forward only: the step's
        backward runs ``grid_update``'s adjoint on (mv, m)."""
        s0, s1, s2 = wp.tid()
        g = grid[s0, s1, s2]
        mv = grid_mv[s0, s1, s2] + vec3(g[0], g[1], g[2])
        m = grid_m[s0, s1, s2] + g[3]
        grid_mv[s0, s1, s2] = mv
        grid_m[s0, s1, s2] = m
        grid_v[s0, s1, s2] = node_velocity(mv, m, s0, s1, s2, gravity, dt, eps, m_min, n_grid, bound, kind, mu_b)
        grid[s0, s1, s2] = vec4(T(0.0))

    @wp.func_native(_LOAD_AGG, adj_snippet=_LOAD_AGG_ADJ)
    def node_read_agg(a: wp.array3d(dtype=vec3), i: int, j: int, k: int, peers: int) -> vec3:
        """``a[i, j, k]``; its adjoint sums the cotangents of ``peers`` (:func:`warp_peers`) and adds them once."""
        ...

    @wp.func
    def gathered(x_p: vec3, F_p: mat33, v_new: vec3, B: mat33, dt: T, inv_dx: T, lo: T, hi: T):
        """A particle's (x' clamped to [lo, hi], v', C', F_trial) from its gathered velocity ``v_new`` and
        ``B = sum_i w_ip v_i (x_i - x_p)^T``."""
        C_new = (T(4.0) * inv_dx * inv_dx) * B
        x_new = x_p + dt * v_new
        x_new = vec3(wp.clamp(x_new[0], lo, hi), wp.clamp(x_new[1], lo, hi), wp.clamp(x_new[2], lo, hi))
        return x_new, v_new, C_new, (wp.identity(3, dtype=T) + dt * C_new) @ F_p

    def make_gather(agg: bool):
        """The G2P of one particle; ``agg``: the grid's cotangent summed over the warp's lanes of the same stencil
        base (:func:`base_peers`) before its atomic adds (the adjoint's scatter), else each lane adds its own."""

        def gather(x_p: vec3, F_p: mat33, off: int, grid_v: wp.array3d(dtype=vec3), dt: T, inv_dx: T, n_grid: int,
                   lo: T, hi: T):
            """G2P of one particle from the grid at offset ``off``: (x' clamped to [lo, hi], v', C', F_trial)."""
            base, fx, W = stencil(x_p, inv_dx, n_grid)
            if wp.static(agg):
                peers = base_peers(base, off, grid_v.shape[1])
            v_new = vec3(T(0.0))
            B = mat33(T(0.0))
            for i in range(3):
                for j in range(3):
                    for k in range(3):
                        w = W[i, 0] * W[j, 1] * W[k, 2]
                        dpos = (vec3(T(int(i)), T(int(j)), T(int(k))) - fx) / inv_dx
                        if wp.static(agg):
                            v_i = node_read_agg(grid_v, base[0] + i + PAD + off, base[1] + j + PAD, base[2] + k + PAD,
                                                peers)
                        else:
                            v_i = grid_v[base[0] + i + PAD + off, base[1] + j + PAD, base[2] + k + PAD]
                        v_new += w * v_i
                        B += w * wp.outer(v_i, dpos)
            return gathered(x_p, F_p, v_new, B, dt, inv_dx, lo, hi)

        gather.__qualname__ += "_agg" if agg else ""
        return wp.func(gather)

    gather, gather_agg = make_gather(False), make_gather(True)

    def make_g2p(agg: bool):
        """The G2P kernel over the particles (``agg``: its adjoint's grid scatter aggregated per warp, ``g2p_agg``)."""

        def g2p(
            x: wp.array(dtype=vec3),
            F: wp.array(dtype=mat33),
            run: wp.array(dtype=int),
            grid_v: wp.array3d(dtype=vec3),
            dt: T,
            inv_dx: T,
            n_grid: int,
            lo: T,
            hi: T,
            x_out: wp.array(dtype=vec3),
            v_out: wp.array(dtype=vec3),
            C_out: wp.array(dtype=mat33),
            F_out: wp.array(dtype=mat33),
        ):
            p = wp.tid()
            x_new, v_new, C_new, F_new = wp.static(gather_agg if agg else gather)(
                x[p], F[p], run_offset(run, p, n_grid, grid_v.shape[0]), grid_v, dt, inv_dx, n_grid, lo, hi)
            v_out[p] = v_new
            C_out[p] = C_new
            F_out[p] = F_new
            x_out[p] = x_new

        g2p.__name__ = g2p.__qualname__ = "g2p_agg" if agg else "g2p"
        return wp.kernel(g2p, module=agg_module if agg else module)

    g2p, g2p_agg = make_g2p(False), make_g2p(True)

    @wp.func_native(_READ4, adj_snippet=_READ4_ADJ_F32 if T is wp.float32 else
                    _READ4_ADJ_ANY.format(c="double", zero="0.0"))
    def node_read4(a: wp.array3d(dtype=vec3), i: int, j: int, k: int, acc: wp.array3d(dtype=vec4)) -> vec3:
        """``a[i, j, k]``; its adjoint adds the cotangent to ``acc[i, j, k]`` (components 0-2; one vector atomic in
        float32 on sm_90+, else component-wise), and nothing to ``a``'s gradient (:func:`grid_unpack_adj4` moves it
        there)."""
        ...

    @wp.func
    def gather4(x_p: vec3, F_p: mat33, off: int, grid_v: wp.array3d(dtype=vec3), acc: wp.array3d(dtype=vec4), dt: T,
                inv_dx: T, n_grid: int, lo: T, hi: T):
        """:func:`gather` whose node reads are :func:`node_read4` (the adjoint's scatter into ``acc``)."""
        base, fx, W = stencil(x_p, inv_dx, n_grid)
        v_new = vec3(T(0.0))
        B = mat33(T(0.0))
        for i in range(3):
            for j in range(3):
                for k in range(3):
                    w = W[i, 0] * W[j, 1] * W[k, 2]
                    dpos = (vec3(T(int(i)), T(int(j)), T(int(k))) - fx) / inv_dx
                    v_i = node_read4(grid_v, base[0] + i + PAD + off, base[1] + j + PAD, base[2] + k + PAD, acc)
                    v_new += w * v_i
                    B += w * wp.outer(v_i, dpos)
        return gathered(x_p, F_p, v_new, B, dt, inv_dx, lo, hi)

    @wp.kernel(module=v4_module)
    def g2p4(
        x: wp.array(dtype=vec3),
        F: wp.array(dtype=mat33),
        run: wp.array(dtype=int),
        grid_v: wp.array3d(dtype=vec3),
        acc: wp.array3d(dtype=vec4),
        dt: T,
        inv_dx: T,
        n_grid: int,
        lo: T,
        hi: T,
        x_out: wp.array(dtype=vec3),
        v_out: wp.array(dtype=vec3),
        C_out: wp.array(dtype=mat33),
        F_out: wp.array(dtype=mat33),
    ):
        """``g2p`` (the same forward) whose adjoint scatters the velocity grid's cotangent into ``acc`` [.., .., ..]
        vec4 with one vector atomic a node (``MPMSolver.vec4_g2p_adj``); :func:`grid_unpack_adj4` adds it into the
        velocity grid's gradient before the grid update's adjoint reads it."""
        p = wp.tid()
        x_new, v_new, C_new, F_new = gather4(x[p], F[p], run_offset(run, p, n_grid, grid_v.shape[0]), grid_v, acc, dt,
                                             inv_dx, n_grid, lo, hi)
        v_out[p] = v_new
        C_out[p] = C_new
        F_out[p] = F_new
        x_out[p] = x_new

    @wp.kernel(module=v4_module)
    def grid_unpack_adj4(acc: wp.array3d(dtype=vec4), adj_grid_v: wp.array3d(dtype=vec3)):
        """After ``g2p4``'s adjoint: ``adj_grid_v += acc[..., :3]``, then ``acc`` set back to zero."""
        s0, s1, s2 = wp.tid()
        g = acc[s0, s1, s2]
        adj_grid_v[s0, s1, s2] = adj_grid_v[s0, s1, s2] + vec3(g[0], g[1], g[2])
        acc[s0, s1, s2] = vec4(T(0.0))

    @wp.func
    def spline_slopes(fx: vec3):
        """d W[k, axis] / d fx[axis] of :func:`stencil`'s quadratic B-spline weights, rows k = 0, 1, 2."""
        return wp.matrix_from_rows(fx - vec3(T(1.5)), T(-2.0) * (fx - vec3(T(1.0))), fx - vec3(T(0.5)))

    @wp.func
    def weight_slope(W: mat33, dW: mat33, i: int, j: int, k: int):
        """d w / d fx of node (i, j, k)'s weight ``w = W[i, 0] W[j, 1] W[k, 2]``."""
        return vec3(dW[i, 0] * W[j, 1] * W[k, 2], W[i, 0] * dW[j, 1] * W[k, 2], W[i, 0] * W[j, 1] * dW[k, 2])

    @wp.kernel(module=adj_module)
    def p2g_adj(
        x: wp.array(dtype=vec3),
        v: wp.array(dtype=vec3),
        C: wp.array(dtype=mat33),
        tau: wp.array(dtype=mat33),
        vol: wp.array(dtype=T),
        mass: wp.array(dtype=T),
        run: wp.array(dtype=int),
        dt: T,
        inv_dx: T,
        n_grid: int,
        adj_mv: wp.array3d(dtype=vec3),
        adj_m: wp.array3d(dtype=T),
        adj_x: wp.array(dtype=vec3),
        adj_v: wp.array(dtype=vec3),
        adj_C: wp.array(dtype=mat33),
        adj_tau: wp.array(dtype=mat33),
    ):
        """The adjoint of :func:`p2g` written out (``MPMSolver.hand_p2g_adj``): from the grid's cotangents ``adj_mv``
        [.., .., ..] vec3 and ``adj_m`` (of the nodes' momentum and mass), ADDED to the particles' ``adj_x``,
        ``adj_v``, ``adj_C``, ``adj_tau`` (vol and mass get none: constants of a rollout). A gather, one thread per
        particle; warp's generated adjoint replays the 27 unrolled node updates and differentiates every temporary.

        With ``A = k tau + m C``, ``k = -4 dt vol / dx^2`` (MLS-MPM's affine momentum with the Kirchhoff stress, Hu et
        al. 2018, as :func:`p2g` adds it) and node i's share ``w_i (m v + A dpos_i)`` and ``w_i m``,
        ``dpos_i = x_i - x_p``, ``g_i = adj_mv[i]``, ``h_i = adj_m[i]``, ``s_i = g_i . (m v + A dpos_i) + h_i m``:

            adj_v += m sum_i w_i g_i,     adj_A = sum_i w_i g_i dpos_i^T  (adj_C += m adj_A, adj_tau += k adj_A),
            adj_x += sum_i (s_i dw_i/dx - w_i A^T g_i)

        (``dpos_i`` falls as ``x_p`` moves; ``dw_i/dx = inv_dx dw_i/dfx`` with the B-spline's derivatives ``fx - 1.5``,
        ``-2 (fx - 1)``, ``fx - 0.5``; the floor of the stencil base has none)."""
        p = wp.tid()
        base, fx, W = stencil(x[p], inv_dx, n_grid)
        off = run_offset(run, p, n_grid, adj_m.shape[0])
        m_p = mass[p]
        k_s = -dt * vol[p] * T(4.0) * inv_dx * inv_dx
        A = k_s * tau[p] + m_p * C[p]
        At = wp.transpose(A)
        mv_p = m_p * v[p]
        dW = spline_slopes(fx)
        g_v = vec3(T(0.0))
        g_A = mat33(T(0.0))
        g_fx = vec3(T(0.0))
        for i in range(3):
            for j in range(3):
                for k in range(3):
                    w = W[i, 0] * W[j, 1] * W[k, 2]
                    dw = weight_slope(W, dW, i, j, k)
                    dpos = (vec3(T(int(i)), T(int(j)), T(int(k))) - fx) / inv_dx
                    I = base[0] + i + PAD + off
                    J = base[1] + j + PAD
                    K = base[2] + k + PAD
                    g = adj_mv[I, J, K]
                    s = wp.dot(g, mv_p + A @ dpos) + adj_m[I, J, K] * m_p
                    wg = w * g
                    g_v += wg
                    g_A += wp.outer(wg, dpos)
                    g_fx += s * dw - (At @ wg) / inv_dx
        adj_v[p] = adj_v[p] + m_p * g_v
        adj_C[p] = adj_C[p] + m_p * g_A
        adj_tau[p] = adj_tau[p] + k_s * g_A
        adj_x[p] = adj_x[p] + inv_dx * g_fx

    @wp.kernel(module=adj_module)
    def g2p4_adj(
        x: wp.array(dtype=vec3),
        F: wp.array(dtype=mat33),
        run: wp.array(dtype=int),
        grid_v: wp.array3d(dtype=vec3),
        acc: wp.array3d(dtype=vec4),
        dt: T,
        inv_dx: T,
        n_grid: int,
        lo: T,
        hi: T,
        adj_x_out: wp.array(dtype=vec3),
        adj_v_out: wp.array(dtype=vec3),
        adj_C_out: wp.array(dtype=mat33),
        adj_F_out: wp.array(dtype=mat33),
        adj_x: wp.array(dtype=vec3),
        adj_F: wp.array(dtype=mat33),
    ):
        """The adjoint of :func:`g2p4` (and :func:`g2p`) written out (``MPMSolver.hand_g2p_adj``): from the outputs'
        cotangents, the nodes' velocity cotangents added to ``acc`` (one vector atomic a node, as ``g2p4``'s adjoint;
        :func:`grid_unpack_adj4` moves them into the velocity grid's gradient) and the particles' ``adj_x``, ``adj_F``
        ADDED to. The output cotangents are read, not zeroed (warp's adjoint of a store zeroes them).

        Forward (:func:`gathered`): ``v' = sum_i w_i v_i``, ``B = sum_i w_i v_i dpos_i^T``, ``C' = c B`` with
        ``c = 4 / dx^2`` (APIC, Jiang et al. 2015, with the quadratic B-spline's ``D^-1``), ``y = x_p + dt v'``,
        ``x' = clamp(y, lo, hi)``, ``F' = (I + dt C') F``. Backward, with ``g_y = adj_x'`` where ``lo <= y < hi``
        (as warp's adjoint of the clamp routes it) else 0:

            g_v = adj_v' + dt g_y,   G_B = c (adj_C' + dt adj_F' F^T),   adj_F += (I + dt C')^T adj_F',
            node i: adj_v_i = w_i (g_v + G_B dpos_i),   adj_x += g_y + sum_i (a_i dw_i/dx - w_i G_B^T v_i)
                    with a_i = v_i . (g_v + G_B dpos_i)."""
        p = wp.tid()
        x_p = x[p]
        F_p = F[p]
        base, fx, W = stencil(x_p, inv_dx, n_grid)
        off = run_offset(run, p, n_grid, grid_v.shape[0])
        v_new = vec3(T(0.0))
        B = mat33(T(0.0))
        for i in range(3):
            for j in range(3):
                for k in range(3):
                    w = W[i, 0] * W[j, 1] * W[k, 2]
                    dpos = (vec3(T(int(i)), T(int(j)), T(int(k))) - fx) / inv_dx
                    v_i = grid_v[base[0] + i + PAD + off, base[1] + j + PAD, base[2] + k + PAD]
                    v_new += w * v_i
                    B += w * wp.outer(v_i, dpos)
        c = T(4.0) * inv_dx * inv_dx
        y = x_p + dt * v_new
        gx = adj_x_out[p]
        g_y = vec3(T(0.0))
        for a in range(3):
            if y[a] >= lo and y[a] < hi:  # as warp's adjoint of clamp = min(max(lo, y), hi) routes it
                g_y[a] = gx[a]
        gF = adj_F_out[p]
        g_v = adj_v_out[p] + dt * g_y
        G_B = c * (adj_C_out[p] + dt * gF @ wp.transpose(F_p))
        G_Bt = wp.transpose(G_B)
        adj_F[p] = adj_F[p] + wp.transpose(wp.identity(3, dtype=T) + (dt * c) * B) @ gF
        dW = spline_slopes(fx)
        g_fx = vec3(T(0.0))
        for i in range(3):
            for j in range(3):
                for k in range(3):
                    w = W[i, 0] * W[j, 1] * W[k, 2]
                    dw = weight_slope(W, dW, i, j, k)
                    dpos = (vec3(T(int(i)), T(int(j)), T(int(k))) - fx) / inv_dx
                    I = base[0] + i + PAD + off
                    J = base[1] + j + PAD
                    K = base[2] + k + PAD
                    v_i = grid_v[I, J, K]
                    u = g_v + G_B @ dpos
                    wu = w * u
                    atomic_add4(acc, I, J, K, vec4(wu[0], wu[1], wu[2], T(0.0)))
                    g_fx += wp.dot(v_i, u) * dw - (w / inv_dx) * (G_Bt @ v_i)
        adj_x[p] = adj_x[p] + g_y + inv_dx * g_fx

    return types.SimpleNamespace(p2g=p2g, p2g_adj=p2g_adj, g2p4_adj=g2p4_adj, p2g_nodes=p2g_nodes, p2g_block=p2g_block,
                                 p2g_agg=p2g_agg, p2g4=p2g4,
                                 grid_update_unpack4=grid_update_unpack4, g2p4=g2p4, grid_unpack_adj4=grid_unpack_adj4,
                                 grid_update=grid_update, g2p=g2p, g2p_agg=g2p_agg,
                                 vec3=vec3, vec4=vec4, mat33=mat33, T=T, scatter=scatter, scatter_agg=scatter_agg,
                                 scatter4=scatter4,
                                 scatter_block=scatter_block, gather=gather, run_offset=run_offset,
                                 node_velocity=node_velocity)


KERNELS = {"float32": make_kernels(wp.float32), "float64": make_kernels(wp.float64)}
