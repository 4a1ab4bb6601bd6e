"""P2G and G2P kernel times by particle order and kernel layout (a script, not a test).

For each ``particles:n_grid`` size and each particle order of the same block of particles (``random``: uniform at
random, as ``bench_sim.block``; ``lattice``: a regular lattice in meshgrid order, as ``gca.assets.particles``
samples objects; ``cell``: the random particles sorted by grid cell; ``morton``: sorted by the Morton code of their
cell; ``ball64``: a lattice ball of ~64 particles per cell in meshgrid order (denser than the paper profile's ~12 per cell:
session 34); ``ball64_sub``: the same particles by sub-lattice, i.e. sorted by their lattice indices
mod 4 (each of the 64 sub-lattices holds one particle per cell) and in meshgrid order within one, so a warp's threads
fall in 32 different cells instead of 8; ``ball64_shuffle``: the same particles in a random order; ``ball12`` and
``ball12_sub``: the paper profile's real density, ~2.4 particles per cell edge, as sampled (C order) and by
sub-lattice (lattice index mod 4; session 34: slower than C order at this density, 56 vs 48 us on an H100);
``duck``: the duck's density (dx / h = 3.76 at n_grid 32: ~38 particles per occupied cell of the duck as sampled,
53 in a full cell; its training's P2G took 88 us a launch against the ball's 60, session 45) in C order,
times on one device, side by side in one run:

- ``p2g``: the per-particle scatter kernel (27 stencil nodes in one thread),
- ``p2g_nodes``: one thread per (particle, node) pair (an option, off since session 13),
- ``p2g_agg``: warp-aggregated atomics (``kernels.p2g_agg``: a warp's particles of one stencil base summed by
  shuffles, one atomic per node and base; an option, off until measured, session 45),
- ``p2g_v4``: the scatter onto the interleaved (mv, m) grid, one 16-byte vector atomic a node on sm_90+
  (``kernels.p2g4``; the fused analytic step's ``MPMSolver.vec4_p2g``, on CUDA by default since session 50),
  with ``p2g_v4_dev``: its grid's largest deviation from ``p2g``'s after one launch each from zero, relative to the
  largest momentum or mass,
- ``p2g_block``: the block-summed scatter (``kernels.scatter_block``; an option, off: slower, session 32),
  with the share of blocks that took the shared window,
- ``p2g_indirect``: the per-particle scatter reading its particle through an index array (thread t scatters particle
  order[t]) with the identity order (the indirection's own cost), and ``p2g_interleaved`` with the cell-interleaved
  order (:func:`interleaved`: each cell's first particle, cells in grid order, then each cell's second, ...), which a
  solver could compute from x0 instead of reordering the data,
- ``g2p``: the per-particle gather, and its adjoint (``g2p_adj``: warp's, scattering the grid's velocity gradient
  with atomics; ``g2p_agg_adj``: ``kernels.g2p_agg``'s, that scatter aggregated per warp like ``p2g_agg``;
  ``g2p4_adj``: ``kernels.g2p4``'s, one vector atomic a node into an interleaved accumulator, plus its unpacking
  ``grid_unpack_adj4``: ``MPMSolver.vec4_g2p_adj``, on CUDA by default since session 51),

as the best of ``--repeats`` averages over ``--iters`` launches (CUDA events around the loop).

Usage::

    python benchmarks/bench_p2g.py --device cuda --sizes 30000:32 100000:64 --json out.json
"""

from __future__ import annotations

import argparse
import functools
import json

import torch
import warp as wp

from gca.efficiency import best_time_us
from gca.sim.kernels import BLOCK, KERNELS, PAD, grid_size, launch_blocks

ORDERS = ("random", "lattice", "cell", "morton", "ball64", "ball64_sub", "ball64_shuffle", "ball12", "ball12_sub",
          "duck")
DUCK_PER_EDGE = 0.03125 / 0.008308  # the duck's dx / h at the paper profile (n_grid 32, spacing 0.008308 m)


def _cells(x: torch.Tensor, n_grid: int) -> torch.Tensor:
    return (x * n_grid).floor().long().clamp(0, n_grid - 1)


def _morton(c: torch.Tensor) -> torch.Tensor:
    """Interleaved bits of 3 cell indices < 1024 (30-bit Morton code)."""
    code = torch.zeros(c.shape[0], dtype=torch.long, device=c.device)
    for bit in range(10):
        for axis in range(3):
            code |= ((c[:, axis] >> bit) & 1) << (3 * bit + axis)
    return code


