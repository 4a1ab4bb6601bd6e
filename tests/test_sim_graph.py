"""gca.sim.graph: frames replayed from static buffers (CUDA graphs on a GPU, the eager twin here).

The twin runs the very code the GPU captures (static input copies, the recompute-backward with
``torch.autograd.grad`` into static cotangents, parameter gradients); it must equal the per-frame
checkpointed rollout in values and gradients, pass a float64 gradcheck, reuse its cached runner and
see in-place parameter updates (what the optimiser does between replays).
"""

import warnings

import pytest
import torch
import warp as wp

from gca.laws.base import Material
from gca.laws.lora import apply_lora
from gca.laws.neural import NeuralElasticity, NeuralLawConfig, NeuralPlasticity
from gca.sim import MPMSolver, SimConfig, rollout
from gca.sim.graph import FrameGraphs, graphed_frame

wp.config.quiet = True
F64 = torch.float64


def _law(dtype=F64, seed=0) -> Material:
    """Small LoRA-adapted neural elasticity + plasticity with non-zero adapters (so they matter)."""
    torch.manual_seed(seed)
    cfg = NeuralLawConfig(widths=(16, 16), stress_scale=2e3, alpha=1e-2)
    el, pl = NeuralElasticity(cfg), NeuralPlasticity(cfg)
    for net in (el, pl):
        apply_lora(net, rank=2, alpha=2.0)
        for name, p in net.named_parameters():
            if name.endswith("lora_B"):
                torch.nn.init.normal_(p, std=0.3)
    return Material(el, pl, 1000.0).to(dtype)


def _scene(n=40, dtype=F64, seed=1):
    g = torch.Generator().manual_seed(seed)
    x0 = (0.4 + 0.2 * torch.rand(n, 3, generator=g)).to(dtype)
    v0 = (torch.tensor([0.3, -0.2, 0.1]) + 0.2 * torch.randn(n, 3, generator=g)).to(dtype)
    vol = torch.full((n,), 2e-6, dtype=dtype)
    return x0, v0, vol, vol * 1000.0


def _loss_and_grads(material, solver, graph, x0, v0, vol, mass, n_steps=8, per_frame=2):
    v0 = v0.clone().requires_grad_(True)
    out = rollout(solver, material, x0, v0, vol, mass, n_steps, per_frame, checkpoint=True, graph=graph)
    w = torch.linspace(0.5, 1.5, out.x.shape[1], dtype=x0.dtype, device=x0.device)[:, None]
    loss = (w * out.x[-1]).sum() + (out.F[-1] ** 2).sum() + 0.1 * out.F_trial[2].sum() + (out.v[3] ** 2).sum()
    params = [p for p in material.parameters() if p.requires_grad]
    return out, torch.autograd.grad(loss, [v0, *params])


def test_twin_equals_checkpointed_rollout():
    material = _law()
    solver = MPMSolver(SimConfig(n_grid=12, dt=1e-3, bound=1, boundary="friction", friction=0.3, dtype="float64",
                                 max_refine=1))
    scene = _scene()
    ref, g_ref = _loss_and_grads(material, solver, False, *scene)
    out, g = _loss_and_grads(material, solver, True, *scene)
    for a, b in ((out.x, ref.x), (out.v, ref.v), (out.F, ref.F), (out.F_trial, ref.F_trial), (out.C, ref.C)):
        torch.testing.assert_close(a, b, atol=1e-12, rtol=1e-12)
    assert len(g) == 1 + 12  # v0 and the 12 LoRA factors of the two 3-layer networks
    assert all(float(t.abs().max()) > 0 for t in g)  # every gradient is exercised
    for a, b in zip(g, g_ref):
        torch.testing.assert_close(a, b, atol=1e-12, rtol=1e-9)


@pytest.mark.grad
def test_graphed_frame_gradcheck_float64():
    material = _law()
    solver = MPMSolver(SimConfig(n_grid=8, dt=1e-3, bound=1, dtype="float64", boundary="sticky", friction=0.0,
                                 max_refine=1))
    x0, v0, vol, mass = _scene(n=4)
    runner = FrameGraphs(solver, material, n_steps=2, n=4, capture=False)
    runner.bind(vol, mass)
    g = torch.Generator().manual_seed(3)
    C = 0.5 * torch.randn(4, 3, 3, generator=g, dtype=F64)
    F = torch.eye(3, dtype=F64) + 0.05 * torch.randn(4, 3, 3, generator=g, dtype=F64)
    lora_b = [p for n, p in material.named_parameters() if n.endswith("lora_B")][:2]

    def fn(x, v, C, F, *_params):  # the parameters enter through the material, listed for gradcheck
        return graphed_frame(runner, x, v, C, F)

    inputs = [t.clone().requires_grad_(True) for t in (x0, v0, C, F)]
    # gradcheck perturbs the parameters in place: the runner must read their current storage
    assert torch.autograd.gradcheck(fn, (*inputs, *lora_b), eps=1e-6, atol=1e-7, rtol=1e-5)


