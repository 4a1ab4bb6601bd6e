"""gca.pipeline.schema: one source of truth for knob values, and validation of params at load (issue 24 item 2,
issue 19 item 3). Every probe asserts the exact message a user sees."""

import copy
import dataclasses

import pytest
import yaml
from pathlib import Path
from gca import config
from gca.pipeline import schema


def _switches(raw, prefix=""):
    """Dotted keys of params.yaml written as a {paper, ci} switch."""
    out = set()
    if isinstance(raw, dict):
        if set(raw) == set(config.PROFILES):
            return {prefix}
        for key, value in raw.items():
            out |= _switches(value, f"{prefix}.{key}" if prefix else str(key))
    return out


def _differences(built, default, where, out):
    for f in dataclasses.fields(built):
        if not f.init or not f.metadata.get("param", True):
            continue
        value, expected = getattr(built, f.name), getattr(default, f.name)
        if dataclasses.is_dataclass(value):
            _differences(value, expected, f"{where}.{f.name}", out)
        elif value != expected:
            out[f"{where}.{f.name}"] = (value, expected)




@pytest.mark.parametrize("section", sorted(schema.KNOB_SECTIONS))
def test_dataclass_defaults_equal_params_yaml(repo_root, section):
    """A default is params.yaml's value: the one value, or for a knob written {paper: a, ci: b} one of a, b
    (the paper value unless the default is the CI one). So a dataclass built in code, in a test or a
    benchmark, runs the pipeline's setup, and no default can stand in for a key params.yaml sets."""
    raw = config.read_yaml(repo_root / "params.yaml")
    switched = _switches(raw)
    prior_sim = set(raw["prior"]["train"]["sim"])
    cls = schema.dataclass_of(schema.KNOB_SECTIONS[section])
    found = {}
    for profile in config.PROFILES:
        diffs = {}
        _differences(schema.build_section(config.resolve(raw, profile), section), cls(), section, diffs)
        found[profile] = diffs

    def origin(key):  # the params key a field's value comes from
        if key.startswith("prior.train.sim.") and key.split(".")[-1] not in prior_sim:
            return "sim." + key.split(".")[-1]
        return key

    bad = []
    for key in set(found["paper"]) | set(found["ci"]):
        if origin(key) in switched:
            if key in found["paper"] and key in found["ci"]:
                bad.append(f"{key}: default {found['paper'][key][1]!r} is neither profile's value")
        else:
            value, default = (found["paper"].get(key) or found["ci"][key])
            bad.append(f"{key}: params.yaml {value!r}, dataclass default {default!r}")
    assert not bad, "; ".join(sorted(bad))


def test_the_golden_test_can_fail(repo_root):
    from gca.sim.solver import SimConfig

    raw = config.read_yaml(repo_root / "params.yaml")
    diffs = {}
    _differences(schema.build_section(config.resolve(raw, "paper"), "sim"), SimConfig(dt=1e-3), "sim", diffs)
    assert diffs == {"sim.dt": (5e-4, 1e-3)}


def test_prior_sim_derives_from_sim(repo_root):
    p = schema.load(None, repo_root / "params.yaml", via_dvc=False)
    prior = schema.build_section(p, "prior.train").sim
    sim = schema.build_section(p, "sim")
    overridden = set(p["prior"]["train"]["sim"])
    assert overridden == {"dt", "bound", "max_refine"}
    for f in dataclasses.fields(sim):
        if f.name not in overridden:
            assert getattr(prior, f.name) == getattr(sim, f.name), f.name
    p["sim"]["friction"] = 0.9  # a change to sim reaches the prior's simulator
    assert schema.build_section(p, "prior.train").sim.friction == 0.9
    p["prior"]["train"]["sim"]["frction"] = 0.1
    with pytest.raises(config.ConfigError, match=r"prior.train.sim overrides keys that `sim` does not have: \['frction'\]"):
        schema.build_section(p, "prior.train")


def test_benchmarks_build_cpr_from_params():
    import pathlib

    root = pathlib.Path(__file__).resolve().parents[1] / "benchmarks"
    offenders = [p.name for p in root.glob("*.py") if "CPRConfig()" in p.read_text()]
    assert offenders == []


# ------------------------------------------------------------------------------------ probes at load


def _write(tmp_path, repo_root, edit):
    tree = yaml.safe_load((repo_root / "params.yaml").read_text())
    tree["profile"] = "ci"
    edit(tree)
    path = tmp_path / "params.yaml"
    path.write_text(yaml.safe_dump(tree, sort_keys=False))
    return path


def _error(tmp_path, repo_root, edit):
    path = _write(tmp_path, repo_root, edit)
    with pytest.raises(config.ConfigError) as info:
        schema.load(None, path, via_dvc=False)
    return str(info.value).replace(str(path), "params.yaml")


def _set(dotted, value):
    def edit(tree):
        node = tree
        *parents, last = dotted.split(".")
        for key in parents:
            node = node[key]
        node[last] = value
    return edit


def _drop(dotted):
    def edit(tree):
        node = tree
        *parents, last = dotted.split(".")
        for key in parents:
            node = node[key]
        del node[last]
    return edit


def _keys(table: str) -> str:
    """The shipped params.yaml's keys of ``table``, as a reference error lists them."""
    node = yaml.safe_load((Path(__file__).resolve().parents[1] / "params.yaml").read_text())
    for key in table.split("."):
        node = node[key]
    return ", ".join(map(str, node))