def lattice_ball(n: int, n_grid: int, per_edge: float = 4.0) -> tuple[torch.Tensor, torch.Tensor]:
    """A ball of ~n particles on a lattice of spacing dx / per_edge (4: ~64 per cell; the paper profile's ball has
    ~2.4, ~12 per cell: ``gca.assets.particles`` at target_count 30k, n_grid 32), centred at the origin, in meshgrid
    order: (x [N, 3] m, float64; lattice indices [N, 3])."""
    s = 1.0 / (per_edge * n_grid)
    r = (3 * n / (4 * torch.pi)) ** (1 / 3) * s  # the radius giving ~n particles
    axis = torch.arange(-r, r + 1e-9, s, dtype=torch.float64)
    x = torch.stack(torch.meshgrid(axis, axis, axis, indexing="ij"), -1).reshape(-1, 3)
    idx = torch.stack(torch.meshgrid(*[torch.arange(len(axis))] * 3, indexing="ij"), -1).reshape(-1, 3)
    inside = (x ** 2).sum(1) <= r * r
    return x[inside], idx[inside]


def particles(n: int, n_grid: int, order: str, device, seed: int = 0) -> torch.Tensor:
    """n positions [n, 3] in a centred cube of ~8 particles per cell, in the given order."""
    side = min((n / 8) ** (1 / 3), n_grid - 8) / n_grid
    lo = 0.5 - side / 2
    if order.startswith("ball12") or order == "duck":  # the paper profile's ball (C order as sampled, or the
        # sampler's sub-lattice order), or a ball at the duck's density
        per_edge = DUCK_PER_EDGE if order == "duck" else 2.4
        h = 1.0 / (per_edge * n_grid)
        x, _ = lattice_ball(n, n_grid, per_edge)
        x = x + 0.5 + 0.5 * h  # cell centres (i + 1/2) h, as the sampler's lattice
        if order == "ball12_sub":  # stable: C order within each sub-lattice (lattice index mod 4)
            idx = torch.floor(x / h).long()
            sub = ((idx[:, 0] % 4) * 4 + idx[:, 1] % 4) * 4 + idx[:, 2] % 4
            x = x[torch.sort(sub, stable=True).indices]
        return x.to(device=device, dtype=torch.float32).contiguous()
    if order.startswith("ball64"):
        x, idx = lattice_ball(n, n_grid)
        if order == "ball64_sub":  # stable: meshgrid order within each sub-lattice
            sub = ((idx[:, 0] % 4) * 4 + idx[:, 1] % 4) * 4 + idx[:, 2] % 4
            x = x[torch.sort(sub, stable=True).indices]
        elif order == "ball64_shuffle":
            x = x[torch.randperm(len(x), generator=torch.Generator().manual_seed(seed))]
        return (x + 0.5).to(device=device, dtype=torch.float32).contiguous()
    if order == "lattice":
        k = round(n ** (1 / 3))
        axis = lo + (torch.arange(k, dtype=torch.float64) + 0.5) * side / k
        x = torch.stack(torch.meshgrid(axis, axis, axis, indexing="ij"), -1).reshape(-1, 3)
    else:
        g = torch.Generator().manual_seed(seed)
        x = lo + side * torch.rand(n, 3, generator=g, dtype=torch.float64)
        if order == "cell":
            c = _cells(x, n_grid)
            x = x[torch.argsort((c[:, 0] * n_grid + c[:, 1]) * n_grid + c[:, 2])]
        elif order == "morton":
            x = x[torch.argsort(_morton(_cells(x, n_grid)))]
    return x.to(device=device, dtype=torch.float32).contiguous()


def interleaved(x: torch.Tensor, n_grid: int) -> torch.Tensor:
    """A permutation [N] (int64) of particles ``x`` [N, 3]: the first particle of every cell (cells in grid order),
    then the second of every cell, and so on, each cell's particles in their given order; 32 consecutive threads then
    fall in up to 32 cells however dense the cells are."""
    c = _cells(x.double(), n_grid)
    key = (c[:, 0] * n_grid + c[:, 1]) * n_grid + c[:, 2]
    by_cell = torch.sort(key, stable=True).indices  # grouped by cell
    k = key[by_cell]
    rank = torch.arange(len(k), device=k.device) - torch.searchsorted(k, k)  # rank of each particle within its cell
    return by_cell[torch.sort(rank * n_grid ** 3 + k, stable=True).indices]


@functools.cache
def _indirect_kernel(dtype: str = "float32"):
    """P2G through an index array: thread t scatters particle order[t] (``kernels.scatter``, forward only)."""
    k = KERNELS[dtype]
    T, vec3, mat33 = k.T, k.vec3, k.mat33

    def p2g_indirect(order, x, v, C, tau, vol, mass, run, dt, inv_dx, n_grid, grid_mv, grid_m):
        p = order[wp.tid()]
        k.scatter(x[p], v[p], C[p], tau[p], vol[p], mass[p], k.run_offset(run, p, n_grid, grid_m.shape[0]), dt,
                  inv_dx, n_grid, grid_mv, grid_m)

    # the types as objects: this module's annotations are strings (``from __future__ import annotations``)
    p2g_indirect.__annotations__ = dict(
        order=wp.array(dtype=int), x=wp.array(dtype=vec3), v=wp.array(dtype=vec3), C=wp.array(dtype=mat33),
        tau=wp.array(dtype=mat33), vol=wp.array(dtype=T), mass=wp.array(dtype=T), run=wp.array(dtype=int), dt=T,
        inv_dx=T, n_grid=int, grid_mv=wp.array3d(dtype=vec3), grid_m=wp.array3d(dtype=T))
    return wp.kernel(p2g_indirect)