def test_runner_is_cached_and_sees_in_place_updates():
    material = _law()
    solver = MPMSolver(SimConfig(n_grid=12, dt=1e-3, bound=1, dtype="float64", boundary="sticky", friction=0.0,
                                 max_refine=1))
    scene = _scene()
    rollout(solver, material, *scene, 4, 2, graph=True)
    runner = solver.frame_graphs(material, 2, scene[0].shape[0])
    with torch.no_grad():
        for p in material.parameters():
            if p.requires_grad:
                p.mul_(1.5)
    out = rollout(solver, material, *scene, 4, 2, graph=True)
    assert solver.frame_graphs(material, 2, scene[0].shape[0]) is runner
    ref = rollout(solver, material, *scene, 4, 2, graph=False)
    torch.testing.assert_close(out.x, ref.x, atol=1e-12, rtol=1e-12)
    other = _law(seed=5)  # another material gets its own runner
    assert solver.frame_graphs(other, 2, scene[0].shape[0]) is not runner


def test_a_runner_is_reused_only_under_the_float32_product_precision_it_was_made_under():
    """train.matmul_precision: a captured graph bakes its products' kernels in, so a runner made while torch's
    float32 products ran at one precision (e.g. TF32, "high") must not serve a rollout at another."""
    material = _law()
    solver = MPMSolver(SimConfig(n_grid=12, dt=1e-3, bound=1, dtype="float64", boundary="sticky", friction=0.0,
                                 max_refine=1))
    n = _scene()[0].shape[0]
    before = torch.get_float32_matmul_precision()
    try:
        torch.set_float32_matmul_precision("high")
        high = solver.frame_graphs(material, 2, n)
        assert solver.frame_graphs(material, 2, n) is high  # the same precision: reused (the control)
        torch.set_float32_matmul_precision("highest")
        highest = solver.frame_graphs(material, 2, n)
        assert highest is not high and (high.precision, highest.precision) == ("high", "highest")
        assert solver.frame_graphs(material, 2, n) is highest
    finally:
        torch.set_float32_matmul_precision(before)


def test_a_runner_is_reused_only_under_the_mlp_kernels_it_was_made_under():
    """train.mlp_kernel: a captured graph bakes the networks' MLP kernels in too."""
    material = _law()
    solver = MPMSolver(SimConfig(n_grid=12, dt=1e-3, bound=1, dtype="float64", boundary="sticky", friction=0.0,
                                 max_refine=1))
    n = _scene()[0].shape[0]
    made = solver.frame_graphs(material, 2, n)
    assert solver.frame_graphs(material, 2, n) is made and made.kernels == ("torch", "torch")  # reused (the control)
    material.elasticity.mlp_kernel = "simt"
    simt = solver.frame_graphs(material, 2, n)
    assert simt is not made and simt.kernels == ("simt", "torch")


