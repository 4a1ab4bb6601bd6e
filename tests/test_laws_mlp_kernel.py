"""gca.laws.mlp_kernel: the neural laws' MLP as one warp tile kernel each way (``warp``) and as a one-thread-per-particle
forward with torch's backward (``simt``), against torch's nn.Sequential (CPU twins of the CUDA paths): values and
gradients in float64 for every activation, float64 gradient checks with negative controls, the laws' ``mlp_kernel``
switch with LoRA inside a merged frame, and a short MPM rollout."""

import pytest
import torch
from torch import nn
from torch.autograd import gradcheck

from gca.laws import mlp_kernel as mk
from gca.laws.lora import apply_lora, lora_parameters, merged_weights
from gca.laws.neural import ACTIVATIONS, NeuralElasticity, NeuralLawConfig, NeuralPlasticity, make_mlp

from test_laws_neural import random_F, scramble
from test_laws_neural_fused import hard_F

f64 = torch.float64


def _net(activation="gelu", widths=(64, 64), seed=0) -> nn.Sequential:
    torch.manual_seed(seed)
    return make_mlp(NeuralLawConfig(widths=widths, activation=activation)).double()


def _weights(net: nn.Sequential) -> list[torch.Tensor]:
    return [net[i].weight.detach().clone().requires_grad_(True) for i in (0, 2, 4)]


def test_activations_cover_the_laws():
    assert set(mk.ACTIVATIONS) == set(ACTIVATIONS)


def _matches_torch(run, net: nn.Sequential, n: int) -> tuple[torch.Tensor, torch.Tensor, list[torch.Tensor]]:
    """``run(z, Ws)`` against ``net(z)``: values and the gradients to z and the three weights, float64, 1e-13
    relative; returns (X, z, Ws)."""
    z = torch.randn(n, 13, dtype=f64, generator=torch.Generator().manual_seed(1)).requires_grad_(True)
    Ws = _weights(net)
    X, ref = run(z, Ws), net(z)
    v = torch.randn(X.shape, dtype=f64, generator=torch.Generator().manual_seed(2))
    got = torch.autograd.grad(X, [z, *Ws], v)
    want = torch.autograd.grad(ref, [z, net[0].weight, net[2].weight, net[4].weight], v)
    torch.testing.assert_close(X, ref, rtol=0, atol=1e-13 * float(ref.detach().abs().max()))
    for a, b in zip(got, want):
        torch.testing.assert_close(a, b, rtol=0, atol=1e-13 * float(b.abs().max()))
    return X, z, Ws


@pytest.mark.parametrize("activation", sorted(ACTIVATIONS))
@pytest.mark.parametrize("n", [37, 16, 200])  # a partial last tile, whole tiles, blocks that loop over several tiles
def test_tile_mlp_equals_torch_values_and_gradients(activation, n):
    net = _net(activation)
    shape = mk.shape_of(net)
    assert shape == mk.MLPShape(13, 64, 64, 9, activation)
    _matches_torch(lambda z, Ws: mk.mlp(z, Ws, shape), net, n)


@pytest.mark.parametrize("activation", sorted(ACTIVATIONS))
def test_simt_mlp_equals_torch_values_and_gradients(activation):
    net = _net(activation)
    run = lambda z, Ws: mk.simt_mlp(z, Ws, mk.shape_of(net), net[1])  # noqa: E731
    X, z, Ws = _matches_torch(run, net, 37)
    with torch.no_grad():  # no gradient wanted: the pre-activations are not stored, the values are the same
        torch.testing.assert_close(run(z, Ws), X.detach(), rtol=0, atol=0)


