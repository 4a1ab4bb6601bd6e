"""The interleaved (mv, m) grid of the forward scatter: ``gca.sim.kernels.scatter4`` / ``p2g4`` and the fused analytic
step's ``*4`` kernels (``MPMSolver.vec4_p2g``).

Off CUDA, and in float64 anywhere, ``atomic_add4`` is warp's component-wise atomic add of the vec4: the same sums in
the same order as ``scatter``'s vec3 and scalar adds, so grids and frames are bitwise the plain ones on a CPU. The
CUDA part (Hopper's ``red.global.add.v4.f32``) is checked by its compile for sm_90 through warp's own NVRTC and
ptxas (no GPU needed; a PTX modifier ptxas refuses fails the same compile: the negative control), and, where CUDA is
present, against the plain kernels in float32 on the pipeline's particle orders.
"""

import contextlib
import importlib.util
import sys

import numpy as np
import pytest
import torch
import warp as wp

from gca.laws.base import Material
from gca.laws.elastic import CorotatedElasticity
from gca.laws.plastic import IdentityPlasticity
from gca.sim import kernels as kernels_module
from gca.sim.frame import simulate_frame
from gca.sim.kernels import KERNELS, grid_size
from gca.sim.solver import MPMSolver, SimConfig
from tests.test_sim_agg_p2g import _lattice_ball, _state


def _p2g_grids(dtype: str, x, v, C, tau, vol, mass, run, n_runs: int, n_grid: int, device="cpu"):
    """(mv [n_runs G, G, G, 3], m [..]) of ``p2g``, and the interleaved grid [n_runs G, G, G, 4] of ``p2g4``."""
    wp.init()  # wp.device_from_torch reads warp's runtime, which a launch would start only later
    k = KERNELS[dtype]
    G = grid_size(n_grid)
    wd = wp.device_from_torch(x.device)  # a tensor's device has its ordinal (torch.device("cuda") has none)
    ins = [wp.from_torch(x, dtype=k.vec3), wp.from_torch(v, dtype=k.vec3), wp.from_torch(C, dtype=k.mat33),
           wp.from_torch(tau, dtype=k.mat33), wp.from_torch(vol), wp.from_torch(mass), wp.from_torch(run), 1e-3,
           float(n_grid), n_grid]
    mv = wp.zeros((n_runs * G, G, G), dtype=k.vec3, device=wd)
    m = wp.zeros((n_runs * G, G, G), dtype=k.T, device=wd)
    mvm = wp.zeros((n_runs * G, G, G), dtype=k.vec4, device=wd)
    wp.launch(k.p2g, dim=x.shape[0], inputs=[*ins, mv, m], device=wd)
    wp.launch(k.p2g4, dim=x.shape[0], inputs=[*ins, mvm], device=wd)
    return wp.to_torch(mv), wp.to_torch(m), wp.to_torch(mvm)


@contextlib.contextmanager
def _recorded_launches(skip: str | None = None):
    """The warp launches inside, as a list of (kernel name, adjoint); ``skip``: a kernel name not launched (a
    negative control)."""
    calls, real = [], wp.launch

    def spy(*a, **kw):  # the tape's replay names the kernel by keyword
        name = (a[0] if a else kw["kernel"]).key.rsplit("__", 1)[-1]
        if name == skip:
            return None
        calls.append((name, bool(kw.get("adjoint"))))
        return real(*a, **kw)

    wp.launch = spy
    try:
        yield calls
    finally:
        wp.launch = real


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_p2g4_is_p2g_interleaved_off_cuda(dtype):
    # two runs in one launch: bitwise the plain kernel's momentum and mass, each run's mass on its own grid
    a = _state(60, seed=21, dtype=dtype)
    b = _state(35, seed=22, lo=0.3, hi=0.6, dtype=dtype)
    x, v, C, _, tau, vol, mass = [torch.cat([sa, sb]) for sa, sb in zip(a, b)]
    run = torch.cat([torch.zeros(60, dtype=torch.int32), torch.ones(35, dtype=torch.int32)])
    mv, m, mvm = _p2g_grids(str(dtype)[6:], x, v, C, tau, vol, mass, run, 2, 12)
    assert float(m.sum()) > 0 and float(mv.abs().max()) > 0
    assert torch.equal(mvm[..., :3], mv) and torch.equal(mvm[..., 3], m)
    G = grid_size(12)
    assert torch.isclose(mvm[:G, ..., 3].sum(), mass[:60].sum()) and torch.isclose(mvm[G:, ..., 3].sum(),
                                                                                    mass[60:].sum())