def test_capture_refused_on_cpu():
    solver = MPMSolver(SimConfig(n_grid=8, dtype="float64", dt=1e-3, bound=3, boundary="sticky", friction=0.0,
                                 max_refine=1))
    with pytest.raises(ValueError, match="CUDA"):
        FrameGraphs(solver, _law(), 2, 4, capture=True)


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_cuda_graphs_match_eager_on_gpu():
    """On a GPU: captured replay vs the eager twin vs the checkpointed rollout (float32); the graphed frames'
    autograd path replays the grid stash (the term shares' path)."""
    material = _law(dtype=torch.float32).cuda()
    solver = MPMSolver(SimConfig(n_grid=16, dt=1e-3, bound=1, boundary="sticky", friction=0.0, max_refine=1), "cuda")
    scene = [t.cuda() for t in _scene(n=500, dtype=torch.float32)]
    ref, g_ref = _loss_and_grads(material, solver, False, *scene)
    out, g = _loss_and_grads(material, solver, True, *scene)
    runner = solver.frame_graphs(material, 2, 500)
    assert runner.capture, "capture fell back to eager"
    assert runner.stashes and runner._rep_graph is not None  # the stash's replay graph was captured and taken
    torch.testing.assert_close(out.x, ref.x, atol=1e-5, rtol=1e-5)
    for a, b in zip(g, g_ref):
        torch.testing.assert_close(a, b, atol=1e-5 * float(b.abs().max()), rtol=1e-3)


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_a_forward_captured_alone_then_its_backward_match_eager_on_gpu():
    """On a GPU: a rollout without gradients first (an evaluation's: the forward graph captured alone), then one with
    gradients (its backward graphs captured then): values and gradients as the eager rollout's."""
    material = _law(dtype=torch.float32).cuda()
    solver = MPMSolver(SimConfig(n_grid=16, dt=1e-3, bound=1, boundary="sticky", friction=0.0, max_refine=1), "cuda")
    scene = [t.cuda() for t in _scene(n=500, dtype=torch.float32)]
    with torch.no_grad():
        first = rollout(solver, material, *scene, 8, 2, graph=True)
    runner = solver.frame_graphs(material, 2, 500)
    assert runner.capture and runner._fwd_graph is not None and runner._bwd_graph is None
    ref, g_ref = _loss_and_grads(material, solver, False, *scene)
    out, g = _loss_and_grads(material, solver, True, *scene)
    assert solver.frame_graphs(material, 2, 500) is runner and runner._bwd_graph is not None
    torch.testing.assert_close(first.x, ref.x, atol=1e-5, rtol=1e-5)
    torch.testing.assert_close(out.x, ref.x, atol=1e-5, rtol=1e-5)
    for a, b in zip(g, g_ref):
        torch.testing.assert_close(a, b, atol=1e-5 * float(b.abs().max()), rtol=1e-3)


def _agree_on_gpu(out, g, ref, g_ref):
    """Two float32 rollouts on a GPU (trajectory, gradients) against each other: the same to rounding (P2G's atomics
    sum in another order each run), every gradient exercised."""
    torch.testing.assert_close(out.x, ref.x, atol=1e-6, rtol=1e-6)
    assert all(float(t.abs().max()) > 0 for t in g)
    for a, b in zip(g, g_ref):
        torch.testing.assert_close(a, b, atol=1e-5 * float(b.abs().max()), rtol=1e-3)


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_frame_mlp_sums_under_cuda_graphs_match_the_plain_frames_on_gpu():
    """On a GPU: the fused Triton MLP's weight gradients summed a frame (``MPMSolver.frame_mlp_grads``) inside the
    captured frames give the plain captured frames' trajectory and gradients (float32, TF32 products: the same
    products, another summation order); the runner is not reused across the switch."""
    pytest.importorskip("triton")
    from gca.laws import mlp_triton

    material = _law(dtype=torch.float32).cuda()
    for net in (material.elasticity, material.plasticity):
        net.mlp_kernel = "triton_tf32"
    scene = [t.cuda() for t in _scene(n=500, dtype=torch.float32)]
    made = []
    init = mlp_triton.FrameSum.__init__
    results = {}
    try:
        mlp_triton.FrameSum.__init__ = lambda self, *a: (made.append(1), init(self, *a))[1]
        for on in (False, True):
            solver = MPMSolver(SimConfig(n_grid=16, dt=1e-3, bound=1, boundary="sticky", friction=0.0,
                                         max_refine=1), "cuda")
            solver.frame_mlp_grads = on
            results[on] = _loss_and_grads(material, solver, True, *scene)
            assert solver.frame_graphs(material, 2, 500).capture, "capture fell back to eager"
            assert bool(made) == on
    finally:
        mlp_triton.FrameSum.__init__ = init
    (ref, g_ref), (out, g) = results[False], results[True]
    _agree_on_gpu(out, g, ref, g_ref)


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_the_mlp_stash_under_cuda_graphs_matches_the_grid_stash_alone_on_gpu():
    """On a GPU: captured frames that keep their networks' fused-MLP outputs (``MPMSolver.mlp_stash_mib``) and replay
    them through the third backward graph give the grid stash's trajectory and gradients (the same kernels on the
    same inputs), through graphed autograd. Two solvers' forward passes differ at float32 rounding on a GPU (P2G's
    atomics sum in another order each run: session 57 saw 6e-8 in 17 of 7500 positions), hence the tolerances."""
    pytest.importorskip("triton")
    material = _law(dtype=torch.float32).cuda()
    for net in (material.elasticity, material.plasticity):
        net.mlp_kernel = "triton_tf32"
    scene = [t.cuda() for t in _scene(n=500, dtype=torch.float32)]
    results = {}
    for mib in (0.0, 64.0):
        solver = MPMSolver(SimConfig(n_grid=16, dt=1e-3, bound=1, boundary="sticky", friction=0.0, max_refine=1),
                           "cuda")
        solver.mlp_stash_mib = mib
        results[mib] = _loss_and_grads(material, solver, True, *scene)
        runner = solver.frame_graphs(material, 2, 500)
        assert runner.capture, "capture fell back to eager"
        assert (runner._rpx_graph is not None) == (mib > 0) and len(runner.mlp_nets) == (2 if mib > 0 else 0)
    (ref, g_ref), (out, g) = results[0.0], results[64.0]
    _agree_on_gpu(out, g, ref, g_ref)


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_capture_survives_unreachable_warp_memory():
    """An unreachable solver (a reference cycle holding warp-owned grid buffers) must not be collected
    inside a capture: warp would free its memory while torch captures, and the capture would fail.
    The collector runs at every allocation here, so without the pause it would collect in the capture."""
    import gc

    material = _law(dtype=torch.float32).cuda()
    scene = [t.cuda() for t in _scene(n=300, dtype=torch.float32)]
    threshold = gc.get_threshold()
    gc.disable()
    try:
        old = MPMSolver(SimConfig(n_grid=16, dt=1e-3, bound=1, boundary="sticky", friction=0.0, max_refine=1), "cuda")
        old.me = old  # a cycle: only the cyclic collector frees it
        old.grid(scene[0], scene[1], torch.zeros(300, 3, 3, device="cuda"), torch.zeros(300, 3, 3, device="cuda"),
                 scene[2], scene[3])  # allocates its warp grid buffers
        del old
        gc.set_threshold(1, 1, 1)
        gc.enable()
        solver = MPMSolver(SimConfig(n_grid=16, dt=1e-3, bound=1, boundary="sticky", friction=0.0, max_refine=1),
                                     "cuda")
        with warnings.catch_warnings():
            warnings.simplefilter("error", RuntimeWarning)  # the eager fallback warns
            _loss_and_grads(material, solver, True, *scene)
        assert solver.frame_graphs(material, 2, 300).capture
    finally:
        gc.set_threshold(*threshold)
        gc.enable()


