"""Checkpoints of neural-law priors (``models/prior/<family>.pt``) and of LoRA adapters.

A **prior** file holds the full networks: ``{kind: "gca.prior", version, family, config, elasticity,
plasticity, metadata}`` where ``config`` is the :class:`NeuralLawConfig` as a dict and the two
entries are state dicts. Loading rebuilds the networks from the stored config.

An **adapter** file holds only what LoRA trained: ``{kind: "gca.adapter", version, lora: {rank,
alpha}, prior: {family, architecture, digest}, elasticity, plasticity, metadata}`` with adapter-only
state dicts (``lora_A``/``lora_B``). ``digest`` fingerprints the prior's base weights, so an adapter
is never silently applied to a different prior.

Loading refuses, with a message naming the file and the mismatch: a wrong kind or version, another
architecture (widths, activation) or output scaling, another LoRA rank/alpha, another prior family or
other prior weights. Writes are atomic and byte-stable (``gca.io.save_torch``); reads use ``weights_only=True``.
"""

from __future__ import annotations

import dataclasses
import hashlib
import os
from pathlib import Path
from typing import Any, Mapping

import torch
from torch import nn

from gca.io import save_torch
from gca.laws.lora import lora_layers, lora_state_dict
from gca.laws.neural import NeuralElasticity, NeuralLawConfig, NeuralPlasticity

VERSION = 1
PRIOR_KIND = "gca.prior"
ADAPTER_KIND = "gca.adapter"


class CheckpointError(ValueError):
    """A checkpoint file is unreadable or does not match what it is loaded into."""


@dataclasses.dataclass(frozen=True)
class Prior:
    """A loaded prior M_0 = {E_0, P_0} with its provenance."""

    elasticity: NeuralElasticity
    plasticity: NeuralPlasticity
    family: str  # material family it was pretrained on ("jelly", "plasticine", "sand", ...)
    config: NeuralLawConfig
    metadata: dict


def _config_dict(cfg: NeuralLawConfig) -> dict:
    out = dataclasses.asdict(cfg)
    out["widths"] = list(cfg.widths)
    return out


def _shared_config(elasticity: nn.Module, plasticity: nn.Module, path: Path) -> NeuralLawConfig:
    if not isinstance(elasticity, NeuralElasticity) or not isinstance(plasticity, NeuralPlasticity):
        raise CheckpointError(f"{path}: expected NeuralElasticity and NeuralPlasticity, got "
                              f"{type(elasticity).__name__} and {type(plasticity).__name__}")
    if elasticity.cfg != plasticity.cfg:
        raise CheckpointError(f"{path}: elasticity and plasticity configs differ: {elasticity.cfg} vs {plasticity.cfg}")
    return elasticity.cfg


def base_state_dict(module: nn.Module) -> dict[str, torch.Tensor]:
    """The non-adapter entries of ``module.state_dict()`` (the prior's weights, also under LoRA)."""
    return {k: v for k, v in module.state_dict().items() if k.rsplit(".", 1)[-1] not in ("lora_A", "lora_B")}


def prior_digest(elasticity: nn.Module, plasticity: nn.Module) -> str:
    """SHA-256 of the base weights of both networks (dtype-independent: hashed as float64)."""
    h = hashlib.sha256()
    for name, module in (("elasticity", elasticity), ("plasticity", plasticity)):
        for key, value in sorted(base_state_dict(module).items()):
            h.update(f"{name}.{key}:{tuple(value.shape)}".encode())
            h.update(value.detach().cpu().to(torch.float64).contiguous().numpy().tobytes())
    return h.hexdigest()


def _save(path: str | os.PathLike, payload: dict) -> Path:
    return save_torch(payload, path)


def _read(path: str | os.PathLike, kind: str) -> dict:
    path = Path(path)
    if not path.is_file():
        raise CheckpointError(f"{path}: checkpoint not found")
    try:
        payload = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # torch raises several types for corrupt files
        raise CheckpointError(f"{path}: not a readable torch checkpoint: {exc}") from exc
    if not isinstance(payload, Mapping) or payload.get("kind") != kind:
        found = payload.get("kind") if isinstance(payload, Mapping) else type(payload).__name__
        raise CheckpointError(f"{path}: expected a {kind!r} checkpoint, found {found!r}")
    if payload.get("version") != VERSION:
        raise CheckpointError(f"{path}: {kind} version {payload.get('version')!r}, this code reads {VERSION}")
    return dict(payload)


def _mismatch(path: Path, what: str, found: Any, expected: Any) -> None:
    if found != expected:
        raise CheckpointError(f"{path}: {what} mismatch: checkpoint has {found!r}, expected {expected!r}")


def save_prior(path: str | os.PathLike, elasticity: NeuralElasticity, plasticity: NeuralPlasticity,
               family: str, metadata: Mapping | None = None) -> Path:
    """Atomically write a prior (config + full state dicts + family + JSON-like metadata)."""
    path = Path(path)
    cfg = _shared_config(elasticity, plasticity, path)
    if lora_layers(elasticity) or lora_layers(plasticity):
        raise CheckpointError(f"{path}: save_prior: networks carry LoRA layers; merge_lora() them first "
                              f"or save the adapter with save_adapter()")
    payload = {"kind": PRIOR_KIND, "version": VERSION, "family": str(family), "config": _config_dict(cfg),
               "elasticity": {k: v.detach().cpu().clone() for k, v in elasticity.state_dict().items()},
               "plasticity": {k: v.detach().cpu().clone() for k, v in plasticity.state_dict().items()},
               "metadata": dict(metadata or {})}
    return _save(path, payload)