def _material():
    return Material(CorotatedElasticity(1e5, 0.3, learnable=False), IdentityPlasticity(), 1000.0).double()


@pytest.mark.parametrize("frames", [True, False], ids=["one_pass_frame", "fused_steps"])
def test_the_fused_analytic_step_takes_the_interleaved_grid(frames):
    # vec4_p2g routes the fused step's kernels (p2g_stress4, grid_update_zero4, g2p_p2g4): off CUDA bitwise the plain
    # fused frame, within rounding of the generic step; agg_p2g, where also on, takes precedence; the grid is left zero
    cfg = SimConfig(n_grid=16, dt=5e-4, bound=2, boundary="friction", friction=0.3, dtype="float64", max_refine=1)
    x, v, C, F, _, vol, mass = _state(400, seed=23, lo=0.05, hi=0.95)
    results = {}
    four = {"p2g_stress4", "grid_update_zero4", "g2p_p2g4"}
    for path in ("vec4", "vec4_and_agg", "fused", "generic"):
        solver = MPMSolver(cfg)
        solver.fuse_frames, solver.fuse_analytic = frames, path != "generic"
        solver.vec4_p2g, solver.agg_p2g = path.startswith("vec4"), path == "vec4_and_agg"
        with _recorded_launches() as calls, torch.no_grad():
            results[path] = simulate_frame(solver, _material(), 4, x, v, C, F, vol, mass)
        names = [name for name, _ in calls]
        took = {c for c in names if c in four}
        assert took == ((four if frames else four - {"g2p_p2g4"}) if path == "vec4" else set())  # a switch that did
        # nothing would fail
        if path == "vec4_and_agg":
            assert "p2g_stress_agg" in names
        if path == "vec4":
            mvm, _ = solver._zeroed_grid4(1)
            assert not mvm.numpy().any()  # grid_update_zero4 leaves the grid zero for the next frame
    assert float((results["vec4"][0] - x).abs().max()) > 1e-6
    for a, b, c in zip(results["vec4"], results["fused"], results["generic"]):
        assert torch.equal(a, b)
        assert float((a - c).abs().max()) <= 1e-12 * float(c.abs().max())


def test_a_frame_stopped_midway_leaves_the_interleaved_grid_zero():
    # a Ctrl-C between a scatter and its zeroing update: the next frame must start from a zero grid
    cfg = SimConfig(n_grid=16, dt=5e-4, dtype="float64", max_refine=1)
    x, v, C, F, _, vol, mass = _state(200, seed=24, lo=0.2, hi=0.8)
    law = _material()
    solver = MPMSolver(cfg)
    solver.fuse_frames, solver.vec4_p2g = True, True
    real = wp.launch

    def stop(k, *a, **kw):
        real(k, *a, **kw)
        if k.key.endswith("p2g_stress4"):
            raise KeyboardInterrupt

    wp.launch = stop
    try:
        with pytest.raises(KeyboardInterrupt), torch.no_grad():
            simulate_frame(solver, law, 3, x, v, C, F, vol, mass)
    finally:
        wp.launch = real
    assert not solver._zeroed_grid4(1)[0].numpy().any()
    with torch.no_grad():  # and the next frame equals a fresh solver's
        again = simulate_frame(solver, law, 3, x, v, C, F, vol, mass)
        fresh = MPMSolver(cfg)
        fresh.fuse_frames, fresh.vec4_p2g = True, True
        ref = simulate_frame(fresh, law, 3, x, v, C, F, vol, mass)
    for a, b in zip(again, ref):
        assert torch.equal(a, b)


def test_vec4_p2g_is_on_cuda_only_by_default():
    solver = MPMSolver(SimConfig(n_grid=8, dt=1e-3, dtype="float64", max_refine=1))
    assert solver.vec4_p2g is None and not solver.vec4s_p2g  # measured faster on the H200 (session 50); a CPU solver
    # keeps the plain grid (bitwise the same anyway)
    solver.vec4_p2g = True
    assert solver.vec4s_p2g
    assert solver.refined(2).vec4_p2g is True  # a refined solver follows the switch


