"""LoRA on the neural laws: identity at init, parameter counts, gradient routing, merge, scale."""

import copy

import pytest
import torch
from torch import nn

from gca.laws.lora import (LoRALinear, apply_lora, count_trainable, full_finetune, lora_layers, merged_weights,
                           lora_parameters, lora_state_dict, merge_lora, set_lora_scale)
from gca.laws.neural import NeuralElasticity, NeuralLawConfig, NeuralPlasticity

from test_laws_neural import random_F


def lora_count(widths, rank):
    """Hand formula: sum over the layers 13 -> widths -> 9 of r * (in + out)."""
    sizes = (13, *widths, 9)
    return sum(rank * (a + b) for a, b in zip(sizes[:-1], sizes[1:]))


def full_count(widths):
    """Hand formula: sum over the layers of in * out (no biases)."""
    sizes = (13, *widths, 9)
    return sum(a * b for a, b in zip(sizes[:-1], sizes[1:]))


def perturb_B(module, seed, std=0.1):
    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for layer in lora_layers(module):
            layer.lora_B.copy_(std * torch.randn(layer.lora_B.shape, generator=g, dtype=layer.lora_B.dtype))


@pytest.mark.parametrize("law_cls", [NeuralElasticity, NeuralPlasticity])
def test_adapted_equals_prior_at_init_bit_for_bit(law_cls):
    torch.manual_seed(0)
    law = law_cls()
    F = random_F(50, 1, torch.float32)
    before = law(F).detach()
    apply_lora(law, rank=16, alpha=16.0, generator=torch.Generator().manual_seed(2))
    assert len(lora_layers(law)) == 3
    assert torch.equal(law(F), before)
    assert all(layer.lora_A.abs().max() > 0 for layer in lora_layers(law))  # A initialised, B = 0


@pytest.mark.parametrize("widths,rank", [((64, 64), 16), ((32, 16, 8), 3)])
@pytest.mark.parametrize("law_cls", [NeuralElasticity, NeuralPlasticity])
def test_trainable_counts(law_cls, widths, rank):
    law = law_cls(NeuralLawConfig(widths=widths))
    assert count_trainable(law) == full_count(widths)
    apply_lora(law, rank=rank, alpha=rank)
    assert count_trainable(law) == lora_count(widths, rank)
    assert sum(p.numel() for p in lora_parameters(law)) == lora_count(widths, rank)
    fresh = full_finetune(law_cls(NeuralLawConfig(widths=widths)).requires_grad_(False))
    assert count_trainable(fresh) == full_count(widths)


def test_paper_scale_counts_by_hand():
    # reference notes 4.1: 4,448 LoRA parameters vs 5,504 base parameters per network (r = 16)
    assert count_trainable(apply_lora(NeuralElasticity(), 16, 16.0)) == 4448
    assert count_trainable(NeuralPlasticity()) == 5504


def test_only_adapter_parameters_get_gradients():
    law = apply_lora(NeuralElasticity().double(), rank=4, alpha=8.0)
    F = random_F(20, 3)
    law(F).square().mean().backward()
    for name, p in law.named_parameters():
        is_lora = name.rsplit(".", 1)[-1] in ("lora_A", "lora_B")
        assert p.requires_grad == is_lora, name
        assert (p.grad is not None) == is_lora, name
    # at init B = 0, so dL/dA = 0 exactly but dL/dB != 0; after a step on B both are non-zero
    assert all(layer.lora_B.grad.abs().max() > 0 for layer in lora_layers(law))
    torch.optim.SGD(lora_parameters(law), lr=1e-3).step()
    law.zero_grad()
    law(F).square().mean().backward()
    assert all(layer.lora_A.grad.abs().max() > 0 for layer in lora_layers(law))


@pytest.mark.parametrize("law_cls", [NeuralElasticity, NeuralPlasticity])
def test_merge_equals_unmerged_and_scale(law_cls):
    torch.manual_seed(4)
    prior = law_cls().double()
    law = apply_lora(law_cls().double(), rank=4, alpha=2.0)
    law.load_state_dict({**law.state_dict(), **prior.state_dict()})
    perturb_B(law, 5)
    F = random_F(30, 6)
    adapted = law(F).detach()
    assert (adapted - prior(F)).abs().max() > 1e-6  # the adapter changes the law
    set_lora_scale(law, 0.0)
    assert torch.equal(law(F), prior(F))  # scale 0 is the prior, bit for bit
    set_lora_scale(law, 2.5)
    merged_25 = merge_lora(copy.deepcopy(law))(F)
    torch.testing.assert_close(merged_25, law(F), rtol=1e-12, atol=1e-9)
    set_lora_scale(law, 1.0)
    merged = merge_lora(copy.deepcopy(law))
    assert not lora_layers(merged) and all(type(m) is nn.Linear for m in merged.mlp if m._parameters)
    torch.testing.assert_close(merged(F), adapted, rtol=1e-12, atol=1e-9)
    assert set(merged.state_dict()) == set(prior.state_dict())  # deployable as a prior


def test_lora_state_dict_and_errors():
    law = apply_lora(NeuralPlasticity(), rank=2, alpha=2.0)
    keys = set(lora_state_dict(law))
    assert keys == {f"mlp.{i}.{ab}" for i in (0, 2, 4) for ab in ("lora_A", "lora_B")}
    with pytest.raises(ValueError, match="already has LoRA"):
        apply_lora(law, 2, 2.0)
    with pytest.raises(ValueError, match="merge_lora"):
        full_finetune(law)
    with pytest.raises(ValueError, match="no LoRA layers"):
        set_lora_scale(NeuralPlasticity(), 0.5)
    with pytest.raises(ValueError, match="no nn.Linear"):
        apply_lora(nn.GELU(), 2, 2.0)
    with pytest.raises(ValueError, match="rank"):
        LoRALinear(nn.Linear(3, 3, bias=False), rank=0, alpha=1.0)


