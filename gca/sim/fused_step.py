"""One MLS-MPM step with an analytic elastic law evaluated inside P2G: three kernels, forward only.

The generic step (``gca.sim.solver``, ``gca.sim.frame``) evaluates the law, then transfers:

    law (SVD kernel, stress kernel, ~6 torch kernels for mu and lam)  ->  tau [N,3,3] in memory
    memsets of mv, m, v_grid  ->  P2G  ->  grid update  ->  G2P                         (~12 kernels)

PhysGaussian's warp solver launches ~6 per step and ran 1.4-1.5x faster than ours on the same job
(``benchmarks/NOTES.md``, session 13; issue 20 item 2). Here, for the analytic laws
(:class:`gca.laws.fused.AnalyticStress`: fixed corotated, neo-Hookean) and where no gradient is asked for
(ground-truth generation, evaluation rollouts, the forward pass of a graphed training frame):

    p2g_stress        tau_p = analytic_stress(F_p) (``gca.laws.fused``: the same warp functions as the laws'
                      kernels, SVD included) inside the particle's scatter (``kernels.scatter``)
    grid_update_zero  the grid update (``kernels.node_velocity``), then the node's mv and m set to zero for the
                      next step, so the step needs no memset
    g2p               unchanged

and for a purely elastic material (identity plasticity: the next step's stress needs no torch in between), a frame of
n steps in 2n + 1 kernels instead of 3n (:meth:`gca.sim.solver.MPMSolver.frame_fused`): ``p2g_stress`` once, then
per step the zeroing grid update and ``g2p_p2g`` (this step's G2P and the next step's stress and P2G in one particle
pass: x and F stored, v and C scattered at once), and one ``g2p`` at the end.

mu and lam are formed once per frame, not per step (:func:`gca.sim.frame.simulate_frame_trial`). The grid
buffers are the solver's own (:meth:`gca.sim.solver.MPMSolver._zeroed_grid`): zero when made and zero again
after every grid update. Same values as the generic step to rounding (tested on the CPU in float64 and
float32); gradients never go through here (the backward recompute of a frame takes the generic step).

The ``*4`` variants (``MPMSolver.vec4_p2g``) keep the grid's momentum and mass interleaved as one vec4 a node, so a
node's share is one 16-byte vector atomic on sm_90+ (``gca.sim.kernels.atomic_add4``); the same sums otherwise.
"""

# no `from __future__ import annotations`: warp resolves the kernels' annotations (closure types) eagerly
import functools
import types

import torch
import warp as wp

from gca.laws.fused import make_law_kernels
from gca.laws.svd_kernel import WARP_FLOATS
from gca.sim.kernels import KERNELS