@pytest.mark.parametrize("module, vector", [("gca_sim_mpm_v4_float32", True), ("gca_sim_mpm_v4_float64", False),
                                            ("gca_sim_fused_step_v4_float32", True)])
def test_the_vector_reduction_compiles_for_sm_90(tmp_path, module, vector):
    # warp's NVRTC and ptxas for the H100/H200's arch, on any machine (the PyPI wheel carries them): float32 takes the
    # vector reduction, float64 warp's own atomic add
    from gca.sim.fused_step import make_fused_step_kernels

    make_fused_step_kernels(torch.float32)  # registers the fused step's modules
    paths = wp.compile_aot_module(module, arch=90, module_dir=str(tmp_path))
    assert paths and all(p.exists() for p in paths)
    src = "".join(p.read_text() for p in tmp_path.glob("*.cu"))
    assert ("red.global.add.v4.f32" in src) == vector
    assert "scatter4" in src and ("grid_update_unpack4" in src) == module.startswith("gca_sim_mpm")
    if module.startswith("gca_sim_mpm"):  # G2P's adjoint into the accumulator: the vector reduction in its adjoint
        adj = src[src.index("void adj_make_kernels__locals__node_read4"):]
        assert ("red.global.add.v4.f32" in adj[:adj.index("}\n\n")]) == vector


def test_ptxas_refuses_a_vector_reduction_it_does_not_know(tmp_path, monkeypatch):
    # the negative control of the compile test above: the same snippet with a modifier sm_90 lacks (.v5) fails the
    # build, so a passing compile means ptxas took the PTX
    bad = kernels_module._ATOMIC_ADD4_F32.replace(".v4.f32", ".v5.f32")
    src = tmp_path / "bad_v4_kernel.py"
    src.write_text(f'''
import warp as wp
vec4 = wp.types.vector(4, wp.float32)
SNIPPET = {bad!r}


@wp.func_native(SNIPPET)
def add4(a: wp.array3d(dtype=vec4), i: int, j: int, k: int, v: vec4):
    ...


@wp.kernel(module="gca_test_bad_v4")
def kern(a: wp.array3d(dtype=vec4)):
    add4(a, wp.tid(), 0, 0, vec4(1.0, 2.0, 3.0, 4.0))
''')
    spec = importlib.util.spec_from_file_location("bad_v4_kernel", src)
    mod = importlib.util.module_from_spec(spec)
    monkeypatch.setitem(sys.modules, "bad_v4_kernel", mod)
    spec.loader.exec_module(mod)
    with pytest.raises(Exception, match="(?i)fail|error"):
        wp.compile_aot_module("gca_test_bad_v4", arch=90, module_dir=str(tmp_path / "out"))


@pytest.mark.gpu
@pytest.mark.parametrize("order", ["lattice", "ball", "duck", "random", "two_runs"])
def test_p2g4_equals_p2g_on_cuda(order):
    # float32 on the GPU: the vector reduction against the scalar atomics, to float32 rounding (the adds' order)
    per_edge = {"lattice": 2.0, "ball": 2.4, "duck": 3.76, "random": 2.0, "two_runs": 3.76}[order]
    x = _lattice_ball(per_edge, 32, 30000, torch.float32, "cuda")
    if order == "random":
        x = x[torch.randperm(len(x), generator=torch.Generator().manual_seed(25)).cuda()].contiguous()
    n_runs = 2 if order == "two_runs" else 1
    if n_runs == 2:
        x = torch.stack([x, x], 1).reshape(-1, 3).contiguous()
    run = (torch.arange(len(x), device="cuda", dtype=torch.int32) % n_runs).contiguous()
    _, v, C, _, tau, vol, mass = _state(x.shape[0], seed=26, dtype=torch.float32, device="cuda")
    mv, m, mvm = _p2g_grids("float32", x, v, C, tau, vol, mass, run, n_runs, 32, device="cuda")
    assert float(m.sum()) > 0
    assert torch.allclose(mvm[..., 3], m, rtol=1e-5, atol=1e-6 * float(m.max()))
    assert torch.allclose(mvm[..., :3], mv, rtol=1e-5, atol=1e-5 * float(mv.abs().max()))
    G = grid_size(32)
    for r in range(n_runs):
        assert np.isclose(float(mvm[r * G:(r + 1) * G, ..., 3].double().sum()), float(mass[run == r].double().sum()),
                          rtol=1e-5)


