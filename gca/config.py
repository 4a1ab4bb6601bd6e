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

Typed access. Library sections map to frozen dataclasses; :func:`build` turns a mapping into one:
every key is required (no code default stands in for a key params.yaml omits), values are coerced to
the field's type or refused, and every message names the key. :func:`load` validates what it read
(``gca.pipeline.schema.validate``, passed as ``check``: each section present, ranges, references).
"""

from __future__ import annotations

import collections.abc
import dataclasses
import math
import os
import types
import typing
from pathlib import Path
from typing import Any, Callable, Mapping, TypeVar

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
         via_dvc: bool | None = None, check: Callable[[Mapping, str | None], None] | None = None) -> dict:
    """Load the resolved params tree for ``stage``.

    Args:
        stage: DVC stage name (``"particles@ball"``); used to restrict the view under DVC.
        path: params file, read directly when not under DVC.
        via_dvc: force/forbid ``dvc.api.params_show``; default: only when DVC is running the stage
            (DVC exports ``DVC_STAGE`` and ``DVC_ROOT`` to stage commands) and ``path`` is the
            repository's ``params.yaml``. Under DVC the stage name DVC gives wins.
        check: called with the resolved params and the stage (the pipeline passes
            :func:`gca.pipeline.schema.validate`: types, ranges, cross-references; under DVC, of the whole
            file, not only the stage's view); a :class:`ConfigError` it raises is re-raised naming the file.

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
    if check is not None:
        # DVC's view holds only the keys the stage declares (`vision.matching` without the rest of `vision`):
        # check the whole file (with any `dvc exp run -S` override already written into it) instead
        full = resolve(read_yaml(path), profile) if via_dvc and path.is_file() else resolved
        try:
            check(full, stage)
        except ConfigError as exc:
            raise ConfigError(f"{path}: {exc}") from None
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


OPTIONAL = {"optional": True}  # field metadata: params may omit the key (the default is its documented meaning)
NOT_A_PARAM = {"param": False}  # field metadata: set by code, never read from params (e.g. TrainConfig.seed)


def build(cls: type[T], mapping: Mapping, name: str = "", *, partial: bool = False) -> T:
    """Build the frozen dataclass ``cls`` from ``mapping``; unknown or missing keys are errors.

    Every field is required (a params file that omits a key never silently takes a code default),
    except fields marked ``metadata=OPTIONAL`` or ``NOT_A_PARAM`` and, with ``partial=True``, every field
    (records such as a camera or a material preset, which name only what differs). Values are coerced
    to the field's type (:func:`coerce`: YAML's ``1e-3`` string becomes a float, ``5.0`` an int) or refused
    with the key named; nested dataclass fields are built recursively. The dataclass's own checks
    (``__post_init__``) become :class:`ConfigError` naming the section.
    """
    where = name or cls.__name__
    if not isinstance(mapping, Mapping):
        raise ConfigError(f"params: {where} must be a mapping, got {type(mapping).__name__} {mapping!r}")
    fields = {f.name: f for f in dataclasses.fields(cls) if f.init}
    hints = typing.get_type_hints(cls)
    unknown = set(mapping) - {k for k, f in fields.items() if f.metadata.get("param", True)}
    if unknown:
        raise ConfigError(f"params section {where}: unknown keys {sorted(unknown)}")
    if not partial:
        missing = [k for k, f in fields.items() if k not in mapping and f.metadata.get("param", True)
                   and not f.metadata.get("optional", False)]
        if missing:
            raise ConfigError(f"params: missing key {where}.{missing[0]}" + (
                f" (and {', '.join(missing[1:])})" if len(missing) > 1 else ""))
    kwargs = {}
    for key, value in mapping.items():
        kwargs[key] = coerce(hints.get(key, Any), value, f"{where}.{key}", partial=partial)
    try:
        return cls(**kwargs)
    except (TypeError, ValueError) as exc:
        if isinstance(exc, ConfigError):
            raise
        raise ConfigError(f"params section {where}: {exc}") from exc


def _number(value: Any, key: str) -> float:
    if isinstance(value, bool):
        raise ConfigError(f"params: {key}={value!r} must be a number")
    if isinstance(value, str):
        try:
            value = float(value.strip())  # YAML 1.1 reads 1e-3 (no dot) as a string
        except ValueError:
            raise ConfigError(f"params: {key}={value!r} must be a number") from None
    if not isinstance(value, (int, float)):
        raise ConfigError(f"params: {key}={value!r} must be a number")
    if not math.isfinite(value):
        raise ConfigError(f"params: {key}={value!r} must be a finite number")
    return value


def coerce(hint: Any, value: Any, key: str, *, partial: bool = False) -> Any:
    """``value`` as type ``hint`` (bool, int, float, str, tuples, optionals, nested dataclasses), or a
    :class:`ConfigError` naming ``key``. Floats must be finite; ints may be written as integral floats."""
    origin, args = typing.get_origin(hint), typing.get_args(hint)
    if dataclasses.is_dataclass(hint) and isinstance(hint, type):
        if isinstance(value, hint):
            return value
        return build(hint, value, key, partial=partial)
    if origin in (typing.Union, types.UnionType):
        if value is None and type(None) in args:
            return None
        options = [a for a in args if a is not type(None)]
        for option in options[:-1]:
            try:
                return coerce(option, value, key, partial=partial)
            except ConfigError:
                pass
        return coerce(options[-1], value, key, partial=partial)
    if hint is bool:
        if not isinstance(value, bool):
            raise ConfigError(f"params: {key}={value!r} must be true or false")
        return value
    if hint is int:
        number = _number(value, key)
        if int(number) != number:
            raise ConfigError(f"params: {key}={value!r} must be an integer")
        return int(number)
    if hint is float:
        return float(_number(value, key))
    if hint is str:
        if not isinstance(value, str):
            raise ConfigError(f"params: {key}={value!r} must be a string")
        return value
    if origin in (dict, collections.abc.Mapping):  # a table of records keyed by name (e.g. demo.captures)
        if not isinstance(value, Mapping):
            raise ConfigError(f"params: {key}={value!r} must be a mapping")
        item = args[1] if len(args) == 2 else Any
        return {str(k): coerce(item, v, f"{key}.{k}", partial=partial) for k, v in value.items()}
    if origin in (tuple, list, collections.abc.Sequence):
        if not isinstance(value, (list, tuple)):
            raise ConfigError(f"params: {key}={value!r} must be a list")
        if origin is tuple and args and args[-1] is not Ellipsis:
            if len(value) != len(args):
                raise ConfigError(f"params: {key}={list(value)!r} must have {len(args)} components")
            return tuple(coerce(a, v, f"{key}[{i}]", partial=partial) for i, (a, v) in enumerate(zip(args, value)))
        item = args[0] if args else Any
        return tuple(coerce(item, v, f"{key}[{i}]", partial=partial) for i, v in enumerate(value))
    return value


_ENTRY_NAMES = {"scenes": "scene", "objects": "object", "materials": "material", "prior.families": "prior family"}


def entry(params: Mapping, dotted: str, name: str) -> Any:
    """``params[dotted][name]``, or a :class:`ConfigError` listing the known names (an unknown scene,
    object or family given to a stage on the command line)."""
    table = section(params, dotted)
    if not isinstance(table, Mapping) or name not in table:
        known = sorted(table) if isinstance(table, Mapping) else []
        what = _ENTRY_NAMES.get(dotted, f"{dotted} entry")
        raise ConfigError(f"params: unknown {what} {name!r} (not a key of {dotted}: {', '.join(map(str, known))})")
    return table[name]


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
