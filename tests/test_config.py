"""gca.config: profile resolution, typed sections, and the shipped params.yaml."""

import dataclasses
from pathlib import Path

import pytest
from gca import config


def test_resolve_picks_active_profile_everywhere():
    tree = {"a": {"paper": 100, "ci": 3}, "b": [{"paper": 1, "ci": 2}], "c": {"d": 5}}
    assert config.resolve(tree, "ci") == {"a": 3, "b": [2], "c": {"d": 5}}
    assert config.resolve(tree, "paper") == {"a": 100, "b": [1], "c": {"d": 5}}
    assert tree["a"] == {"paper": 100, "ci": 3}  # input untouched


def test_unknown_profile_is_refused(tmp_path):
    path = tmp_path / "params.yaml"
    path.write_text("profile: laptop\n")
    with pytest.raises(config.ConfigError, match="laptop"):
        config.load(path=path, via_dvc=False)


def test_missing_and_malformed_files_name_the_file(tmp_path):
    with pytest.raises(config.ConfigError, match="nope.yaml"):
        config.load(path=tmp_path / "nope.yaml", via_dvc=False)
    bad = tmp_path / "bad.yaml"
    bad.write_text("a: [1, 2\n")
    with pytest.raises(config.ConfigError, match="bad.yaml"):
        config.load(path=bad, via_dvc=False)


@dataclasses.dataclass(frozen=True)
class _Inner:
    dt: float = 1e-3  # s


@dataclasses.dataclass(frozen=True)
class _Outer:
    n: int
    inner: _Inner = _Inner()


def test_build_nested_and_refuses_unknown_keys():
    built = config.build(_Outer, {"n": 3, "inner": {"dt": 2e-3}}, "sim")
    assert built == _Outer(3, _Inner(2e-3))
    with pytest.raises(config.ConfigError, match="sim.inner: unknown keys \\['dx'\\]"):
        config.build(_Outer, {"n": 3, "inner": {"dx": 1}}, "sim")
    with pytest.raises(config.ConfigError, match="sim"):
        config.build(_Outer, {}, "sim")


def test_section_names_missing_key():
    with pytest.raises(config.ConfigError, match="'a.b.c'"):
        config.section({"a": {"b": {}}}, "a.b.c")


def test_flatten():
    assert config.flatten({"a": {"b": 1, "c": {"d": [1]}}, "e": 2}) == {"a.b": 1, "a.c.d": [1], "e": 2}


def test_shipped_params_resolve_in_both_profiles(repo_root):
    raw = config.read_yaml(repo_root / "params.yaml")
    assert raw["profile"] in config.PROFILES
    for profile in config.PROFILES:
        resolved = config.resolve(raw, profile)
        _assert_no_switch_left(resolved)


def _assert_no_switch_left(node):
    if isinstance(node, dict):
        assert set(node) != set(config.PROFILES), f"unresolved profile switch {node}"
        for v in node.values():
            _assert_no_switch_left(v)
    elif isinstance(node, list):
        for v in node:
            _assert_no_switch_left(v)