@pytest.mark.gpu
def test_the_interleaved_fused_frame_equals_the_plain_one_on_cuda():
    # PhysGaussian's job's shape: the fused frame at the duck's density, float32, 20 steps, vec4 against the plain grid
    cfg = SimConfig(n_grid=32, dt=2e-4, bound=2, boundary="friction", friction=0.3, dtype="float32", max_refine=1)
    x = _lattice_ball(3.76, 32, 30000, torch.float32, "cuda")
    _, v, C, F, _, vol, mass = _state(x.shape[0], seed=27, dtype=torch.float32, device="cuda")
    material = Material(CorotatedElasticity(1e5, 0.3, learnable=False), IdentityPlasticity(), 1000.0).cuda()
    results = []
    for vec4 in (False, True):
        solver = MPMSolver(cfg, "cuda")
        solver.fuse_frames, solver.vec4_p2g = True, vec4
        with torch.no_grad():
            results.append(simulate_frame(solver, material, 20, x, 0.1 * v, 0.1 * C, F, vol, mass))
    assert float((results[0][0] - x).abs().max()) > 0
    for a, b in zip(*results):
        assert torch.isfinite(b).all()
        assert float((b - a).abs().max()) <= 1e-4 * float(a.abs().max())


# -- the generic step's forward P2G on the interleaved scratch (MPMSolver.vec4_step) ------------------------------


@pytest.mark.parametrize("keep_grid", [True, False], ids=["kept_grid", "recomputed"])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_vec4_step_is_the_plain_step_off_cuda(dtype, keep_grid):
    # a step's values and gradients bitwise the plain step's (0 + the sums is the sums), the forward through p2g4 and
    # grid_update_unpack4 (a switch that did nothing would fail), the backward unchanged, the scratch left zero
    cfg = SimConfig(n_grid=16, dt=1e-3, bound=2, boundary="friction", friction=0.5, dtype=str(dtype)[6:], max_refine=1)
    x, v, C, F, tau, vol, mass = _state(300, seed=31, lo=0.02, hi=0.98, dtype=dtype)
    outs = {}
    for vec4 in (True, False):
        solver = MPMSolver(cfg)
        solver.vec4_step, solver.keep_grid = vec4, keep_grid
        inputs = [t.clone().requires_grad_() for t in (x, v, C, F, tau)]
        with _recorded_launches() as calls:
            step = solver.step(*inputs, vol, mass)
            forward = {name for name, _ in calls}  # the step's own launches (a recompute's tape relaunches p2g)
            outs[vec4] = (*step, *torch.autograd.grad(step, inputs, [torch.ones_like(o) for o in step]))
        assert ({"p2g4", "grid_update_unpack4"} <= forward and "p2g" not in forward) if vec4 else \
            ("p2g" in forward and "p2g4" not in forward)
        if vec4:
            assert not solver._scratch_grid("p2g", 1).numpy().any()
    assert float(outs[True][0].detach().sub(x).abs().max()) > 0
    for a, b in zip(outs[True], outs[False]):
        assert torch.equal(a, b)


@pytest.mark.parametrize("switches, taken", [(("vec4_step",), {("p2g4", False)}),
                                             (("vec4_step", "vec4_g2p_adj"), {("p2g4", False), ("g2p4", True)})],
                         ids=["vec4_step", "both"])