@functools.cache
def make_fused_step_kernels(dtype: torch.dtype) -> types.SimpleNamespace:
    """Build ``p2g_stress``, ``grid_update_zero`` and ``g2p_p2g`` (and their block-summed, warp-aggregated and
    interleaved-grid ``*4`` variants) for ``torch.float32`` or ``torch.float64``."""
    T = WARP_FLOATS[dtype]
    k = KERNELS[T.__name__]
    law = make_law_kernels(dtype)
    vec3, mat33 = k.vec3, k.mat33
    scatter, scatter_agg, gather = k.scatter, k.scatter_agg, k.gather
    run_offset, node_velocity = k.run_offset, k.node_velocity
    analytic_stress = law.analytic_stress
    module = f"gca_sim_fused_step_{T.__name__}"
    agg_module = f"gca_sim_fused_step_agg_{T.__name__}"  # the warp-aggregated variants: compiled where launched

    def make_p2g_stress(agg: bool):
        """``p2g_stress``, or with ``agg`` its scatter's atomics aggregated per warp (``kernels.scatter_agg``)."""

        def p2g_stress(
            x: wp.array(dtype=vec3),
            v: wp.array(dtype=vec3),
            C: wp.array(dtype=mat33),
            F: wp.array(dtype=mat33),
            kind: int,
            mu: wp.array(dtype=T),
            lam: wp.array(dtype=T),
            per: int,
            j_min: T,
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
            tau = analytic_stress(kind, F[p], mu[p * per], lam[p * per], j_min)
            wp.static(scatter_agg if agg else scatter)(x[p], v[p], C[p], tau, vol[p], mass[p],
                                                       run_offset(run, p, n_grid, grid_m.shape[0]), dt, inv_dx,
                                                       n_grid, grid_mv, grid_m)

        p2g_stress.__name__ = p2g_stress.__qualname__ = "p2g_stress_agg" if agg else "p2g_stress"
        return wp.kernel(p2g_stress, module=agg_module if agg else module)

    @wp.kernel(module=module)
    def grid_update_zero(
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
        grid_mv[s0, s1, s2] = vec3(T(0.0))
        grid_m[s0, s1, s2] = T(0.0)

    def make_g2p_p2g(agg: bool):
        """``g2p_p2g``, or with ``agg`` its scatter's atomics aggregated per warp (``kernels.scatter_agg``)."""

        def g2p_p2g(
            x_src: wp.array(dtype=vec3),
            F_src: wp.array(dtype=mat33),
            run: wp.array(dtype=int),
            grid_v: wp.array3d(dtype=vec3),
            kind: int,
            mu: wp.array(dtype=T),
            lam: wp.array(dtype=T),
            per: int,
            j_min: T,
            vol: wp.array(dtype=T),
            mass: wp.array(dtype=T),
            dt: T,
            inv_dx: T,
            n_grid: int,
            lo: T,
            hi: T,
            x_dst: wp.array(dtype=vec3),
            F_dst: wp.array(dtype=mat33),
            grid_mv: wp.array3d(dtype=vec3),
            grid_m: wp.array3d(dtype=T),
        ):
            """G2P of one step and P2G of the next in one particle pass, for a purely elastic material (F_e =
            F_trial): the particle's new x and F are stored (``*_dst`` may be ``*_src``: each thread reads its particle
            before it writes it), its new v and C go straight into the scatter onto the zeroed mv and m."""
            p = wp.tid()
            off = run_offset(run, p, n_grid, grid_v.shape[0])
            x1, v1, C1, F1 = gather(x_src[p], F_src[p], off, grid_v, dt, inv_dx, n_grid, lo, hi)
            x_dst[p] = x1
            F_dst[p] = F1
            tau = analytic_stress(kind, F1, mu[p * per], lam[p * per], j_min)
            wp.static(scatter_agg if agg else scatter)(x1, v1, C1, tau, vol[p], mass[p], off, dt, inv_dx, n_grid,
                                                       grid_mv, grid_m)

        g2p_p2g.__name__ = g2p_p2g.__qualname__ = "g2p_p2g_agg" if agg else "g2p_p2g"
        return wp.kernel(g2p_p2g, module=agg_module if agg else module)

    p2g_stress, p2g_stress_agg = make_p2g_stress(False), make_p2g_stress(True)
    g2p_p2g, g2p_p2g_agg = make_g2p_p2g(False), make_g2p_p2g(True)

    scatter4, vec4 = k.scatter4, k.vec4
    v4_module = f"gca_sim_fused_step_v4_{T.__name__}"  # the interleaved (mv, m) grid's variants, compiled where
    # launched

    @wp.kernel(module=v4_module)
    def p2g_stress4(
        x: wp.array(dtype=vec3),
        v: wp.array(dtype=vec3),
        C: wp.array(dtype=mat33),
        F: wp.array(dtype=mat33),
        kind: int,
        mu: wp.array(dtype=T),
        lam: wp.array(dtype=T),
        per: int,
        j_min: T,
        vol: wp.array(dtype=T),
        mass: wp.array(dtype=T),
        run: wp.array(dtype=int),
        dt: T,
        inv_dx: T,
        n_grid: int,
        grid: wp.array3d(dtype=vec4),
    ):
        """``p2g_stress`` onto the interleaved grid (``kernels.scatter4``: mv in components 0-2, m in 3)."""
        p = wp.tid()
        tau = analytic_stress(kind, F[p], mu[p * per], lam[p * per], j_min)
        scatter4(x[p], v[p], C[p], tau, vol[p], mass[p], run_offset(run, p, n_grid, grid.shape[0]), dt, inv_dx, n_grid,
                 grid)

    @wp.kernel(module=v4_module)
    def grid_update_zero4(
        grid: wp.array3d(dtype=vec4),
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
        """``grid_update_zero`` of the interleaved grid: the node's velocity, then its (mv, m) set to zero."""
        s0, s1, s2 = wp.tid()
        g = grid[s0, s1, s2]
        grid_v[s0, s1, s2] = node_velocity(vec3(g[0], g[1], g[2]), g[3], s0, s1, s2, gravity, dt, eps, m_min, n_grid,
                                           bound, kind, mu_b)
        grid[s0, s1, s2] = vec4(T(0.0))

    @wp.kernel(module=v4_module)
    def g2p_p2g4(
        x_src: wp.array(dtype=vec3),
        F_src: wp.array(dtype=mat33),
        run: wp.array(dtype=int),
        grid_v: wp.array3d(dtype=vec3),
        kind: int,
        mu: wp.array(dtype=T),
        lam: wp.array(dtype=T),
        per: int,
        j_min: T,
        vol: wp.array(dtype=T),
        mass: wp.array(dtype=T),
        dt: T,
        inv_dx: T,
        n_grid: int,
        lo: T,
        hi: T,
        x_dst: wp.array(dtype=vec3),
        F_dst: wp.array(dtype=mat33),
        grid: wp.array3d(dtype=vec4),
    ):
        """``g2p_p2g`` whose scatter goes onto the interleaved grid (``kernels.scatter4``)."""
        p = wp.tid()
        off = run_offset(run, p, n_grid, grid_v.shape[0])
        x1, v1, C1, F1 = gather(x_src[p], F_src[p], off, grid_v, dt, inv_dx, n_grid, lo, hi)
        x_dst[p] = x1
        F_dst[p] = F1
        tau = analytic_stress(kind, F1, mu[p * per], lam[p * per], j_min)
        scatter4(x1, v1, C1, tau, vol[p], mass[p], off, dt, inv_dx, n_grid, grid)

    scatter_block = k.scatter_block
    block_module = f"gca_sim_fused_step_block_{T.__name__}"  # block-cooperative (tile) kernels, compiled apart

    @wp.kernel(module=block_module)
    def p2g_stress_block(
        x: wp.array(dtype=vec3),
        v: wp.array(dtype=vec3),
        C: wp.array(dtype=mat33),
        F: wp.array(dtype=mat33),
        kind: int,
        mu: wp.array(dtype=T),
        lam: wp.array(dtype=T),
        per: int,
        j_min: T,
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
        """``p2g_stress`` with the scatter summed per thread block first (``kernels.scatter_block``); launched by
        ``kernels.launch_blocks``."""
        blk, lane = wp.tid()
        n = x.shape[0]
        p = blk * wp.block_dim() + lane
        q = wp.min(p, n - 1)
        tau = analytic_stress(kind, F[q], mu[q * per], lam[q * per], j_min)
        scatter_block(p < n, x[q], v[q], C[q], tau, vol[q], mass[q], run_offset(run, q, n_grid, grid_m.shape[0]),
                      lane, dt, inv_dx, n_grid, grid_mv, grid_m, windows)

    @wp.kernel(module=block_module)
    def g2p_p2g_block(
        x_src: wp.array(dtype=vec3),
        F_src: wp.array(dtype=mat33),
        run: wp.array(dtype=int),
        grid_v: wp.array3d(dtype=vec3),
        kind: int,
        mu: wp.array(dtype=T),
        lam: wp.array(dtype=T),
        per: int,
        j_min: T,
        vol: wp.array(dtype=T),
        mass: wp.array(dtype=T),
        dt: T,
        inv_dx: T,
        n_grid: int,
        lo: T,
        hi: T,
        x_dst: wp.array(dtype=vec3),
        F_dst: wp.array(dtype=mat33),
        grid_mv: wp.array3d(dtype=vec3),
        grid_m: wp.array3d(dtype=T),
        windows: wp.array(dtype=int),
    ):
        """``g2p_p2g`` with the scatter summed per thread block first. A thread past the last particle reads the last
        one (maybe as its own thread rewrites it) and stores and scatters nothing."""
        blk, lane = wp.tid()
        n = x_src.shape[0]
        p = blk * wp.block_dim() + lane
        q = wp.min(p, n - 1)
        off = run_offset(run, q, n_grid, grid_v.shape[0])
        x1, v1, C1, F1 = gather(x_src[q], F_src[q], off, grid_v, dt, inv_dx, n_grid, lo, hi)
        if p < n:
            x_dst[p] = x1
            F_dst[p] = F1
        tau = analytic_stress(kind, F1, mu[q * per], lam[q * per], j_min)
        scatter_block(p < n, x1, v1, C1, tau, vol[q], mass[q], off, lane, dt, inv_dx, n_grid, grid_mv, grid_m, windows)

    return types.SimpleNamespace(p2g_stress=p2g_stress, grid_update_zero=grid_update_zero, g2p=k.g2p, g2p_p2g=g2p_p2g,
                                 p2g_stress_block=p2g_stress_block, g2p_p2g_block=g2p_p2g_block,
                                 p2g_stress_agg=p2g_stress_agg, g2p_p2g_agg=g2p_p2g_agg,
                                 p2g_stress4=p2g_stress4, grid_update_zero4=grid_update_zero4, g2p_p2g4=g2p_p2g4)
