"""Warp-aggregated atomics: the forward P2G (``gca.sim.kernels.p2g_agg``, ``MPMSolver.agg_p2g``) and G2P's adjoint
(``g2p_agg``, ``MPMSolver.agg_g2p``).

On a CPU every thread is its own peer, so the kernels are ``p2g``'s and ``g2p``'s (bitwise). The CUDA part
(``__match_any_sync``, the shuffle tree of ``_peer_tree``) is checked three ways here: the tree's algorithm lane by
lane in Python (a model of the snippet, with a broken variant as the negative control), its compile for sm_90 (warp's
own NVRTC, no GPU needed), and, where CUDA is present, the kernels against the plain ones on dense lattices, shuffled
peers, one cell and two runs (many peers per warp).
"""

import numpy as np
import pytest
import torch
import warp as wp

from gca.laws.base import Material
from gca.laws.elastic import CorotatedElasticity
from gca.laws.plastic import IdentityPlasticity
from gca.sim.frame import simulate_frame
from gca.sim.kernels import KERNELS, grid_size
from gca.sim.solver import MPMSolver, SimConfig


def _state(n, seed, lo=0.1, hi=0.9, dtype=torch.float64, device="cpu"):
    g = torch.Generator().manual_seed(seed)
    to = dict(dtype=dtype)
    x = lo + (hi - lo) * torch.rand(n, 3, generator=g, **to)
    v = torch.randn(n, 3, generator=g, **to)
    C = 0.5 * torch.randn(n, 3, 3, generator=g, **to)
    F = torch.eye(3, **to) + 0.05 * torch.randn(n, 3, 3, generator=g, **to)
    tau = 10.0 * torch.randn(n, 3, 3, generator=g, **to)
    vol = torch.full((n,), 1e-4, **to)
    mass = 1e3 * vol
    return [t.to(device) for t in (x, v, C, F, tau, vol, mass)]


def _lattice_ball(per_edge: float, n_grid: int, n: int, dtype, device) -> torch.Tensor:
    """A ball of ~n lattice points at spacing dx / per_edge in C order (as ``gca.assets.particles`` samples)."""
    h = 1.0 / (per_edge * n_grid)
    r = (3 * n / (4 * np.pi)) ** (1 / 3) * h
    axis = torch.arange(-r, r + 1e-12, h, dtype=torch.float64)
    x = torch.stack(torch.meshgrid(axis, axis, axis, indexing="ij"), -1).reshape(-1, 3)
    return (x[(x ** 2).sum(1) <= r * r] + 0.5 + 0.5 * h).to(dtype=dtype, device=device).contiguous()


@pytest.mark.parametrize("switch, kernel", [("agg_p2g", "p2g_agg"), ("agg_g2p", "g2p_agg")])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_the_aggregated_kernels_equal_the_plain_ones_off_cuda(dtype, switch, kernel):
    # each CPU thread is its own peer and leader: the same terms in the same order, values and gradients bitwise
    cfg = SimConfig(n_grid=16, dt=1e-3, bound=2, boundary="friction", friction=0.5, dtype=str(dtype)[6:], max_refine=1)
    x, v, C, F, tau, vol, mass = _state(300, seed=6, lo=0.02, hi=0.98, dtype=dtype)
    calls = []
    real = wp.launch

    def spy(k, *a, **kw):
        calls.append((k.key.rsplit("__", 1)[-1], bool(kw.get("adjoint"))))
        return real(k, *a, **kw)

    outs = {}
    for agg in (True, False):
        solver = MPMSolver(cfg)
        setattr(solver, switch, agg)
        inputs = [t.clone().requires_grad_() for t in (x, v, C, F, tau)]
        calls.clear()
        wp.launch = spy
        try:
            step = solver.step(*inputs, vol, mass)
            outs[agg] = (*step, *torch.autograd.grad(step, inputs, [torch.ones_like(o) for o in step]))
        finally:
            wp.launch = real
        taken = {adjoint for name, adjoint in calls if name == kernel}
        assert taken == ({False, True} if kernel == "g2p_agg" else {False}) if agg else not taken  # the switch
        # takes the kernel (a switch that did nothing would fail); P2G's adjoint stays p2g's
    assert float(outs[True][0].detach().sub(x).abs().max()) > 0  # the particles moved
    for a, b in zip(outs[True], outs[False]):
        assert torch.equal(a, b)