def test_the_training_switches_give_a_swept_rollouts_results_bitwise(switches, taken):
    # training's path (graphed frames' eager twin, the grid stash, the reverse sweep) with the switches on and off:
    # trajectories, stashes and gradients bitwise, the sweep's frames through the switches' kernels
    from test_sim_stash import _solver, _swept
    from test_sim_graph import _law, _scene

    material, scene = _law(), _scene()
    results = {}
    for vec4 in (True, False):
        solver = _solver()
        for switch in switches:
            setattr(solver, switch, vec4)
        with _recorded_launches() as calls:
            results[vec4] = _swept(solver, material, scene)
        assert taken <= set(calls) if vec4 else not taken & set(calls)
    (x1, g1, s1), (x0, g0, s0) = results[True], results[False]
    assert torch.equal(x1, x0) and s1 is not None
    for a, b in zip(s1, s0):  # the stash keeps the unpacked grid
        assert all(torch.equal(p, q) for p, q in zip(a, b))
    for a, b in zip(g1, g0):
        assert float(b.abs().max()) > 0 and torch.equal(a, b)


def test_vec4_step_defaults_to_the_gpu_and_yields_to_the_other_p2g_options():
    solver = MPMSolver(SimConfig(n_grid=8, dt=1e-3, dtype="float64", max_refine=1))
    assert solver.vec4_step is None and not solver.vec4s_step  # where the vector reduction runs (session 51); a CPU solver
    solver.vec4_step, solver.agg_p2g = True, True
    assert solver.refined(2).vec4_step is True
    x, v, C, F, tau, vol, mass = _state(50, seed=32)
    with _recorded_launches() as calls, torch.no_grad():
        solver.step(x, v, C, F, tau, vol, mass)
    names = {name for name, _ in calls}
    assert "p2g_agg" in names and "p2g4" not in names


# -- G2P's adjoint into an interleaved accumulator (MPMSolver.vec4_g2p_adj) -----------------------------------------


def _step_with_grads(solver, state, skip_unpack=False):
    """(outputs and input gradients of one step with sum-of-outputs cotangents, the kernels launched as (name,
    adjoint)); ``skip_unpack``: ``grid_unpack_adj4`` not launched (the negative control)."""
    x, v, C, F, tau, vol, mass = state
    inputs = [t.clone().requires_grad_() for t in (x, v, C, F, tau)]
    with _recorded_launches(skip="grid_unpack_adj4" if skip_unpack else None) as calls:
        step = solver.step(*inputs, vol, mass)
        out = (*step, *torch.autograd.grad(step, inputs, [torch.ones_like(o) for o in step]))
    return out, calls


@pytest.mark.parametrize("with_step", [False, True], ids=["adjoint_alone", "with_vec4_step"])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_vec4_g2p_adj_gives_the_plain_gradients_off_cuda(dtype, with_step):
    # on a kept grid (training's backward): values and gradients bitwise the plain step's, G2P's adjoint through g2p4
    # and the unpacking (a switch that did nothing would fail), the accumulator left zero; without the unpacking the
    # gradients change (the negative control: they flow through the accumulator)
    cfg = SimConfig(n_grid=16, dt=1e-3, bound=2, boundary="friction", friction=0.5, dtype=str(dtype)[6:], max_refine=1)
    state = _state(300, seed=34, lo=0.02, hi=0.98, dtype=dtype)
    results = {}
    for vec4 in (True, False):
        solver = MPMSolver(cfg)
        solver.keep_grid, solver.vec4_g2p_adj, solver.vec4_step = True, vec4, vec4 and with_step
        results[vec4], calls = _step_with_grads(solver, state)
        adjoints = {name for name, adjoint in calls if adjoint}
        assert ("g2p4" in adjoints and "g2p" not in adjoints) if vec4 else \
            ("g2p" in adjoints and "g2p4" not in adjoints)
        assert (("grid_unpack_adj4", False) in calls) == vec4
        if vec4:
            assert not solver._scratch_grid("g2p_adj", 1).numpy().any()
    for a, b in zip(results[True], results[False]):
        assert torch.equal(a, b)
    solver = MPMSolver(cfg)
    solver.keep_grid, solver.vec4_g2p_adj = True, True
    broken, _ = _step_with_grads(solver, state, skip_unpack=True)
    assert not torch.equal(broken[4], results[False][4])  # the gradient of x


