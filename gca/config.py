"""One way in for every parameter: ``params.yaml`` read through DVC (or directly in tests).

Profiles. ``params.yaml`` carries a top-level ``profile`` switch (``paper`` or ``ci``). Any knob whose
size depends on the profile is written as a mapping with exactly the profile names as keys::

    n_gaussians: {paper: 100000, ci: 3000}   # Gaussians per object [count]

:func:`resolve` replaces each such mapping with the value of the active profile, so library code only
ever sees plain values. Both values live next to each other, with one comment: one source of truth.

Reading. In a DVC run a stage calls ``load(stage)``; that goes through
``dvc.api.params_show(stages=stage)`` so only the params the stage declares in ``dvc.yaml`` are
visible and reading an undeclared key fails (instead of silently escaping DVC's invalidation).
Outside DVC (tests, ``python stages/x.py --params p.yaml``) the YAML file is read directly.

Typed access. Library sections map to frozen dataclasses; :func:`build` turns a mapping into one and
refuses unknown or missing keys with a message naming the section.
"""

from __future__ import annotations

import dataclasses
import os
import typing
from pathlib import Path
from typing import Any, Mapping, TypeVar

import yaml

PROFILES = ("paper", "ci")
T = TypeVar("T")


class ConfigError(ValueError):
    """A params file or section is malformed (names the file/section and the key)."""


def _is_profile_switch(node: Any) -> bool:
    return isinstance(node, Mapping) and len(node) > 0 and set(node) == set(PROFILES)


def resolve(node: Any, profile: str) -> Any:
    """Replace every ``{paper: a, ci: b}`` mapping in ``node`` by the active profile's value.

    Args:
        node: parsed YAML (nested dicts/lists/scalars).
        profile: ``"paper"`` or ``"ci"``.

    Returns:
        A new tree with plain values (the input is not modified).
    """
    if profile not in PROFILES:
        raise ConfigError(f"unknown profile {profile!r}; expected one of {PROFILES}")
    if _is_profile_switch(node):
        return resolve(node[profile], profile)
    if isinstance(node, Mapping):
        return {k: resolve(v, profile) for k, v in node.items()}
    if isinstance(node, list):
        return [resolve(v, profile) for v in node]
    return node


def read_yaml(path: str | os.PathLike) -> dict:
    """Parse a params YAML file, naming the file in any error."""
    path = Path(path)
    if not path.is_file():
        raise ConfigError(f"{path}: params file not found")
    try:
        tree = yaml.safe_load(path.read_text())
    except yaml.YAMLError as exc:
        raise ConfigError(f"{path}: not valid YAML: {exc}") from exc
    if not isinstance(tree, dict):
        raise ConfigError(f"{path}: top level must be a mapping")
    return tree


def _active_profile(tree: Mapping) -> str:
    profile = tree.get("profile", "paper")
    if profile not in PROFILES:
        raise ConfigError(f"params: profile={profile!r} is not one of {PROFILES}")
    return profile


def _params_via_dvc(stage: str) -> dict:
    import dvc.api  # lazy: ~1 s import, and not installed on the GPU box

    return dict(dvc.api.params_show(stages=stage))


def load(stage: str | None = None, path: str | os.PathLike = "params.yaml",
         via_dvc: bool | None = None) -> dict:
    """Load the resolved params tree for ``stage``.

    Args:
        stage: DVC stage name (``"particles@ball"``); used to restrict the view under DVC.
        path: params file, read directly when not under DVC.
        via_dvc: force/forbid ``dvc.api.params_show``; default: only when DVC is running the stage
            (DVC exports ``DVC_STAGE`` and ``DVC_ROOT`` to stage commands) and ``path`` is the
            repository's ``params.yaml``. Under DVC the stage name DVC gives wins.

    Returns:
        Nested dict with profile switches resolved and ``profile`` kept at the top.
    """
    path = Path(path)
    dvc_stage = os.environ.get("DVC_STAGE")  # set by DVC for every stage command it runs
    if via_dvc is None:
        via_dvc = bool(dvc_stage) and path.resolve() == Path(os.environ.get("DVC_ROOT", ".")).resolve() / "params.yaml"
    stage = dvc_stage or stage
    tree = _params_via_dvc(stage) if via_dvc else read_yaml(path)
    if via_dvc and "profile" not in tree:
        raise ConfigError(f"dvc.yaml: stage {stage!r} must declare the `profile` param (it selects the scale)")
    profile = _active_profile(tree)
    resolved = resolve(tree, profile)
    resolved["profile"] = profile
    return resolved


def section(params: Mapping, dotted: str) -> Any:
    """Return ``params[a][b]...`` for ``dotted = "a.b"``, naming the missing key on failure."""
    node: Any = params
    walked = []
    for key in dotted.split("."):
        walked.append(key)
        if not isinstance(node, Mapping) or key not in node:
            raise ConfigError(f"params: missing key {'.'.join(walked)!r}")
        node = node[key]
    return node


def build(cls: type[T], mapping: Mapping, name: str = "") -> T:
    """Build the frozen dataclass ``cls`` from ``mapping``; unknown or missing keys are errors.

    Nested dataclass fields are built recursively. Fields with defaults may be omitted.
    """
    if not isinstance(mapping, Mapping):
        raise ConfigError(f"params section {name or cls.__name__}: expected a mapping, got {type(mapping).__name__}")
    fields = {f.name: f for f in dataclasses.fields(cls)}
    hints = typing.get_type_hints(cls)
    unknown = set(mapping) - set(fields)
    if unknown:
        raise ConfigError(f"params section {name or cls.__name__}: unknown keys {sorted(unknown)}")
    kwargs = {}
    for key, value in mapping.items():
        sub = hints.get(key)
        sub = sub if isinstance(sub, type) and dataclasses.is_dataclass(sub) else None
        kwargs[key] = build(sub, value, f"{name}.{key}" if name else key) if sub and isinstance(value, Mapping) else value
    try:
        return cls(**kwargs)
    except TypeError as exc:
        raise ConfigError(f"params section {name or cls.__name__}: {exc}") from exc




def flatten(tree: Mapping, prefix: str = "", sep: str = ".") -> dict[str, Any]:
    """Flatten a nested mapping to ``{"a.b.c": value}`` (lists are kept as values)."""
    flat: dict[str, Any] = {}
    for key, value in tree.items():
        name = f"{prefix}{sep}{key}" if prefix else str(key)
        if isinstance(value, Mapping):
            flat.update(flatten(value, name, sep))
        else:
            flat[name] = value
    return flat
