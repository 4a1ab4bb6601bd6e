"""benchmarks/precision_decision.py: the rule fixed in session 38 for ``train.mlp_kernel: triton_tf32`` (adopt only
if every calibration scene's mean CD moves by no more than the FP32 seeds' spread and no candidate run diverges), on
tuning records made here; records the rule cannot compare are refused with one line (exit 2); the documented tune
commands' overrides are accepted by the tuning's own loader (calibration scenes only)."""

import json
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SCRIPT = ROOT / "benchmarks" / "precision_decision.py"
sys.path.insert(0, str(ROOT / "benchmarks"))
import precision_decision as pd  # noqa: E402

SCENES = ("calib_torus", "calib_mushroom", "calib_star")
BASE = {"calib_torus": [0.020, 0.022, 0.021], "calib_mushroom": [0.010, 0.012, 0.011],
        "calib_star": [0.030, 0.031, 0.032]}


def record(cds: dict, overrides=(), status=None, seeds=(0, 1, 2)) -> dict:
    """A tuning record as ``gca.pipeline.tune.build_record`` writes it, GCA's trial 0 only."""
    units = [{"scene": s, "seed": k, "chamfer_mean": cds[s][i], "method": "gca", "trial": 0,
              "status": (status or {}).get((s, k), "ok")} for s in SCENES for i, k in enumerate(seeds)]
    return {"profile": "paper", "benchmark_version": "2.0",
            "budget": {"trials": 1, "iterations": 200, "seeds": list(seeds), "scenes": list(SCENES)},
            "overrides": ["tuning.trials=1", f"tuning.seeds={list(seeds)}", *overrides],
            "methods": {"gca": {"trials": [{"trial": 0, "units": units}]}}}


TF32 = ("train.mlp_kernel=triton_tf32",)
FP32 = ("train.mlp_kernel=torch",)


def shifted(delta: dict) -> dict:
    return {s: [v + delta.get(s, 0.0) for v in BASE[s]] for s in SCENES}


def test_a_candidate_within_every_scenes_seed_spread_is_adopted():
    result = pd.decide(record(BASE), record(shifted({"calib_torus": 0.0019, "calib_star": -0.0019}), TF32))
    assert result["adopt"] and result["candidate"] == "triton_tf32"
    assert result["scenes"]["calib_torus"]["spread"] == pytest.approx(0.002)
    assert result["scenes"]["calib_torus"]["move"] == pytest.approx(0.0019)
    assert "Decision: adopt train.mlp_kernel: triton_tf32" in pd.table(result)


@pytest.mark.parametrize("scene", SCENES)
def test_one_scene_moving_past_its_spread_keeps_torch(scene):
    """The spread is each scene's own (0.002 on each here): 0.0021 on any one scene is too much, in either
    direction, and the other scenes stay within theirs."""
    for sign in (1, -1):
        result = pd.decide(record(BASE), record(shifted({scene: sign * 0.0021}), TF32))
        assert not result["adopt"] and not result["scenes"][scene]["within"]
        assert all(r["within"] for s, r in result["scenes"].items() if s != scene)
        assert "keep train.mlp_kernel: torch" in pd.table(result)


def test_the_spread_is_the_references_not_the_candidates():
    """A candidate whose own seeds scatter widely (0.02 apart) does not widen what it is held to (the FP32 seeds'
    0.002): its mean moved by 0.005 keeps torch; the same move is adopted where the reference's spread is wider."""
    wide = {s: [v[0] - 0.01, v[1] + 0.005 + 0.01, v[2] + 0.005 + 0.005] for s, v in BASE.items()}
    result = pd.decide(record(BASE), record(wide, TF32))
    assert not result["adopt"] and all(not r["within"] for r in result["scenes"].values())
    swapped = pd.decide(record(wide), record(BASE, TF32))
    assert swapped["adopt"]