def test_vec4_g2p_adj_defaults_to_the_gpu_and_yields_to_agg_g2p():
    cfg = SimConfig(n_grid=8, dt=1e-3, dtype="float64", max_refine=1)
    solver = MPMSolver(cfg)
    assert solver.vec4_g2p_adj is None and not solver.vec4s_g2p_adj  # session 51; a CPU solver
    solver.vec4_g2p_adj, solver.agg_g2p, solver.keep_grid = True, True, True
    assert solver.refined(2).vec4_g2p_adj is True
    _, calls = _step_with_grads(solver, _state(50, seed=35))
    adjoints = {name for name, adjoint in calls if adjoint}
    assert "g2p_agg" in adjoints and "g2p4" not in adjoints


@pytest.mark.gpu
@pytest.mark.parametrize("keep_grid, adj", [(False, False), (True, False), (True, True)],
                         ids=["vec4_step_recomputed", "vec4_step_kept", "both_kept"])
def test_the_training_switches_match_the_plain_step_on_cuda(keep_grid, adj):
    # float32 on the GPU at the duck's density: a step's values and gradients to float32 rounding
    cfg = SimConfig(n_grid=32, dt=2e-4, bound=2, boundary="friction", friction=0.3, dtype="float32", max_refine=1)
    x = _lattice_ball(3.76, 32, 30000, torch.float32, "cuda")
    _, v, C, F, tau, vol, mass = _state(x.shape[0], seed=36, dtype=torch.float32, device="cuda")
    state = (x, 0.1 * v, 0.1 * C, F, tau, vol, mass)
    outs = []
    for vec4 in (False, True):
        solver = MPMSolver(cfg, "cuda")
        solver.keep_grid, solver.vec4_step, solver.vec4_g2p_adj = keep_grid, vec4, vec4 and adj
        outs.append(_step_with_grads(solver, state)[0])
    for a, b in zip(*outs):
        assert torch.isfinite(b).all()
        assert float((b - a).abs().max()) <= 1e-4 * float(a.abs().max())


@pytest.mark.gpu
def test_both_training_switches_through_captured_frames_on_cuda():
    # training's path on a GPU: graphed frames (warm-up, then capture), the stash and the reverse sweep, float32, both
    # vector switches against none: trajectories and gradients to float32 rounding; the scratches made by the warm-ups
    # (before any capture) and left zero
    from test_sim_graph import _law, _scene
    from test_sim_stash import _swept

    cfg = SimConfig(n_grid=12, dt=1e-3, bound=1, boundary="friction", friction=0.3, dtype="float32", max_refine=1)
    material = _law(dtype=torch.float32).cuda()
    scene = tuple(t.cuda() for t in _scene(n=400, dtype=torch.float32))
    results = {}
    for vec4 in (False, True):
        solver = MPMSolver(cfg, "cuda")
        solver.stash_mib, solver.vec4_step, solver.vec4_g2p_adj = 1536.0, vec4, vec4
        results[vec4] = _swept(solver, material, scene)
        if vec4:
            assert {k[0] for k in solver._scratch_grids} == {"p2g", "g2p_adj"}
            assert all(not t.numpy().any() for t in solver._scratch_grids.values())
    (x1, g1, _), (x0, g0, _) = results[True], results[False]
    assert float((x1 - x0).abs().max()) <= 1e-4 * float(x0.abs().max())
    for a, b in zip(g1, g0):
        assert torch.isfinite(a).all() and float(b.abs().max()) > 0
        assert float((a - b).abs().max()) <= 1e-3 * float(b.abs().max())


@pytest.mark.parametrize("dtype, arch, on", [("float32", 90, True), ("float32", 80, False), ("float64", 90, False)])
def test_the_vector_switches_default_to_where_the_vector_reduction_runs(dtype, arch, on):
    # None: float32 on sm_90+ only (elsewhere the interleaved kernels add component-wise, never measured); a device
    # faked on a CPU solver
    import types

    solver = MPMSolver(SimConfig(n_grid=8, dt=1e-3, dtype=dtype, max_refine=1))
    solver.device, solver.wp_device = torch.device("cuda", 0), types.SimpleNamespace(arch=arch)
    assert (solver.vec4_p2g, solver.vec4_step, solver.vec4_g2p_adj) == (None, None, None)  # the defaults
    assert (solver.vec4s_p2g, solver.vec4s_step, solver.vec4s_g2p_adj) == (on, on, on)
    solver.vec4_step = False
    assert not solver.vec4s_step