def _check_config(path: Path, stored: NeuralLawConfig, expected: NeuralLawConfig) -> None:
    _mismatch(path, "architecture (widths, activation)", stored.architecture(), expected.architecture())
    _mismatch(path, "output scaling (stress_scale, alpha)", (stored.stress_scale, stored.alpha),
              (expected.stress_scale, expected.alpha))


def load_prior(path: str | os.PathLike, family: str | None = None,
               config: NeuralLawConfig | None = None) -> Prior:
    """Load a prior written by :func:`save_prior` (networks in float32, on the CPU, trainable).

    Args:
        path: the ``.pt`` file.
        family: if given, the file's family must equal it.
        config: if given, the file's config must equal it (architecture and output scaling).

    Returns:
        A :class:`Prior`.
    """
    path = Path(path)
    payload = _read(path, PRIOR_KIND)
    try:
        stored = NeuralLawConfig(**payload["config"])
    except (TypeError, ValueError) as exc:
        raise CheckpointError(f"{path}: malformed config {payload.get('config')!r}: {exc}") from exc
    if family is not None:
        _mismatch(path, "prior family", payload["family"], family)
    if config is not None:
        _check_config(path, stored, config)
    elasticity, plasticity = NeuralElasticity(stored), NeuralPlasticity(stored)
    for name, module in (("elasticity", elasticity), ("plasticity", plasticity)):
        try:
            module.load_state_dict(payload[name])
        except RuntimeError as exc:
            raise CheckpointError(f"{path}: {name} weights do not fit the stored config: {exc}") from exc
    return Prior(elasticity, plasticity, payload["family"], stored, dict(payload["metadata"]))


def _lora_hparams(module: nn.Module, path: Path) -> tuple[int, float]:
    layers = lora_layers(module)
    if not layers:
        raise CheckpointError(f"{path}: {type(module).__name__} has no LoRA layers (call apply_lora first)")
    hparams = {(layer.rank, layer.alpha) for layer in layers}
    if len(hparams) != 1:
        raise CheckpointError(f"{path}: {type(module).__name__} mixes LoRA (rank, alpha) values {sorted(hparams)}")
    return hparams.pop()


def save_adapter(path: str | os.PathLike, elasticity: NeuralElasticity, plasticity: NeuralPlasticity,
                 family: str, metadata: Mapping | None = None) -> Path:
    """Atomically write the LoRA adapters of both networks (adapter weights only) and their prior's identity."""
    path = Path(path)
    cfg = _shared_config(elasticity, plasticity, path)
    rank, alpha = _lora_hparams(elasticity, path)
    _mismatch(path, "plasticity LoRA (rank, alpha)", _lora_hparams(plasticity, path), (rank, alpha))
    payload = {"kind": ADAPTER_KIND, "version": VERSION, "lora": {"rank": rank, "alpha": alpha},
               "prior": {"family": str(family), "architecture": cfg.architecture(),
                         "digest": prior_digest(elasticity, plasticity)},
               "elasticity": lora_state_dict(elasticity), "plasticity": lora_state_dict(plasticity),
               "metadata": dict(metadata or {})}
    return _save(path, payload)


def load_adapter(path: str | os.PathLike, elasticity: NeuralElasticity, plasticity: NeuralPlasticity,
                 family: str) -> dict:
    """Load adapter weights into LoRA-wrapped prior networks (in place).

    Args:
        path: file written by :func:`save_adapter`.
        elasticity, plasticity: the prior networks after ``apply_lora`` with the adapter's rank/alpha.
        family: the family of that prior; must equal the adapter's.

    Returns:
        The adapter's metadata.
    """
    path = Path(path)
    payload = _read(path, ADAPTER_KIND)
    cfg = _shared_config(elasticity, plasticity, path)
    stored = payload["prior"]
    _mismatch(path, "prior family", stored["family"], family)
    _mismatch(path, "architecture (widths, activation)", stored["architecture"], cfg.architecture())
    for module in (elasticity, plasticity):
        _mismatch(path, f"LoRA (rank, alpha) of {type(module).__name__}",
                  (payload["lora"]["rank"], payload["lora"]["alpha"]), _lora_hparams(module, path))
    _mismatch(path, "prior weights digest (adapter trained on another prior)", stored["digest"],
              prior_digest(elasticity, plasticity))
    for name, module in (("elasticity", elasticity), ("plasticity", plasticity)):
        _load_adapter_entries(path, name, module, payload[name])
    return dict(payload["metadata"])


def _load_adapter_entries(path: Path, name: str, module: nn.Module, entries: Mapping) -> None:
    expected = set(lora_state_dict(module))
    if set(entries) != expected:
        raise CheckpointError(f"{path}: {name} adapter keys differ: missing {sorted(expected - set(entries))}, "
                              f"unexpected {sorted(set(entries) - expected)}")
    result = module.load_state_dict(dict(entries), strict=False)
    if result.unexpected_keys:
        raise CheckpointError(f"{path}: {name} adapter has unexpected keys {result.unexpected_keys}")