def test_simt_stores_pre_activations_only_when_a_gradient_is_wanted(monkeypatch):
    net = _net()
    shape = mk.shape_of(net)
    z = torch.randn(20, 13, dtype=f64, requires_grad=True)
    Ws = _weights(net)
    saves = []
    real = mk._SimtMLP.apply
    monkeypatch.setattr(mk._SimtMLP, "apply", lambda *a: saves.append(a[-1]) or real(*a))
    with torch.no_grad():  # the simulation's forward: Ws require grad (LoRA), but nothing will be differentiated
        mk.simt_mlp(z, Ws, shape, net[1])
    mk.simt_mlp(z.detach(), [W.detach() for W in Ws], shape, net[1])  # nothing requires grad
    mk.simt_mlp(z, Ws, shape, net[1])  # the recomputed frame: a gradient follows
    assert saves == [False, False, True]


@pytest.mark.grad
def test_simt_mlp_gradcheck_float64_and_its_negative_control():
    net = _net("gelu", widths=(8, 6))
    z = torch.randn(21, 13, dtype=f64, generator=torch.Generator().manual_seed(3)).requires_grad_(True)
    shape = mk.shape_of(net)
    assert gradcheck(lambda z, *Ws: mk.simt_mlp(z, list(Ws), shape, net[1]), (z, *_weights(net)))
    # the backward takes the derivative from the activation module it is given: SiLU's for a GELU forward must fail
    assert not gradcheck(lambda z, *Ws: mk.simt_mlp(z, list(Ws), shape, nn.SiLU()), (z, *_weights(net)),
                         raise_exception=False)


@pytest.mark.grad
def test_tile_mlp_gradcheck_float64():
    net = _net("gelu", widths=(8, 6))
    z = torch.randn(21, 13, dtype=f64, generator=torch.Generator().manual_seed(3)).requires_grad_(True)
    shape = mk.shape_of(net)
    assert gradcheck(lambda z, *Ws: mk.mlp(z, list(Ws), shape), (z, *_weights(net)))


@pytest.mark.grad
def test_gradcheck_catches_a_wrong_activation_derivative(monkeypatch):
    # negative control: GELU forward with SiLU's derivative in the backward must fail the check above
    real = mk._activation

    def mixed(name, T, module):
        act, _ = real("gelu", T, module)
        return act, real("silu", T, module + "_neg")[1]

    monkeypatch.setattr(mk, "_activation", mixed)
    shape = mk.MLPShape(13, 5, 7, 9, "gelu")  # a shape of its own: its cached kernels are this test's alone
    net = nn.Sequential(nn.Linear(13, 5, bias=False), nn.GELU(), nn.Linear(5, 7, bias=False), nn.GELU(),
                        nn.Linear(7, 9, bias=False)).double()
    z = torch.randn(9, 13, dtype=f64, generator=torch.Generator().manual_seed(4)).requires_grad_(True)
    try:
        assert not gradcheck(lambda z, *Ws: mk.mlp(z, list(Ws), shape), (z, *_weights(net)), raise_exception=False)
    finally:
        mk.make_mlp_kernels.cache_clear()


@pytest.mark.parametrize("device", ["cpu", pytest.param("cuda", marks=[pytest.mark.gpu, pytest.mark.skipif(
    not torch.cuda.is_available(), reason="needs a CUDA device")])])
