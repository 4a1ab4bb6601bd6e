"""Slow pure-torch reference of one MLS-MPM step (for tests: compare values and VJPs with warp).

Same scheme, grid layout, wall conditions and clamp as :mod:`gca.sim.kernels`, written with dense
torch ops over the 27 stencil nodes so that torch autograd differentiates it.
"""

from __future__ import annotations

import itertools

import torch

from gca.sim.kernels import PAD, grid_size
from gca.sim.solver import SimConfig

_OFFSETS = torch.tensor(list(itertools.product(range(3), repeat=3)))  # [27, 3] stencil offsets


def stencil_ref(x: torch.Tensor, n_grid: int):
    """Stored node indices [N, 27, 3], weights [N, 27] and x_i - x_p [N, 27, 3] (m)."""
    dx = 1.0 / n_grid
    X = x / dx
    base = torch.floor(X - 0.5).long().clamp(-PAD, n_grid + PAD - 2)
    fx = X - base.to(x.dtype)
    W = torch.stack([0.5 * (1.5 - fx) ** 2, 0.75 - (fx - 1.0) ** 2, 0.5 * (fx - 0.5) ** 2], dim=1)
    offs = _OFFSETS.to(x.device)
    w = W[:, offs[:, 0], 0] * W[:, offs[:, 1], 1] * W[:, offs[:, 2], 2]
    dpos = (offs.to(x.dtype)[None] - fx[:, None]) * dx
    return base[:, None] + offs[None] + PAD, w, dpos


def _flat(idx: torch.Tensor, G: int) -> torch.Tensor:
    return (idx[..., 0] * G + idx[..., 1]) * G + idx[..., 2]


def _walls_ref(gv: torch.Tensor, cfg: SimConfig) -> torch.Tensor:
    """Wall condition on grid velocities [G, G, G, 3] (node I stored at I + PAD)."""
    G = gv.shape[0]
    I = torch.arange(G, device=gv.device) - PAD
    for axis in range(3):
        for sign, inside in ((-1.0, I < cfg.bound), (1.0, I > cfg.n_grid - cfg.bound)):
            shape = [1, 1, 1]
            shape[axis] = G
            mask = inside.view(shape)
            n = torch.zeros(3, dtype=gv.dtype, device=gv.device)
            n[axis] = sign
            gv = torch.where(mask[..., None], _wall_ref(gv, n, cfg), gv)
    return gv


def _wall_ref(v: torch.Tensor, n: torch.Tensor, cfg: SimConfig) -> torch.Tensor:
    if cfg.boundary == "sticky":
        return torch.zeros_like(v)
    vn = (v * n).sum(-1, keepdim=True)
    vt = v - vn * n
    if cfg.boundary == "slip":
        out = vt
    else:
        vt_norm = vt.norm(dim=-1, keepdim=True).clamp_min(1e-30)
        out = torch.where(vt_norm <= cfg.friction * vn, torch.zeros_like(vt),
                          vt * (1.0 - cfg.friction * vn / vt_norm))
    return torch.where(vn > 0, out, v)


def step_ref(cfg: SimConfig, x, v, C, F, tau, vol, mass):
    """Reference of :meth:`gca.sim.solver.MPMSolver.step` (same arguments and returns)."""
    G = grid_size(cfg.n_grid)
    dt, dx = cfg.dt, cfg.dx
    idx, w, dpos = stencil_ref(x, cfg.n_grid)
    flat = _flat(idx, G).reshape(-1)
    affine = -dt * vol[:, None, None] * 4.0 / dx**2 * tau + mass[:, None, None] * C
    contrib = w[..., None] * (mass[:, None, None] * v[:, None] + torch.einsum("pab,pnb->pna", affine, dpos))
    mv = torch.zeros(G**3, 3, dtype=x.dtype, device=x.device).index_add(0, flat, contrib.reshape(-1, 3))
    m = torch.zeros(G**3, dtype=x.dtype, device=x.device).index_add(0, flat, (w * mass[:, None]).reshape(-1))
    g = torch.tensor(cfg.gravity, dtype=x.dtype, device=x.device)
    gv = torch.where(m[:, None] > cfg.min_node_mass, mv / (m[:, None] + cfg.eps_mass) + dt * g, torch.zeros_like(mv))
    gv = _walls_ref(gv.reshape(G, G, G, 3), cfg).reshape(-1, 3)
    v_i = gv[flat].reshape(*w.shape, 3)
    v_new = (w[..., None] * v_i).sum(1)
    C_new = 4.0 / dx**2 * torch.einsum("pn,pna,pnb->pab", w, v_i, dpos)
    lo, hi = cfg.clamp_range
    x_new = (x + dt * v_new).clamp(lo, hi)
    eye = torch.eye(3, dtype=x.dtype, device=x.device)
    return x_new, v_new, C_new, (eye + dt * C_new) @ F