@pytest.mark.parametrize("build", ["composite", "batched"])
@pytest.mark.parametrize("graph", [False, True])
def test_runs_rolled_out_together_equal_each_run_alone(graph, build):
    # issue 20's batched trainer, its simulation: two runs (their own LoRA laws, particle sets and launches) in one
    # launch per step (MPMSolver.with_runs + a CompositeMaterial of the runs' materials) give each run's trajectory
    # (bitwise on the CPU) and gradients (launch velocity and its law's adapters, to rounding) as when it is rolled
    # out alone, through the checkpointed rollout and through the CUDA-graph runner's eager twin. ``batched``: the runs'
    # laws in one batch (gca.laws.batched: equal slices, one bmm per layer), trajectories then to rounding too.
    from gca.laws.base import CompositeMaterial
    from gca.laws.batched import BatchedElasticity, runs_material

    solver = MPMSolver(SimConfig(n_grid=12, dt=1e-3, bound=1, boundary="friction", friction=0.3, dtype="float64",
                                 max_refine=1))
    laws = [_law(seed=0), _law(seed=5)]
    scenes = [_scene(n=30, seed=1), _scene(n=22 if build == "composite" else 30, seed=2)]

    def loss_and_grads(material, solver, x0, v0, vol, mass, params):
        v0 = v0.clone().requires_grad_(True)
        out = rollout(solver, material, x0, v0, vol, mass, 8, 2, checkpoint=True, graph=graph)
        loss = (out.x[-1] ** 2).sum() + (out.F[-1] ** 2).sum() + (out.v[3] ** 2).sum()
        return out, loss, torch.autograd.grad(loss, [v0, *params])

    alone = []
    for law, scene in zip(laws, scenes):
        params = [p for p in law.parameters() if p.requires_grad]
        out, _, grads = loss_and_grads(law, solver, *scene, params)
        alone.append((out, grads))
    counts = [s[0].shape[0] for s in scenes]
    run = torch.cat([torch.full((c,), r, dtype=torch.int32) for r, c in enumerate(counts)])
    batch = solver.with_runs(run, 2)
    both = CompositeMaterial(laws, counts) if build == "composite" else runs_material(laws, counts)
    assert isinstance(both.elasticity, BatchedElasticity) == (build == "batched")
    params = [p for law in laws for p in law.parameters() if p.requires_grad]
    cat = [torch.cat([s[i] for s in scenes]) for i in range(4)]
    out, _, grads = loss_and_grads(both, batch, *cat, params)
    n_params = len(params) // 2
    for r, (ref, ref_grads) in enumerate(alone):
        rows = slice(0, counts[0]) if r == 0 else slice(counts[0], None)
        for a, b in ((out.x, ref.x), (out.v, ref.v), (out.F, ref.F), (out.F_trial, ref.F_trial)):
            if build == "composite":
                assert torch.equal(a[:, rows], b)
            else:
                torch.testing.assert_close(a[:, rows], b, rtol=1e-12, atol=1e-14)
        # gradients to rounding (torch's CPU kernels may vectorise a slice of a batch differently): float64 1e-12
        torch.testing.assert_close(grads[0][rows], ref_grads[0], rtol=1e-12, atol=1e-14)  # d loss / d v0 of this run
        for a, b in zip(grads[1 + r * n_params:1 + (r + 1) * n_params], ref_grads[1:]):
            assert float(b.abs().max()) > 0
            torch.testing.assert_close(a, b, rtol=1e-12, atol=1e-16)
    shared = rollout(solver.with_runs(torch.zeros_like(run), 1), both, *cat, 8, 2, graph=graph)  # control: one grid
    assert not torch.equal(shared.x[-1, :counts[0]], alone[0][0].x[-1])