@pytest.mark.parametrize("frames", [True, False], ids=["one_pass_frame", "fused_steps"])
def test_the_fused_analytic_step_takes_the_aggregated_scatter(frames):
    # agg_p2g also routes the fused step's kernels (p2g_stress_agg, g2p_p2g_agg): off CUDA bitwise the plain fused
    # frame, and within rounding of the generic step (law, then transfers)
    cfg = SimConfig(n_grid=16, dt=5e-4, bound=2, boundary="friction", friction=0.3, dtype="float64", max_refine=1)
    x, v, C, F, _, vol, mass = _state(400, seed=11, lo=0.05, hi=0.95)
    material = Material(CorotatedElasticity(1e5, 0.3, learnable=False), IdentityPlasticity(), 1000.0).double()
    calls, real, results = [], wp.launch, {}
    for path in ("agg", "fused", "generic"):
        solver = MPMSolver(cfg)
        solver.fuse_frames, solver.agg_p2g, solver.fuse_analytic = frames, path == "agg", path != "generic"
        calls.clear()
        wp.launch = lambda k, *a, **kw: (calls.append(k.key.rsplit("__", 1)[-1]), real(k, *a, **kw))[1]
        try:
            with torch.no_grad():
                results[path] = simulate_frame(solver, material, 4, x, v, C, F, vol, mass)
        finally:
            wp.launch = real
        took = {c for c in calls if c.endswith("_agg")}
        assert took == ({"p2g_stress_agg", "g2p_p2g_agg"} if frames else {"p2g_stress_agg"}) if path == "agg" \
            else not took
    assert float((results["agg"][0] - x).abs().max()) > 1e-6
    for a, b, c in zip(results["agg"], results["fused"], results["generic"]):
        assert torch.equal(a, b)
        assert float((a - c).abs().max()) <= 1e-12 * float(c.abs().max())


def test_agg_p2g_takes_the_runs_grids():
    # two runs in one launch: the peers' key is the base node's stacked index, so equal bases of two runs never
    # merge; off CUDA bitwise the per-particle kernel's grid, and each run's mass stays on its own grid
    k = KERNELS["float64"]
    a = _state(40, seed=7)
    b = _state(25, seed=8, lo=0.3, hi=0.6)
    x, v, C, _, tau, vol, mass = [torch.cat([sa, sb]) for sa, sb in zip(a, b)]
    run = torch.cat([torch.zeros(40, dtype=torch.int32), torch.ones(25, dtype=torch.int32)])
    G = grid_size(12)
    grids = {}
    for kernel in (k.p2g, k.p2g_agg):
        mv, m = wp.zeros((2 * G, G, G), dtype=k.vec3), wp.zeros((2 * G, G, G), dtype=k.T)
        wp.launch(kernel, dim=65, inputs=[wp.from_torch(x, dtype=k.vec3), wp.from_torch(v, dtype=k.vec3),
                                          wp.from_torch(C, dtype=k.mat33), wp.from_torch(tau, dtype=k.mat33),
                                          wp.from_torch(vol), wp.from_torch(mass), wp.from_torch(run), 1e-3, 12.0, 12,
                                          mv, m])
        grids[kernel.key.rsplit("__", 1)[-1]] = (mv.numpy(), m.numpy())
    assert np.array_equal(grids["p2g"][0], grids["p2g_agg"][0]) and np.array_equal(grids["p2g"][1], grids["p2g_agg"][1])
    m = grids["p2g_agg"][1]
    assert np.isclose(m[:G].sum(), float(mass[:40].sum())) and np.isclose(m[G:].sum(), float(mass[40:].sum()))