@pytest.mark.grad
def test_merged_forward_equals_lowrank_path_float64():
    """The merged-weight forward equals the rank-r path in values and in the gradients of x, A, B."""
    g = torch.Generator().manual_seed(3)
    layer = LoRALinear(torch.nn.Linear(13, 64, bias=False).double(), rank=4, alpha=8.0, generator=g)
    with torch.no_grad():
        layer.lora_B.normal_(generator=g)
    layer.scale = 0.7
    x = torch.randn(50, 13, dtype=torch.float64, generator=g, requires_grad=True)
    y, y_ref = layer(x), layer.forward_lowrank(x)
    torch.testing.assert_close(y, y_ref, rtol=1e-13, atol=1e-13)
    w = torch.randn_like(y)
    grads = torch.autograd.grad((y * w).sum(), (x, layer.lora_A, layer.lora_B))
    grads_ref = torch.autograd.grad((y_ref * w).sum(), (x, layer.lora_A, layer.lora_B))
    for a, b in zip(grads, grads_ref):
        torch.testing.assert_close(a, b, rtol=1e-12, atol=1e-12)
    merged = lambda x, A, B: torch.func.functional_call(layer, {"lora_A": A, "lora_B": B}, (x,))  # noqa: E731
    assert torch.autograd.gradcheck(merged, (x[:3].detach().requires_grad_(), layer.lora_A.detach().requires_grad_(),
                                             layer.lora_B.detach().requires_grad_()))


def _count_merges(monkeypatch):
    """Count calls of LoRALinear.delta_weight (one per formed merged weight)."""
    calls = []
    original = LoRALinear.delta_weight

    def counting(self):
        calls.append(self)
        return original(self)

    monkeypatch.setattr(LoRALinear, "delta_weight", counting)
    return calls


def test_merged_weights_block_forms_each_merge_once_with_the_same_values_and_gradients(monkeypatch):
    torch.manual_seed(0)
    law = apply_lora(NeuralElasticity(NeuralLawConfig(widths=(8, 8))).double(), rank=2, alpha=2.0)
    perturb_B(law, 1)
    Fs = [random_F(20, seed, torch.float64) for seed in (1, 2, 3)]
    params = list(lora_parameters(law))
    calls = _count_merges(monkeypatch)
    ref_loss = sum((law(F) ** 2).sum() for F in Fs)  # the per-call merge: 3 layers x 3 calls
    assert len(calls) == 9
    ref = torch.autograd.grad(ref_loss, params)
    calls.clear()
    with merged_weights(law):
        with merged_weights(law):  # nested: reuses the outer merge
            loss = sum((law(F) ** 2).sum() for F in Fs)
    assert len(calls) == 3
    assert all(layer._merged is None for layer in lora_layers(law))  # cleared on exit
    torch.testing.assert_close(loss, ref_loss, rtol=1e-13, atol=0)
    for a, b in zip(torch.autograd.grad(loss, params), ref):
        assert float(b.abs().max()) > 0
        torch.testing.assert_close(a, b, rtol=1e-12, atol=1e-14)


def test_a_simulated_frame_merges_once_not_per_step(monkeypatch):
    import gca.sim.frame as frame
    from gca.laws.base import Material
    from gca.sim import MPMSolver, SimConfig

    torch.manual_seed(0)
    cfg = NeuralLawConfig(widths=(8, 8), stress_scale=2e3, alpha=1e-2)
    el, pl = (apply_lora(net, rank=2, alpha=2.0) for net in (NeuralElasticity(cfg), NeuralPlasticity(cfg)))
    perturb_B(el, 1)
    perturb_B(pl, 2)
    material = Material(el, pl, 1000.0).double()
    solver = MPMSolver(SimConfig(n_grid=8, dt=1e-3, bound=1, dtype="float64", max_refine=1))
    g = torch.Generator().manual_seed(3)
    x = (0.4 + 0.2 * torch.rand(30, 3, generator=g)).double()
    v = (0.3 * torch.randn(30, 3, generator=g)).double().requires_grad_(True)
    vol = torch.full((30,), 2e-6, dtype=torch.float64)
    C = torch.zeros(30, 3, 3, dtype=torch.float64)
    F = torch.eye(3, dtype=torch.float64).expand(30, 3, 3).contiguous()
    params = [v, *lora_parameters(material)]

    def run():
        out = frame.simulate_frame_trial(solver, material, 4, x, v, C, F, vol, vol * 1000.0)
        loss = (out[0] ** 2).sum() + (out[3] ** 2).sum() + out[4].sum()
        return loss, torch.autograd.grad(loss, params)

    calls = _count_merges(monkeypatch)
    loss, grads = run()
    assert len(calls) == 6  # 3 layers x 2 networks, once for the frame's 4 steps
    import contextlib
    monkeypatch.setattr(frame, "merged_weights", lambda m: contextlib.nullcontext())  # the per-step merge
    calls.clear()
    ref_loss, ref = run()
    assert len(calls) == 24  # negative control: 6 layers x 4 steps
    torch.testing.assert_close(loss, ref_loss, rtol=1e-13, atol=0)
    for a, b in zip(grads, ref):
        assert float(b.abs().max()) > 0
        torch.testing.assert_close(a, b, rtol=1e-11, atol=1e-15)