PROBES = [
    (_drop("particles.floor_gap"), "params.yaml: params: missing key particles.floor_gap"),
    (_drop("sim.n_grid"), "params.yaml: params: missing key sim.n_grid"),
    (_set("train.iterations", -5), "params.yaml: params: train.iterations=-5 must be >= 1"),
    (_set("train.iterations", 0), "params.yaml: params: train.iterations=0 must be >= 1"),
    (_set("sim.dt", "abc"), "params.yaml: params: sim.dt='abc' must be a number"),
    (_set("scenes.ball.v0", [1, 2]), "params.yaml: params: scenes.ball.v0=[1, 2] must have 3 components"),
    (_set("train.lr_elasticity", float("nan")), "params.yaml: params: train.lr_elasticity=nan must be a finite number"),
    (_set("particles.floor_gap", -0.5), "params.yaml: params: particles.floor_gap=-0.5 must be > 0.0"),
    (_set("particles.floor_gap", 0.05),
     "params.yaml: params: particles.floor_gap=0.05 must lie above the floor's wall zone, "
     "sim.bound / sim.n_grid = 0.0625 m"),
    (_set("scenes.ball.object", "nosuch"),
     f"params.yaml: params: scenes.ball.object='nosuch' is not a key of objects ({_keys('objects')})"),
    (_set("scenes.ball.material", "steel"),
     f"params.yaml: params: scenes.ball.material='steel' is not a key of materials ({_keys('materials')})"),
    (_set("scenes.ball.prior", "honey"),
     f"params.yaml: params: scenes.ball.prior='honey' is not a key of prior.families ({_keys('prior.families')})"),
    (_set("scenes.duck.methods", ["gca", "gcaa"]), "params.yaml: params: scenes.duck.methods: unknown methods ['gcaa']"),
    (_set("train.keep", "first"), "params.yaml: params section train: train.keep must be 'best' or 'last', got 'first'"),
    (_set("sim.cuda_graphs", "yes"), "params.yaml: params: sim.cuda_graphs='yes' must be true or false"),
    (_set("video.n_frames", 2.5), "params.yaml: params: video.n_frames=2.5 must be an integer"),
    (_set("demo.new_shape.law_scene", "nosuch"), "params.yaml: params: demo.new_shape.law_scene='nosuch' is not a key of scenes"),
]


@pytest.mark.parametrize("edit,message", PROBES, ids=[m.split("params: ")[-1][:40] for _, m in PROBES])
def test_bad_params_are_refused_at_load_naming_the_key(tmp_path, repo_root, edit, message):
    assert _error(tmp_path, repo_root, edit).startswith(message)


def test_yaml_exponent_string_is_coerced(tmp_path, repo_root):
    path = tmp_path / "params.yaml"
    path.write_text((repo_root / "params.yaml").read_text().replace("  dt: 5.0e-4   ", "  dt: 1e-3     ", 1))
    raw = config.read_yaml(path)
    assert raw["sim"]["dt"] == "1e-3"  # PyYAML (YAML 1.1) reads it as a string
    assert schema.build_section(schema.load(None, path, via_dvc=False), "sim").dt == 1e-3


def test_shipped_params_validate_in_both_profiles(repo_root):
    raw = config.read_yaml(repo_root / "params.yaml")
    for profile in config.PROFILES:
        schema.validate(config.resolve(copy.deepcopy(raw), profile))


def test_unknown_entry_names_the_table():
    with pytest.raises(config.ConfigError, match=r"^params: unknown scene 'nosuch' \(not a key of scenes: ball, cat\)$"):
        config.entry({"scenes": {"ball": {}, "cat": {}}}, "scenes", "nosuch")


def test_a_params_file_cut_to_one_scene_runs_its_stages_but_not_the_demo(tmp_path, repo_root):
    def cut(tree):
        tree["scenes"] = {"duck": tree["scenes"]["duck"]}

    path = _write(tmp_path, repo_root, cut)
    assert list(schema.load("train@duck", path, via_dvc=False)["scenes"]) == ["duck"]
    with pytest.raises(config.ConfigError, match="demo.new_shape.law_scene='cat' is not a key of scenes \\(duck\\)"):
        schema.load("demo", path, via_dvc=False)


def test_under_dvc_the_whole_file_is_checked_not_the_stage_view(tmp_path, repo_root, monkeypatch):
    """DVC shows a stage only the keys it declares (train: `vision.matching`, not `vision.depth`): that view
    must not read as missing keys, and a bad key outside it is still refused."""
    full = schema.load(None, _write(tmp_path, repo_root, lambda tree: None), via_dvc=False)
    view = {"profile": "ci", "vision": {"matching": full["vision"]["matching"]}, "train": full["train"]}
    monkeypatch.setattr(config, "_params_via_dvc", lambda stage: copy.deepcopy(view))
    path = tmp_path / "params.yaml"
    assert schema.load("train@duck", path, via_dvc=True) == view
    _write(tmp_path, repo_root, _set("particles.floor_gap", -0.5))
    with pytest.raises(config.ConfigError, match="particles.floor_gap=-0.5 must be > 0.0"):
        schema.load("train@duck", path, via_dvc=True)
