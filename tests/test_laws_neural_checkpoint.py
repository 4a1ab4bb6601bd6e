"""Prior and adapter checkpoints: round trips and refusals with clear messages."""

import pytest
import torch

from gca.laws.checkpoint import (CheckpointError, load_adapter, load_prior, prior_digest, save_adapter,
                                 save_prior)
from gca.laws.lora import apply_lora, lora_layers
from gca.laws.neural import NeuralElasticity, NeuralLawConfig, NeuralPlasticity

from test_laws_neural import random_F
from test_laws_lora import perturb_B

CFG = NeuralLawConfig(widths=(16, 8), stress_scale=5e3)


def make_prior(cfg=CFG, seed=0):
    torch.manual_seed(seed)
    return NeuralElasticity(cfg), NeuralPlasticity(cfg)


def test_prior_round_trip(tmp_path):
    E, P = make_prior()
    path = save_prior(tmp_path / "prior" / "jelly.pt", E, P, "jelly", {"epochs": 3, "loss": 0.5})
    assert [p.name for p in path.parent.iterdir()] == ["jelly.pt"]  # atomic: no temporary left behind
    prior = load_prior(path, family="jelly", config=CFG)
    assert prior.family == "jelly" and prior.config == CFG and prior.metadata == {"epochs": 3, "loss": 0.5}
    F = random_F(10, 1, torch.float32)
    assert torch.equal(prior.elasticity(F), E(F)) and torch.equal(prior.plasticity(F), P(F))
    assert load_prior(path).config == CFG  # no expectations: the stored config rebuilds the networks


@pytest.mark.parametrize("kwargs,match", [
    (dict(family="sand"), "prior family mismatch.*'jelly'.*'sand'"),
    (dict(config=NeuralLawConfig(widths=(16, 16), stress_scale=5e3)), "architecture.*widths"),
    (dict(config=NeuralLawConfig(widths=(16, 8), activation="tanh", stress_scale=5e3)), "architecture"),
    (dict(config=NeuralLawConfig(widths=(16, 8))), "output scaling"),
])
def test_prior_mismatch_errors(tmp_path, kwargs, match):
    path = save_prior(tmp_path / "jelly.pt", *make_prior(), "jelly")
    with pytest.raises(CheckpointError, match=match) as info:
        load_prior(path, **kwargs)
    assert str(path) in str(info.value)


def test_prior_refuses_lora_and_wrong_kind(tmp_path):
    E, P = make_prior()
    with pytest.raises(CheckpointError, match="merge_lora"):
        save_prior(tmp_path / "x.pt", apply_lora(E, 2, 2.0), P, "jelly")
    assert not (tmp_path / "x.pt").exists()
    with pytest.raises(CheckpointError, match="not found"):
        load_prior(tmp_path / "missing.pt")
    torch.save({"kind": "something"}, tmp_path / "other.pt")
    with pytest.raises(CheckpointError, match="expected a 'gca.prior'"):
        load_prior(tmp_path / "other.pt")


def adapted(tmp_path, rank=4, family="jelly", cfg=CFG, seed=0):
    """Save a prior, load it, wrap with LoRA and perturb the adapter (as training would)."""
    prior_path = save_prior(tmp_path / f"{family}.pt", *make_prior(cfg, seed), family)
    prior = load_prior(prior_path)
    E, P = apply_lora(prior.elasticity, rank, rank), apply_lora(prior.plasticity, rank, rank)
    perturb_B(E, 1), perturb_B(P, 2)
    return prior_path, E, P


def test_adapter_round_trip(tmp_path):
    prior_path, E, P = adapted(tmp_path)
    path = save_adapter(tmp_path / "adapter.pt", E, P, "jelly", {"epoch": 7})
    payload = torch.load(path, weights_only=True)
    n_adapter = sum(t.numel() for t in payload["elasticity"].values())
    assert n_adapter == sum(l.lora_A.numel() + l.lora_B.numel() for l in lora_layers(E))  # adapter only
    prior = load_prior(prior_path)
    E2, P2 = apply_lora(prior.elasticity, 4, 4), apply_lora(prior.plasticity, 4, 4)
    F = random_F(10, 3, torch.float32)
    assert not torch.equal(E2(F), E(F))
    assert load_adapter(path, E2, P2, "jelly") == {"epoch": 7}
    assert torch.equal(E2(F), E(F)) and torch.equal(P2(F), P(F))


def test_adapter_mismatch_errors(tmp_path):
    _, E, P = adapted(tmp_path)
    path = save_adapter(tmp_path / "adapter.pt", E, P, "jelly")

    def fresh(rank=4, cfg=CFG, seed=0, family="jelly"):
        prior = load_prior(save_prior(tmp_path / "p2.pt", *make_prior(cfg, seed), family))
        return apply_lora(prior.elasticity, rank, rank), apply_lora(prior.plasticity, rank, rank)

    with pytest.raises(CheckpointError, match=r"adapter\.pt: LoRA \(rank, alpha\).*\(4, 4\.0\).*\(8, 8\.0\)"):
        load_adapter(path, *fresh(rank=8), "jelly")
    with pytest.raises(CheckpointError, match="architecture.*16, 8.*16, 16"):
        load_adapter(path, *fresh(cfg=NeuralLawConfig(widths=(16, 16), stress_scale=5e3)), "jelly")
    with pytest.raises(CheckpointError, match="prior family mismatch.*'jelly'.*'sand'"):
        load_adapter(path, *fresh(), "sand")
    with pytest.raises(CheckpointError, match="another prior"):
        load_adapter(path, *fresh(seed=9), "jelly")
    with pytest.raises(CheckpointError, match="no LoRA layers"):
        load_adapter(path, *make_prior(), "jelly")
    with pytest.raises(CheckpointError, match="expected a 'gca.adapter'"):
        load_adapter(tmp_path / "jelly.pt", *fresh(), "jelly")


def test_digest_ignores_dtype_and_adapter(tmp_path):
    E, P = make_prior()
    d = prior_digest(E, P)
    assert prior_digest(E.double(), P.double()) == d
    assert prior_digest(apply_lora(E, 2, 2.0), P) == d
    with torch.no_grad():
        P.mlp[0].weight[0, 0] += 1e-3
    assert prior_digest(E, P) != d
