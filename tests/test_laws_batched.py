"""gca.laws.batched: several runs' neural laws in one batch (features and heads over all particles, one bmm per
layer) against each run's law on its slice (CompositeMaterial), in values and gradients."""

import pytest
import torch

from gca.laws.base import CompositeMaterial
from gca.laws.batched import BatchedElasticity, runs_material
from gca.laws.lora import lora_parameters, merged_weights

from test_laws_neural import random_F
from test_sim_graph import _law

F64 = torch.float64


def _runs(n_runs=3, seed=0):
    """Runs' LoRA-adapted neural materials (float64), each with its own base weights and adapters."""
    return [_law(seed=seed + r) for r in range(n_runs)]


@pytest.mark.parametrize("merged", [False, True])
def test_batched_laws_equal_each_run_on_its_slice(merged):
    mats = _runs()
    n = 20
    F = random_F(3 * n, 4, F64)
    batched, reference = runs_material(mats, [n] * 3), CompositeMaterial(mats, [n] * 3)
    assert isinstance(batched.elasticity, BatchedElasticity)
    params = [p for m in mats for p in lora_parameters(m)]
    results = []
    for material in (batched, reference):
        Fx = F.clone().requires_grad_()
        with merged_weights(material) if merged else torch.enable_grad():
            loss = (material.stress(Fx) ** 2).sum() * 1e-6 + (material.project(Fx) ** 2).sum()
        results.append((loss, *torch.autograd.grad(loss, [Fx, *params])))
    for a, b in zip(*results):
        assert float(b.detach().abs().max()) > 0
        torch.testing.assert_close(a, b, rtol=1e-12, atol=1e-15)


def test_batched_laws_fall_back_to_per_run_slices():
    mats = _runs(2)
    assert isinstance(runs_material(mats, [10, 12]), CompositeMaterial)  # unequal slices
    with pytest.raises(ValueError, match="2 runs x 10 particles expected"):
        runs_material(mats, [10, 10]).stress(random_F(21, 0, F64))
    batched = runs_material(mats, [10, 10])
    for net in (*batched.elasticity.nets, *batched.plasticity.nets):
        net.fast_path = False  # the torch reference path: each run on its slice
    F = random_F(20, 1, F64)
    torch.testing.assert_close(batched.stress(F), CompositeMaterial(mats, [10, 10]).stress(F), rtol=1e-12, atol=0)


def test_a_batch_that_mixed_the_runs_weights_would_be_caught(monkeypatch):
    # negative control: every run given run 0's weights must fail the comparison above
    import gca.laws.batched as batched_mod
    real = batched_mod.effective_weight
    first = {}
    monkeypatch.setattr(batched_mod, "effective_weight",
                        lambda layer: first.setdefault(tuple(layer.weight.shape), real(layer)))
    mats = _runs()
    F = random_F(60, 4, F64)
    with pytest.raises(AssertionError):
        torch.testing.assert_close(runs_material(mats, [20] * 3).stress(F), CompositeMaterial(mats, [20] * 3).stress(F),
                                   rtol=1e-12, atol=1e-15)


@pytest.mark.grad
def test_batched_linear_gradcheck_float64():
    from gca.laws.batched import batched_linear

    g = torch.Generator().manual_seed(0)
    h = torch.randn(3, 7, 5, generator=g, dtype=F64, requires_grad=True)
    W = torch.randn(3, 4, 5, generator=g, dtype=F64, requires_grad=True)
    assert torch.autograd.gradcheck(batched_linear, (h, W))
    torch.testing.assert_close(batched_linear(h, W), torch.bmm(h, W.transpose(1, 2)), rtol=1e-14, atol=0)