class _FakeGraph:
    """torch.cuda.CUDAGraph's stand-in on the CPU: its capture runs the body eagerly (a context of its own below)."""

    def replay(self):
        pass

    def pool(self):
        return None


def test_a_rollout_without_gradients_captures_the_forward_graph_alone(monkeypatch):
    """An evaluation's rollout (no gradient) captures no backward graph; a later rollout with gradients captures it
    then, once; a frame runner's own forward (the reverse sweep's) captures both at once, as before. CUDA's graph API
    is faked (the capture's bodies run eagerly) to count the passes each capture runs on the CPU."""
    import contextlib

    monkeypatch.setattr(torch.cuda, "Stream", lambda *a, **k: type("S", (), {"wait_stream": lambda self, s: None})())
    monkeypatch.setattr(torch.cuda, "current_stream", lambda *a, **k: type("S", (), {"wait_stream": lambda self, s: None})())
    monkeypatch.setattr(torch.cuda, "stream", lambda s: contextlib.nullcontext())
    monkeypatch.setattr(torch.cuda, "CUDAGraph", _FakeGraph)
    monkeypatch.setattr(torch.cuda, "graph", lambda g, **k: contextlib.nullcontext())
    solver = MPMSolver(SimConfig(n_grid=8, dt=1e-3, bound=1, dtype="float64", boundary="sticky", friction=0.0,
                                 max_refine=1))
    x0, v0, vol, mass = _scene(n=4)
    C, F = torch.zeros(4, 3, 3, dtype=F64), torch.eye(3, dtype=F64).expand(4, 3, 3).clone()

    def runner_counting():
        runner = FrameGraphs(solver, _law(), n_steps=2, n=4, capture=False)
        runner.capture = True  # as on a GPU, with the fake graph API above
        runner.bind(vol, mass)
        calls = {"forward": 0, "backward": 0}
        for name in calls:
            real = getattr(runner, f"_run_{name}")

            def counted(*a, _real=real, _name=name, **k):
                calls[_name] += 1
                return _real(*a, **k)
            setattr(runner, f"_run_{name}", counted)
        return runner, calls

    runner, calls = runner_counting()
    with torch.no_grad():
        graphed_frame(runner, x0, v0, C, F)
        graphed_frame(runner, x0, v0, C, F)
    assert calls == {"forward": 2, "backward": 0}  # warm-up + capture of the forward only; replays run nothing
    assert runner._fwd_graph is not None and runner._bwd_graph is None
    v = v0.clone().requires_grad_(True)
    out = graphed_frame(runner, x0, v, C, F)
    torch.autograd.grad(out[0].sum(), v)
    backward_runs = 2 * (2 if runner.stashes else 1)  # warm-up + capture (and the stash's replay graph)
    assert calls == {"forward": 2, "backward": backward_runs} and runner._bwd_graph is not None
    out = graphed_frame(runner, x0, v, C, F)
    torch.autograd.grad(out[0].sum(), v)
    assert calls == {"forward": 2, "backward": backward_runs}  # captured once
    # negative control: the runner's forward as the reverse sweep calls it captures both passes at once
    sweep, calls = runner_counting()
    sweep.forward(x0, v0, C, F)
    assert calls == {"forward": 2, "backward": backward_runs} and sweep._bwd_graph is not None