def test_weight_gradients_repeat_bit_for_bit(device):
    # the backward's blocks each sum their tiles' weight gradients on chip and the partials are summed in a fixed
    # order: the same inputs give the same bits. On the CPU warp runs blocks one after another, so any version
    # repeats there; the CUDA case is the one an atomic-per-block version (blocks finishing in any order) would fail.
    n = 300 if device == "cpu" else 30000
    net = _net()
    z = torch.randn(n, 13, generator=torch.Generator().manual_seed(6)).to(device)
    Ws = [W.detach().float().to(device).requires_grad_(True) for W in _weights(net)]
    v = torch.randn(n, 9, generator=torch.Generator().manual_seed(7)).to(device)
    first, second = (torch.autograd.grad(mk.mlp(z, Ws, mk.shape_of(net)), Ws, v) for _ in range(2))
    assert mk.backward_blocks(-(-n // 16), z.device) < -(-n // 16)  # blocks loop over several tiles here
    assert all(torch.equal(a, b) for a, b in zip(first, second))


def test_empty_batch_and_frozen_weights():
    net = _net()
    shape = mk.shape_of(net)
    z = torch.zeros(0, 13, dtype=f64, requires_grad=True)
    X = mk.mlp(z, _weights(net), shape)
    X.sum().backward()
    assert X.shape == (0, 9) and z.grad.shape == (0, 13)
    z = torch.randn(5, 13, dtype=f64, requires_grad=True)
    Ws = [W.detach() for W in _weights(net)]  # the prior's frozen weights: only z gets a gradient
    (g,) = torch.autograd.grad(mk.mlp(z, Ws, shape).square().sum(), [z])
    (want,) = torch.autograd.grad(net(z).square().sum(), [z])
    torch.testing.assert_close(g, want, rtol=1e-12, atol=1e-14)


def test_zero_features_map_to_zero():
    net = _net()
    assert torch.equal(mk.mlp(torch.zeros(3, 13, dtype=f64), _weights(net), mk.shape_of(net)),
                       torch.zeros(3, 9, dtype=f64))  # zero at rest, exactly (bias-free, act(0) = 0)


@pytest.mark.parametrize("net, why", [
    (nn.Sequential(nn.Linear(13, 8, bias=False), nn.GELU(), nn.Linear(8, 9, bias=False)), "one hidden layer"),
    (nn.Sequential(nn.Linear(13, 8), nn.GELU(), nn.Linear(8, 8, bias=False), nn.GELU(), nn.Linear(8, 9, bias=False)),
     "a bias"),
    (nn.Sequential(nn.Linear(13, 8, bias=False), nn.GELU("tanh"), nn.Linear(8, 8, bias=False), nn.GELU("tanh"),
                   nn.Linear(8, 9, bias=False)), "tanh-approximate GELU"),
    (nn.Sequential(nn.Linear(13, 8, bias=False), nn.GELU(), nn.Linear(8, 8, bias=False), nn.Tanh(),
                   nn.Linear(8, 9, bias=False)), "two activations"),
    (nn.Sequential(nn.Linear(13, 8, bias=False), nn.GELU(), nn.Linear(8, 8, bias=False), nn.GELU("tanh"),
                   nn.Linear(8, 9, bias=False)), "an approximate GELU in the second place only"),
])
def test_unfusable_shapes_are_recognised(net, why):
    assert mk.shape_of(net) is None, why


def test_bad_inputs_are_refused():
    net = _net()
    shape = mk.shape_of(net)
    with pytest.raises(ValueError, match="float32 or float64 on one device"):
        mk.mlp(torch.zeros(4, 13, dtype=torch.float16), [W.half() for W in _weights(net)], shape)
    with pytest.raises(ValueError, match=r"z must be \[N, 13\]"):
        mk.mlp(torch.zeros(4, 12, dtype=f64), _weights(net), shape)
    with pytest.raises(ValueError, match="weights must be"):
        mk.mlp(torch.zeros(4, 13, dtype=f64), _weights(net)[::-1], shape)


@pytest.mark.parametrize("law_cls", [NeuralElasticity, NeuralPlasticity])
def test_law_with_the_tile_mlp_equals_the_torch_mlp(law_cls):
    """Whole law with LoRA inside a merged frame: outputs and gradients to F and to the adapters."""
    law = scramble(apply_lora(law_cls(NeuralLawConfig()).double(), rank=4, alpha=4.0), seed=1)
    F = hard_F().requires_grad_(True)
    params = [F, *lora_parameters(law)]
    out = {}
    for kind in ("warp", "simt", "torch"):
        law.mlp_kernel = kind
        with merged_weights(law):
            y = law(F)
            out[kind] = (y, torch.autograd.grad(y.square().sum(), params))
    y_t, g_t = out["torch"]
    for kind in ("warp", "simt"):
        y_w, g_w = out[kind]
        torch.testing.assert_close(y_w, y_t, rtol=0, atol=1e-12 * float(y_t.detach().abs().max()))
        for a, b in zip(g_w, g_t):
            torch.testing.assert_close(a, b, rtol=0, atol=1e-10 * float(b.abs().max()))


def test_mlp_kernel_switch(monkeypatch):
    law = NeuralElasticity().double()
    F = random_F(6, 2)
    calls = []
    real = mk.mlp
    monkeypatch.setattr(mk, "mlp", lambda *a, **k: calls.append(1) or real(*a, **k))
    law(F)  # the default: torch's MLP
    assert law.mlp_kernel == "torch" and calls == []
    law.mlp_kernel = "warp"
    law(F)
    assert calls == [1]
    simt = []
    real_simt = mk.simt_mlp
    monkeypatch.setattr(mk, "simt_mlp", lambda *a, **k: simt.append(1) or real_simt(*a, **k))
    law.mlp_kernel = "simt"
    law(F)
    assert calls == [1] and simt == [1]
    law.mlp_kernel = "fast"
    with pytest.raises(ValueError, match="mlp_kernel='fast' is not one of"):
        law(F)
    shallow = NeuralElasticity(NeuralLawConfig(widths=(16,))).double()
    shallow.mlp_kernel = "warp"
    with pytest.raises(ValueError, match="fuses two hidden layers"):
        shallow(F)


def test_rollout_with_the_tile_mlp_equals_the_torch_mlp():
    """A replayed-frame rollout (the CUDA-graph path's eager twin) of a LoRA neural law: trajectories and gradients
    to the launch velocity and every adapter, with the MLP in the tile kernel and in torch."""
    from gca.sim import MPMSolver, SimConfig

    from test_sim_graph import _law, _loss_and_grads, _scene

    solver = MPMSolver(SimConfig(n_grid=12, dt=1e-3, bound=1, boundary="friction", friction=0.3, dtype="float64",
                                 max_refine=1))
    runs = {}
    for kind in ("warp", "simt", "torch"):
        material = _law()
        for net in (material.elasticity, material.plasticity):
            net.mlp_kernel = kind
        runs[kind] = _loss_and_grads(material, solver, True, *_scene())
    ref, g_ref = runs["torch"]
    for kind in ("warp", "simt"):
        out, g = runs[kind]
        for a, b in ((out.x, ref.x), (out.v, ref.v), (out.F, ref.F), (out.C, ref.C)):
            torch.testing.assert_close(a, b, atol=1e-12, rtol=1e-12)
        assert len(g) == 1 + 12 and all(float(t.abs().max()) > 0 for t in g)
        for a, b in zip(g, g_ref):
            torch.testing.assert_close(a, b, atol=1e-12, rtol=1e-9)


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
@pytest.mark.parametrize("kind", ["simt", "warp"])
def test_frames_with_a_warp_mlp_are_captured_on_cuda(kind):
    """The kernels launch on torch's stream and allocate through torch, so a frame runner captures them in its CUDA
    graphs (a failed capture falls back to eager launches with only a warning: a slowdown, not an error)."""
    from gca.sim import MPMSolver, SimConfig

    from test_sim_graph import _law, _loss_and_grads, _scene

    solver = MPMSolver(SimConfig(n_grid=16, dt=1e-3, bound=1, boundary="sticky", friction=0.0, max_refine=1), "cuda")
    material = _law(torch.float32).to("cuda")
    for net in (material.elasticity, material.plasticity):
        net.mlp_kernel = kind
    _loss_and_grads(material, solver, True, *(t.float().cuda() for t in _scene(dtype=torch.float32)))
    runner = solver.frame_graphs(material, 2, _scene()[0].shape[0])
    assert runner.capture and runner.kernels == (kind, kind)