def test_a_diverged_run_of_either_record_or_a_non_finite_cd_keeps_torch():
    result = pd.decide(record(BASE), record(BASE, TF32, status={("calib_star", 1): "diverged"}))
    assert not result["adopt"] and result["not_ok"] == ["candidate calib_star@seed1: diverged"]
    wide = shifted({})
    wide["calib_torus"][2] = 0.5  # a diverged FP32 seed with a finite CD would widen the torus's spread to ~0.48
    result = pd.decide(record(wide, status={("calib_torus", 2): "diverged"}), record(shifted({"calib_torus": 0.1}),
                                                                                      TF32))
    assert result["scenes"]["calib_torus"]["within"] and not result["adopt"]
    assert result["not_ok"] == ["reference calib_torus@seed2: diverged"]
    cds = shifted({})
    cds["calib_mushroom"][2] = float("nan")
    result = pd.decide(record(BASE), record(cds, TF32))
    assert not result["adopt"] and not result["scenes"]["calib_mushroom"]["finite"]
    assert "non-finite" in pd.table(result)


@pytest.mark.parametrize("change, why", [
    (lambda r, c: c.update(profile="ci"), "profile differ"),
    (lambda r, c: c["budget"].update(iterations=100), "budget differ"),
    (lambda r, c: c["overrides"].append("align.rdga.lambda1=1"), "differ by ['align.rdga.lambda1', 'train.mlp_kernel']"),
    (lambda r, c: c["overrides"].remove(TF32[0]), "differ by nothing"),
    (lambda r, c: c["methods"]["gca"]["trials"][0]["units"].pop(), "candidate is not complete"),
    (lambda r, c: [x["methods"]["gca"]["trials"][0].update(units=[u for u in x["methods"]["gca"]["trials"][0]["units"]
                                                                  if u["scene"] != "calib_star"]) for x in (r, c)],
     "reference is not complete"),
    (lambda r, c: [x["methods"]["gca"]["trials"][0]["units"].append(
        {"scene": "calib_extra", "seed": 0, "chamfer_mean": 0.1, "status": "ok"}) for x in (c,)],
     "different (scene, seed) units"),
    (lambda r, c: c.update(overrides=[o.replace("triton_tf32", "torch") for o in c["overrides"]]),
     "got 'torch' and 'torch'"),
    (lambda r, c: r["overrides"].append("train.mlp_kernel=simt"), "got 'triton_tf32' and 'simt'"),
    (lambda r, c: c["methods"]["gca"]["trials"][0].update(trial=1), "no trial 0"),
])
def test_records_the_rule_cannot_compare_are_refused(change, why, capsys):
    ref, cand = record(BASE), record(BASE, TF32)
    change(ref, cand)
    with pytest.raises(SystemExit) as exc:
        pd.decide(ref, cand)
    assert exc.value.code == 2 and why in capsys.readouterr().err


def test_overrides_compare_as_values_not_as_text():
    """``tuning.seeds=[0,1,2]`` and ``tuning.seeds=[0, 1, 2]`` are one value (YAML, as the tuning reads them)."""
    cand = record(BASE, TF32)
    cand["overrides"] = [o.replace("[0, 1, 2]", "[0,1,2]") for o in cand["overrides"]]
    assert cand["overrides"] != record(BASE)["overrides"][:2] + list(TF32)
    assert pd.decide(record(BASE), cand)["adopt"]


def test_one_seed_has_no_spread_and_is_refused(capsys):
    one = {s: v[:1] for s, v in BASE.items()}
    with pytest.raises(SystemExit) as exc:
        pd.decide(record(one, seeds=(0,)), record(one, TF32, seeds=(0,)))
    assert exc.value.code == 2 and ">= 2 seeds per scene" in capsys.readouterr().err