@pytest.mark.parametrize("switch", ["agg_p2g", "agg_g2p"])
def test_aggregation_is_off_by_default_and_none_means_cuda_only(switch):
    solver = MPMSolver(SimConfig(n_grid=8, dt=1e-3, dtype="float64", max_refine=1))
    resolved = switch.replace("agg_", "aggs_")
    assert getattr(solver, switch) is False and not getattr(solver, resolved)  # not measured on a GPU yet (session 45)
    setattr(solver, switch, None)
    assert not getattr(solver, resolved)  # a CPU solver
    setattr(solver, switch, True)
    assert getattr(solver, resolved)
    assert getattr(solver.refined(2), switch) is True  # a refined solver follows the switch


# -- the shuffle tree of _PEER_SUM4, lane by lane ------------------------------------------------------------------

def _popc(u: int) -> int:
    return bin(u & 0xFFFFFFFF).count("1")


def _ffs(u: int) -> int:
    u &= 0xFFFFFFFF
    return (u & -u).bit_length()  # 1-based index of the lowest set bit, 0 for none


def _peer_sum_model(keys: list[int], values: list[float], broken: bool = False) -> list[float]:
    """``_PEER_SUM4`` for one warp (one component), each intrinsic as CUDA defines it: lane l's peers are the lanes
    with its key (``__match_any_sync``); every round all lanes read their source's sum before any adds
    (``__shfl_sync``), then leave by their rank's low bit (``__ballot_sync``). ``broken`` skips the lanes' leaving
    (the negative control: lanes then add sums already added)."""
    n = len(keys)
    peers = [sum(1 << j for j in range(n) if keys[j] == keys[lane]) for lane in range(n)]
    rest = [peers[lane] & ~((2 << lane) - 1) & 0xFFFFFFFF for lane in range(n)]
    rank = [_popc(peers[lane] & ((1 << lane) - 1)) for lane in range(n)]
    s = list(values)
    while any(rest[lane] != 0 for lane in range(n)):  # __any_sync over a lane's peers: the same for all of them
        nxt = [_ffs(rest[lane]) for lane in range(n)]
        t = [s[nxt[lane] - 1] if nxt[lane] else s[lane] for lane in range(n)]
        s = [s[lane] + t[lane] if nxt[lane] else s[lane] for lane in range(n)]
        done = sum(1 << lane for lane in range(n) if rank[lane] & 1)
        if not broken:
            rest = [r & ~done for r in rest]
        rank = [r >> 1 for r in rank]
        if broken and all(r == 0 for r in rank):
            break
    return s


def _leaders(keys: list[int]) -> list[int]:
    return [lane for lane in range(len(keys)) if keys.index(keys[lane]) == lane]  # the lowest lane of each key