def measure(n: int, n_grid: int, order: str, device, iters: int, repeats: int, block_dims=()) -> dict:
    k = KERNELS["float32"]
    wd = wp.device_from_torch(device)
    x = particles(n, n_grid, order, device)
    n = x.shape[0]
    g = torch.Generator().manual_seed(1)
    to = dict(dtype=torch.float32, device=device)
    v = torch.randn(n, 3, generator=g).to(**to)
    C = torch.randn(n, 3, 3, generator=g).to(**to)
    tau = (1e3 * torch.randn(n, 3, 3, generator=g)).to(**to)
    vol = torch.full((n,), 1e-6, **to)
    mass = vol * 1e3
    G = grid_size(n_grid)
    mv = wp.zeros((G, G, G), dtype=k.vec3, device=wd)
    m = wp.zeros((G, G, G), dtype=k.T, device=wd)
    wx, wv = wp.from_torch(x, dtype=k.vec3), wp.from_torch(v, dtype=k.vec3)
    wC, wtau = wp.from_torch(C, dtype=k.mat33), wp.from_torch(tau, dtype=k.mat33)
    wvol, wmass = wp.from_torch(vol), wp.from_torch(mass)
    run = wp.zeros(n, dtype=wp.int32, device=wd)  # one run
    args = [wx, wv, wC, wtau, wvol, wmass, run, 1e-4, float(n_grid), n_grid, mv, m]
    F = torch.eye(3, **to).expand(n, 3, 3).contiguous()
    outs = [wp.zeros(n, dtype=t, device=wd) for t in (k.vec3, k.vec3, k.mat33, k.mat33)]
    g2p_args = [wx, wp.from_torch(F, dtype=k.mat33), run, mv, 1e-4, float(n_grid), n_grid, 0.0, 1.0, *outs]
    row = {"particles": n, "n_grid": n_grid, "order": order}
    row["p2g_us"] = best_time_us(lambda: wp.launch(k.p2g, dim=n, inputs=args, device=wd), device, iters, repeats)
    for bd in block_dims:  # the same kernels launched with other thread-block sizes (warp's default: 256)
        row[f"p2g_bd{bd}_us"] = best_time_us(lambda: wp.launch(k.p2g, dim=n, inputs=args, device=wd, block_dim=bd),
                                             device, iters, repeats)
    indirect = _indirect_kernel()
    for name, order_t in (("p2g_indirect_us", torch.arange(n, device=device)), ("p2g_interleaved_us",
                                                                              interleaved(x, n_grid))):
        w_order = wp.from_torch(order_t.to(torch.int32).contiguous())
        row[name] = best_time_us(lambda: wp.launch(indirect, dim=n, inputs=[w_order, *args], device=wd), device,
                                 iters, repeats)
    row["p2g_nodes_us"] = best_time_us(lambda: wp.launch(k.p2g_nodes, dim=27 * n, inputs=args, device=wd), device,
                                       iters, repeats)
    row["p2g_agg_us"] = best_time_us(lambda: wp.launch(k.p2g_agg, dim=n, inputs=args, device=wd), device, iters,
                                     repeats)
    mvm = wp.zeros((G, G, G), dtype=k.vec4, device=wd)
    args4 = [*args[:-2], mvm]
    mv.zero_()
    m.zero_()
    wp.launch(k.p2g, dim=n, inputs=args, device=wd)
    wp.launch(k.p2g4, dim=n, inputs=args4, device=wd)
    t_mv, t_m, t_mvm = wp.to_torch(mv), wp.to_torch(m), wp.to_torch(mvm)
    row["p2g_v4_dev"] = max(float((t_mvm[..., :3] - t_mv).abs().max() / t_mv.abs().max()),
                            float((t_mvm[..., 3] - t_m).abs().max() / t_m.abs().max()))
    row["p2g_v4_us"] = best_time_us(lambda: wp.launch(k.p2g4, dim=n, inputs=args4, device=wd), device, iters, repeats)
    windows = wp.zeros(1, dtype=int, device=wd)
    row["p2g_block_us"] = best_time_us(lambda: launch_blocks(k.p2g_block, n, [*args, windows], wd), device, iters,
                                       repeats)
    launches = (iters * (max(1, repeats) + 1)) * -(-n // BLOCK)  # best_time_us's rounds
    row["window_share"] = float(windows.numpy()[0]) / launches if wd.is_cuda else float("nan")
    row["g2p_us"] = best_time_us(lambda: wp.launch(k.g2p, dim=n, inputs=g2p_args, device=wd), device, iters, repeats)
    adj = [wp.zeros_like(a) if isinstance(a, wp.array) else None for a in g2p_args]
    row["g2p_adj_us"] = best_time_us(lambda: wp.launch(k.g2p, dim=n, inputs=g2p_args, adj_inputs=adj, adjoint=True,
                                                       device=wd), device, iters, repeats)
    acc = wp.zeros((G, G, G), dtype=k.vec4, device=wd)
    args4 = [*g2p_args[:4], acc, *g2p_args[4:]]
    adj4 = [wp.zeros_like(a) if isinstance(a, wp.array) and a is not acc else None for a in args4]

    def g2p4_adj():
        wp.launch(k.g2p4, dim=n, inputs=args4, adj_inputs=adj4, adjoint=True, device=wd)
        wp.launch(k.grid_unpack_adj4, dim=(G, G, G), inputs=[acc, adj4[3]], device=wd)

    row["g2p4_adj_us"] = best_time_us(g2p4_adj, device, iters, repeats)
    row["g2p_agg_adj_us"] = best_time_us(lambda: wp.launch(k.g2p_agg, dim=n, inputs=g2p_args, adj_inputs=adj,
                                                           adjoint=True, device=wd), device, iters, repeats)
    for bd in block_dims:
        row[f"g2p_bd{bd}_us"] = best_time_us(lambda: wp.launch(k.g2p, dim=n, inputs=g2p_args, device=wd, block_dim=bd),
                                             device, iters, repeats)
        row[f"g2p_adj_bd{bd}_us"] = best_time_us(lambda: wp.launch(k.g2p, dim=n, inputs=g2p_args, adj_inputs=adj,
                                                                   adjoint=True, device=wd, block_dim=bd),
                                                 device, iters, repeats)
    return row


def main(argv=None) -> list[dict]:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    p.add_argument("--sizes", nargs="+", default=["30000:32", "100000:64"])
    p.add_argument("--orders", nargs="+", default=list(ORDERS), choices=ORDERS)
    p.add_argument("--iters", type=int, default=200)
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--json", default=None)
    p.add_argument("--block-dims", nargs="*", type=int, default=[],
                   help="also time p2g, g2p and G2P's adjoint launched with these thread-block sizes")
    a = p.parse_args(argv)
    wp.config.quiet = True
    wp.init()
    device = torch.device(a.device)
    if device.type == "cuda" and device.index is None:  # warp needs an explicit ordinal
        device = torch.device("cuda", torch.cuda.current_device())
    rows = []
    print("| particles | grid | order | p2g us | p2g_v4 us (dev) | p2g_agg us | p2g indirect us | p2g interleaved us | "
          "p2g_nodes us | "
          "p2g_block us (window share) | g2p us | g2p adjoint us | g2p_agg adjoint us | g2p4 adjoint + unpack us |\n"
          "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |")
    for spec in a.sizes:
        n, n_grid = (int(s) for s in spec.split(":"))
        for order in a.orders:
            r = measure(n, n_grid, order, device, a.iters, a.repeats, a.block_dims)
            rows.append(r)
            print(f"| {r['particles']} | {n_grid}^3 | {order} | {r['p2g_us']:.1f} | {r['p2g_v4_us']:.1f} "
                  f"({r['p2g_v4_dev']:.1e}) | {r['p2g_agg_us']:.1f} | "
                  f"{r['p2g_indirect_us']:.1f} | "
                  f"{r['p2g_interleaved_us']:.1f} | {r['p2g_nodes_us']:.1f} | "
                  f"{r['p2g_block_us']:.1f} ({r['window_share']:.2f}) | {r['g2p_us']:.1f} | {r['g2p_adj_us']:.1f} | "
                  f"{r['g2p_agg_adj_us']:.1f} | {r['g2p4_adj_us']:.1f} |",
                  flush=True)
            if a.block_dims:
                print("|   block dims " + ", ".join(f"{bd}: p2g {r[f'p2g_bd{bd}_us']:.1f} g2p {r[f'g2p_bd{bd}_us']:.1f} "
                                                  f"adj {r[f'g2p_adj_bd{bd}_us']:.1f}" for bd in a.block_dims) + " |",
                      flush=True)
    if a.json:
        with open(a.json, "w") as f:
            json.dump({"device": torch.cuda.get_device_name(device) if device.type == "cuda" else "cpu",
                       "rows": rows}, f, indent=2)
    return rows


if __name__ == "__main__":
    main()