def test_the_command_line_writes_the_verdict_and_refuses_a_bad_file(tmp_path):
    ref, cand = tmp_path / "fp32.json", tmp_path / "tf32.json"
    ref.write_text(json.dumps(record(BASE)))
    cand.write_text(json.dumps(record(shifted({"calib_mushroom": 0.003}), TF32)))
    out = subprocess.run([sys.executable, str(SCRIPT), "--reference", str(ref), "--candidate", str(cand), "--json",
                          str(tmp_path / "v.json")], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert "| calib_mushroom | 3 |" in out.stdout and "keep train.mlp_kernel: torch" in out.stdout
    assert json.loads((tmp_path / "v.json").read_text())["adopt"] is False
    cand.write_text("{not json")
    out = subprocess.run([sys.executable, str(SCRIPT), "--reference", str(ref), "--candidate", str(cand)],
                         capture_output=True, text=True, timeout=120)
    assert out.returncode == 2 and str(cand) in out.stderr and len(out.stderr.strip().splitlines()) == 1


def test_the_documented_overrides_load_on_the_calibration_scenes():
    """The commands in the script's docstring: the tuning's loader takes both settings' overrides (a typed train
    config with the option, 3 seeds, one trial), and its scenes are the calibration scenes."""
    from gca.config import build, section
    from gca.pipeline import tune
    from gca.train.config import TrainConfig

    for extra, kernel in (([], "triton_tf32"), (list(TF32), "triton_tf32"), (list(FP32), "torch")):
        raw, resolved, cfg = tune.load_config(ROOT / "params.yaml", "paper",
                                              ["tuning.trials=1", "tuning.seeds=[0,1,2]", *extra])
        assert cfg.trials == 1 and cfg.seeds == (0, 1, 2) and set(cfg.scenes) == set(SCENES)
        assert all(resolved["scenes"][s].get("calibration") for s in cfg.scenes)
        train = build(TrainConfig, section(resolved, "train"), "train")
        assert train.mlp_kernel == kernel  # the paper default is TF32 since session 44: the reference names torch
    doc = pd.__doc__
    assert '--set tuning.trials=1 --set "tuning.seeds=[0,1,2]"' in doc and f"--set {TF32[0]}" in doc
    assert f"--set {FP32[0]}" in doc


def test_the_kernel_a_record_ran_is_what_the_rule_compares(capsys):
    """A tuning record holds the MLP kernel its runs used (session 44 on); the rule compares that, not the overrides
    alone: a reference made at the new paper default (TF32) without naming torch is refused. Records without the field
    (made at the old default) read as their override, else torch: session 44's own pair is still decided."""
    ref, cand = record(BASE, FP32), record(BASE, TF32)
    ref["mlp_kernel"], cand["mlp_kernel"] = "torch", "triton_tf32"
    assert pd.decide(ref, cand)["adopt"] and pd.decide(ref, cand)["reference"] == "torch"
    old_ref = record(BASE)  # no field, no override: the default then, torch
    assert pd.decide(old_ref, record(BASE, TF32))["reference"] == "torch"
    unnamed = record(BASE)
    unnamed["mlp_kernel"] = "triton_tf32"  # made since session 44 without --set train.mlp_kernel=torch
    with pytest.raises(SystemExit) as exc:
        pd.decide(unnamed, cand)
    assert exc.value.code == 2 and "must set train.mlp_kernel=torch" in capsys.readouterr().err


def test_another_methods_trial_0_is_decided_by_the_same_rule(tmp_path):
    """``--method neuma``: the knob is global to every method's training, so the rule can check it on NeuMA's trial 0
    too; a record without that method's trial is refused, and GCA's units are not read for it."""
    def as_method(rec, name):
        rec["methods"] = {name: rec["methods"]["gca"]}
        return rec
    ref, cand = as_method(record(BASE), "neuma"), as_method(record(shifted({"calib_star": 0.003}), TF32), "neuma")
    verdict = pd.decide(ref, cand, method="neuma")
    assert verdict["method"] == "neuma" and not verdict["adopt"] and not verdict["scenes"]["calib_star"]["within"]
    assert "(neuma's trial 0)" in pd.table(verdict)
    with pytest.raises(SystemExit) as exc:
        pd.decide(record(BASE), record(BASE, TF32), method="neuma")  # GCA's records only
    assert exc.value.code == 2
    (tmp_path / "r.json").write_text(json.dumps(ref))
    (tmp_path / "c.json").write_text(json.dumps(as_method(record(BASE, TF32), "neuma")))
    out = subprocess.run([sys.executable, str(SCRIPT), "--reference", str(tmp_path / "r.json"), "--candidate",
                          str(tmp_path / "c.json"), "--method", "neuma"], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0 and "adopt train.mlp_kernel: triton_tf32 (neuma's trial 0)" in out.stdout, out.stderr