@pytest.mark.parametrize("case", ["one", "singletons", "pairs", "lattice", "scattered", "partial"])
def test_peer_sum_tree_gives_each_leader_its_peers_sum(case):
    rng = np.random.default_rng(len(case))
    keys = {"one": [5] * 32, "singletons": list(range(32)), "pairs": [i // 2 for i in range(32)],
            "lattice": [i // 3 + (i % 7 == 0) for i in range(32)],  # runs of ~3, some split off, as C order gives
            "scattered": list(rng.integers(0, 5, 32)), "partial": list(rng.integers(0, 4, 19))}[case]
    values = list(rng.integers(1, 1000, len(keys)).astype(float))  # integers: sums exact in any order
    out = _peer_sum_model(keys, values)
    for lead in _leaders(keys):
        assert out[lead] == sum(v for k, v in zip(keys, values) if k == keys[lead])


def test_peer_sum_tree_negative_control():
    keys = [3] * 32
    values = [float(i + 1) for i in range(32)]
    assert _peer_sum_model(keys, values)[0] == sum(values)
    assert _peer_sum_model(keys, values, broken=True)[0] != sum(values)


@pytest.mark.parametrize("module", ["gca_sim_mpm_agg_float32", "gca_sim_mpm_agg_float64"])  # their own modules
def test_agg_p2g_compiles_for_sm_90(tmp_path, module):
    # the CUDA snippets (match, shuffles, ballots) through warp's own NVRTC for the H100/H200's arch, on any machine
    # (the PyPI wheel carries NVRTC; a snippet that does not compile raises "CUDA kernel build failed"); float64 is
    # what the CUDA tests below run
    paths = wp.compile_aot_module(module, arch=90, module_dir=str(tmp_path))
    assert paths and all(p.exists() for p in paths)
    src = "".join(p.read_text() for p in tmp_path.glob("*.cu"))
    assert "__match_any_sync" in src and "__shfl_sync" in src and "p2g_agg" in src and "g2p_agg" in src
    # (the fused step's *_agg kernels call the same kernels.scatter_agg as p2g_agg: compiled here through it)
    adj = src[src.index("void adj_make_kernels__locals__node_read_agg"):]  # the G2P adjoint's aggregated scatter
    assert "__shfl_sync" in adj[:adj.index("}\n\n")]


CUDA_CASES = ["ball", "duck", "ball64", "duck_shuffled", "one_cell", "two_runs"]


def _cuda_case(case: str):
    """Particles on CUDA (float64) for a peer pattern: C-order lattice balls at the paper ball's density (~2.3 lanes of
    a warp per stencil base), the duck's (~4) and ~64 per cell; the duck's shuffled (a base's lanes not adjacent);
    1000 particles inside one cell (all 32 lanes on one base: five rounds; a partial last warp); the duck's lattice
    twice, interleaved as runs 0 and 1 (the same base in one warp for two runs: keys must keep them apart).
    Returns (x [N, 3], run [N] int32, n_runs)."""
    wp.init()  # wp.from_torch reads warp's runtime, which a launch would start only later (session 46's first call)
    if case == "one_cell":
        g = torch.Generator().manual_seed(13)
        x = (15.6 + 0.8 * torch.rand(1000, 3, generator=g, dtype=torch.float64)) / 32  # cell 15, away from its edges
        return x.cuda(), torch.zeros(1000, dtype=torch.int32, device="cuda"), 1
    per_edge = {"ball": 2.4, "ball64": 4.0}.get(case, 3.76)
    x = _lattice_ball(per_edge, 32, 30000, torch.float64, "cuda")
    if case == "duck_shuffled":
        x = x[torch.randperm(len(x), generator=torch.Generator().manual_seed(14)).cuda()]
    if case == "two_runs":
        x = torch.stack([x, x], 1).reshape(-1, 3)
        run = torch.arange(len(x), device="cuda", dtype=torch.int32) % 2
        return x.contiguous(), run, 2
    return x, torch.zeros(len(x), dtype=torch.int32, device="cuda"), 1


@pytest.mark.gpu
@pytest.mark.parametrize("case", CUDA_CASES)
def test_agg_p2g_equals_p2g_on_cuda(case):
    # float64 grids equal to rounding (the sums reordered), each run's mass on its own grid
    k = KERNELS["float64"]
    x, run, n_runs = _cuda_case(case)
    n = x.shape[0]
    _, v, C, _, tau, vol, mass = _state(n, seed=3, device="cuda")
    G = grid_size(32)
    grids = []
    for kernel in (k.p2g, k.p2g_agg):
        mv = torch.zeros(n_runs * G, G, G, 3, dtype=torch.float64, device="cuda")
        m = torch.zeros(n_runs * G, G, G, dtype=torch.float64, device="cuda")
        wp.launch(kernel, dim=n, inputs=[wp.from_torch(x, dtype=k.vec3), wp.from_torch(v, dtype=k.vec3),
                                         wp.from_torch(C, dtype=k.mat33), wp.from_torch(tau, dtype=k.mat33),
                                         wp.from_torch(vol), wp.from_torch(mass), wp.from_torch(run), 1e-4, 32.0, 32,
                                         wp.from_torch(mv, dtype=k.vec3), wp.from_torch(m)],
                  device=wp.device_from_torch(x.device))
        grids.append((mv, m))
    (mv0, m0), (mv1, m1) = grids
    assert float(m0.sum()) > 0
    assert torch.allclose(m1, m0, rtol=1e-12, atol=1e-12 * float(m0.max()))
    assert torch.allclose(mv1, mv0, rtol=1e-12, atol=1e-12 * float(mv0.abs().max()))
    for r in range(n_runs):
        assert abs(float(m1[r * G:(r + 1) * G].sum()) - float(mass[run == r].sum())) <= 1e-12 * float(mass.sum())


@pytest.mark.gpu
@pytest.mark.parametrize("case", CUDA_CASES)
def test_agg_g2p_adjoint_equals_g2p_s_on_cuda(case):
    # the grid's cotangent (the aggregated scatter) and the particles' (unchanged) match warp's own adjoint
    k = KERNELS["float64"]
    x, run_t, n_runs = _cuda_case(case)
    n = x.shape[0]
    _, _, _, F, _, _, _ = _state(n, seed=4, device="cuda")
    g = torch.Generator().manual_seed(5)
    G = grid_size(32)
    gv = torch.randn(n_runs * G, G, G, 3, generator=g, dtype=torch.float64).cuda()
    cots = [torch.randn(n, *s, generator=g, dtype=torch.float64).cuda() for s in ((3,), (3,), (3, 3), (3, 3))]
    wd = wp.device_from_torch(x.device)
    run = wp.from_torch(run_t)
    results = []
    for kernel in (k.g2p, k.g2p_agg):
        adj_x, adj_F, adj_gv = torch.zeros_like(x), torch.zeros_like(F), torch.zeros_like(gv)
        ins = [wp.from_torch(x, dtype=k.vec3), wp.from_torch(F, dtype=k.mat33), run, wp.from_torch(gv, dtype=k.vec3),
               1e-4, 32.0, 32, 0.0, 1.0]
        outs = [wp.zeros(n, dtype=t, device=wd) for t in (k.vec3, k.vec3, k.mat33, k.mat33)]
        adj_ins = [wp.from_torch(adj_x, dtype=k.vec3), wp.from_torch(adj_F, dtype=k.mat33), wp.zeros_like(run),
                   wp.from_torch(adj_gv, dtype=k.vec3), 0.0, 0.0, 0, 0.0, 0.0]
        adj_outs = [wp.from_torch(c.clone(), dtype=t) for c, t in zip(cots, (k.vec3, k.vec3, k.mat33, k.mat33))]
        wp.launch(kernel, dim=n, inputs=ins + outs, adj_inputs=adj_ins + adj_outs, adjoint=True, device=wd)
        results.append((adj_x, adj_F, adj_gv))
    for a, b in zip(*results):
        assert float(a.abs().max()) > 0
        assert torch.allclose(b, a, rtol=1e-10, atol=1e-12 * float(a.abs().max()))


@pytest.mark.gpu
def test_the_aggregated_fused_frame_equals_the_plain_one_on_cuda():
    # the fused analytic frame (p2g_stress_agg, g2p_p2g_agg) at the duck's density, float64, 4 steps: to rounding
    cfg = SimConfig(n_grid=32, dt=2e-4, bound=2, boundary="friction", friction=0.3, dtype="float64", max_refine=1)
    x = _lattice_ball(3.76, 32, 30000, torch.float64, "cuda")
    _, v, C, F, _, vol, mass = _state(x.shape[0], seed=12, device="cuda")
    material = Material(CorotatedElasticity(1e5, 0.3, learnable=False), IdentityPlasticity(), 1000.0).double().cuda()
    results = []
    for agg in (False, True):
        solver = MPMSolver(cfg, "cuda")
        solver.agg_p2g, solver.vec4_p2g = agg, False  # the reference: the scalar scatter (vec4_p2g's CUDA default off)
        with torch.no_grad():
            results.append(simulate_frame(solver, material, 4, x, 0.1 * v, 0.1 * C, F, vol, mass))
    assert float((results[0][0] - x).abs().max()) > 0
    for a, b in zip(*results):
        assert torch.isfinite(b).all()
        assert float((b - a).abs().max()) <= 1e-10 * float(a.abs().max())
