"""Tuning on calibration scenes only (issue 22 items 1-2): gca.pipeline.tuning (protocol) and gca.pipeline.tune (CLI)."""

import json
import math
import re
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import yaml

from gca import config
from gca.config import ConfigError
from gca.pipeline import tune, tuning
from gca.pipeline.tuning import TuningConfig

ROOT = Path(__file__).resolve().parents[1]
TABLE_SCENES = ("ball", "duck", "pawn", "cat", "fish", "bottle", "dragon", "wolf", "pudding", "composite")


def _shipped(profile="paper"):
    params = config.load(path=ROOT / "params.yaml", via_dvc=False)
    if profile != params["profile"]:
        raw = config.read_yaml(ROOT / "params.yaml")
        params = config.resolve(raw, profile)
        params["profile"] = profile
    return params, config.build(TuningConfig, params["tuning"], "tuning")


def test_the_search_is_a_seeded_latin_hypercube_from_the_frozen_params():
    params, cfg = _shipped()
    u = tuning.latin_hypercube(7, 4, seed=3)
    assert u.shape == (7, 4) and np.array_equal(u, tuning.latin_hypercube(7, 4, seed=3))
    for j in range(4):  # one point in each of the 7 strata of every dimension
        assert sorted(np.floor(u[:, j] * 7).astype(int)) == list(range(7))
    assert not np.array_equal(u, tuning.latin_hypercube(7, 4, seed=4))
    for method in cfg.methods:
        trials = tuning.trial_values(cfg, method, params)
        assert len(trials) == cfg.trials and trials == tuning.trial_values(cfg, method, params)
        knobs = cfg.knobs(method)
        assert trials[0] == {k.name: tuning.frozen_value(params, k) for k in knobs}  # trial 0: the frozen params
        # and those values are params.yaml's: applying trial 0 changes nothing
        assert tuning.apply_values(params, cfg, method, trials[0]) == params
        for t in trials[1:]:
            assert all(k.low <= t[k.name] <= k.high for k in knobs)
    assert tuning.trial_values(cfg, "gca", params)[1]["lr"] != tuning.trial_values(cfg, "neuma", params)[1]["lr"]


def test_every_learned_method_gets_the_same_budget_and_its_own_keys():
    params, cfg = _shipped()
    assert set(cfg.methods) == {"gca", "neuma", "pacnerf_depth"}  # GCA, NeuMA, PAC-NeRF-style
    assert {k.name for k in cfg.knobs("gca")} == {"lambda_m", "lambda_1", "lambda_2", "lr"}
    # the budget is one for all: trials x iterations x seeds on each calibration scene
    assert cfg.budget()["iterations_per_method"] == cfg.trials * cfg.iterations * len(cfg.seeds) * len(cfg.scenes)
    assert cfg.iterations == params["train"]["iterations"]  # tuned at the budget the tables train with
    gca = tuning.apply_values(params, cfg, "gca", {"lambda_m": 2.0, "lambda_1": 0.02, "lambda_2": 0.03, "lr": 2.0})
    assert gca["align"]["rdga"]["lambda_mask"] == 2.0 and gca["align"]["rdga"]["lambda1"] == 0.02
    assert gca["train"]["lr_elasticity"] == pytest.approx(2 * params["train"]["lr_elasticity"])
    assert gca["train"]["lr_plasticity"] == pytest.approx(2 * params["train"]["lr_plasticity"])  # ratio kept
    assert gca["train"]["lr_explicit"] == params["train"]["lr_explicit"]  # another method's knob untouched
    raw = dict(params["tuning"])
    raw["methods"] = {**raw["methods"], "neuma": {"lr": {"keys": ["train.lr_explicit"], "range": [0.1, 1.0],
                                                         "factor": False}}}
    with pytest.raises(ConfigError, match="knob of both"):
        config.build(TuningConfig, raw, "tuning")


def test_neuma_lr_scale_multiplies_its_published_rates():
    import dataclasses

    from gca.train.config import NEUMA_LR, TrainConfig, neuma_recipe

    base = neuma_recipe(TrainConfig(neuma_lr_scale=1.0), "jelly")
    assert (base.lr_elasticity, base.lr_plasticity) == NEUMA_LR["jelly"][:2]  # 1.0: as published
    scaled = neuma_recipe(dataclasses.replace(TrainConfig(), neuma_lr_scale=2.0), "jelly")
    assert scaled.lr_elasticity == pytest.approx(2 * NEUMA_LR["jelly"][0])
    tuned = TrainConfig()  # the default is the tuning's choice (tuning/record.json), both rates scaled
    assert tuned.neuma_lr_scale != 1.0
    assert neuma_recipe(tuned, "jelly").lr_plasticity == pytest.approx(tuned.neuma_lr_scale * NEUMA_LR["jelly"][1])
    with pytest.raises(ValueError, match="neuma_lr_scale"):
        TrainConfig(neuma_lr_scale=0.0)


def test_a_table_scene_is_refused():
    params, cfg = _shipped()
    tuning.check_scenes(params, cfg.scenes)
    assert all(params["scenes"][s]["calibration"] is True for s in cfg.scenes)
    for scene in TABLE_SCENES:
        with pytest.raises(ConfigError, match="not a calibration scene"):
            tuning.check_scenes(params, ["calib_torus", scene])
    with pytest.raises(ConfigError, match="not a calibration scene"):
        tune.main(["--work", "/nonexistent/never", "--profile", "ci", "--set", "tuning.scenes=[calib_star, ball]",
                   "--set", "tuning.record=''"])


def test_params_citing_a_record_are_not_tuned_again_by_accident(tmp_path):
    """Once params.yaml cites a record (its knobs hold the choice), a tuning run would draw its trials around the
    chosen values and redo every unit: refused with the way to re-make that tuning or tune anew (negative control:
    with the citation overridden it goes on, to the next check: the shard's)."""
    raw = yaml.safe_load((ROOT / "params.yaml").read_text())
    raw["tuning"]["record"] = "tuning/record.json"
    cited = tmp_path / "params.yaml"
    cited.write_text(yaml.safe_dump(raw, sort_keys=False))
    argv = ["--work", str(tmp_path / "never"), "--params", str(cited), "--profile", "ci", "--shard", "5/2"]
    with pytest.raises(ConfigError, match="cites the tuning record tuning/record.json.*git show"):
        tune.main(argv)
    with pytest.raises(ConfigError, match="--shard 5/2"):  # past the citation check, stopped by the next one
        tune.main([*argv, "--set", "tuning.record=''"])
    assert not (tmp_path / "never").exists()


def _unit(cd, shares=None, status="ok", scene="calib_torus"):
    return {"scene": scene, "seed": 0, "status": status, "chamfer_mean": cd, "term_shares": shares or {}}


def _shares(silhouette=1.0, glob=1.0, anchor=1.0, cos=0.5):
    out = {"share/total/norm": 10.0}
    for term, norm in (("silhouette", silhouette), ("global", glob), ("anchor", anchor)):
        out[f"share/{term}/norm"], out[f"share/{term}/cos"] = norm, cos
    return out


def test_the_objective_is_cd_with_each_rdga_term_carrying_a_share():
    _, cfg = _shipped()
    cfg = TuningConfig(scenes=("calib_torus",), trials=3, seeds=(0,))
    good = tuning.score(cfg, "gca", [_unit(0.02, _shares())])
    assert good["feasible"] and good["objective"] == 0.02 and good["shares"]["global"]["norm_share"] == 0.1
    silent = tuning.score(cfg, "gca", [_unit(0.01, _shares(anchor=0.1))])  # anchor: 1% of the gradient
    assert not silent["feasible"] and silent["shortfall"] == pytest.approx(0.04)
    against = tuning.score(cfg, "gca", [_unit(0.01, _shares(cos=-0.2))])  # terms pulling against the total
    assert not against["feasible"]
    failed = tuning.score(cfg, "gca", [_unit(0.005, _shares(), status="failed")])
    assert math.isinf(failed["objective"]) and not failed["feasible"]
    # the lowest CD is not chosen when a term is silent (negative control), the best feasible one is
    trials = [{"score": s} for s in (good, silent, against, failed)]
    assert tuning.choose(trials) == 0
    assert tuning.choose(trials[1:]) == 0  # none feasible: the least shortfall
    neuma = tuning.score(cfg, "neuma", [_unit(0.03)])  # no RDGA term: CD alone
    assert neuma["feasible"] and neuma["shares"] == {}
    assert not tuning.score(cfg, "neuma", [])["complete"]


def test_a_result_made_under_another_setup_is_not_this_units(tmp_path):
    """A unit's result counts only under the stamp of its own setup (the trial's values applied to the params,
    method, scene, seed): re-run with other trials (tuning.sampler_seed) or other params, the old files are not
    taken for the new units, and the record counts them as missing (negative control: the same setup counts)."""
    params, cfg = _shipped()
    values = tuning.trial_values(cfg, "gca", params)[1]
    path = tune.unit_path(tmp_path, "gca", 1, "calib_torus", 0)
    made = tune.unit_stamp(params, cfg, "gca", values, "calib_torus", 0)
    path.parent.mkdir(parents=True)
    path.write_text(json.dumps({**_unit(0.01), "stamp": made}))
    assert tune.done_unit(path, made) is not None  # the same setup: done
    other_cfg = config.build(TuningConfig, {**params["tuning"], "sampler_seed": cfg.sampler_seed + 1}, "tuning")
    other_values = tuning.trial_values(other_cfg, "gca", params)[1]
    assert other_values != values
    assert tune.done_unit(path, tune.unit_stamp(params, other_cfg, "gca", other_values, "calib_torus", 0)) is None
    changed = {**params, "sim": {**params["sim"], "friction": 0.5}}
    assert tune.done_unit(path, tune.unit_stamp(changed, cfg, "gca", values, "calib_torus", 0)) is None
    assert tune.done_unit(path, tune.unit_stamp(params, cfg, "gca", values, "calib_torus", 1)) is None
    path.write_text(json.dumps(_unit(0.01)))  # an unstamped (older) result
    assert tune.done_unit(path, made) is None


def test_frozen_params_are_the_cited_records_choice():
    """params.yaml's tuned knobs cannot drift from the record it cites (and a record cannot sit uncited)."""
    params, cfg = _shipped()
    if cfg.record:
        record = json.loads((ROOT / cfg.record).read_text())
        assert tuning.frozen_mismatches(params, record) == []
        assert set(record["methods"]) == set(cfg.methods)
        budgets = {json.dumps(record["budget"], sort_keys=True)}
        assert len(budgets) == 1 and all("chosen" in e for e in record["methods"].values())
    else:
        assert not (ROOT / "tuning" / "record.json").exists(), "a tuning record exists but params.yaml does not cite it"
    # negative control: a record whose choice differs from params.yaml is caught
    fake = {"methods": {"gca": {"chosen": {"params": {"align.rdga.lambda1": params["align"]["rdga"]["lambda1"] * 3,
                                                      "align.rdga.lambda2": params["align"]["rdga"]["lambda2"]}}}}}
    assert tuning.frozen_mismatches(params, fake) == [
        f"align.rdga.lambda1: params.yaml {params['align']['rdga']['lambda1']!r}, tuning record (gca) "
        f"{params['align']['rdga']['lambda1'] * 3!r}"]


def test_the_printed_params_change_applied_as_is_passes_the_frozen_check():
    """What tune prints to apply is what the frozen check accepts (session 19: it printed 6 digits, the check wants 1e-9)."""
    import yaml

    params, _ = _shipped()
    chosen = {"align.rdga.lambda1": 0.12345678912345678, "train.neuma_lr_scale": 2.3456789123456789}
    record = {"methods": {"gca": {"chosen": {"trial": 4, "feasible": False, "params": {k: v for k, v in chosen.items()
                                                                                      if k.startswith("align")}}},
                          "neuma": {"chosen": {"trial": 1, "feasible": True,
                                               "params": {"train.neuma_lr_scale": chosen["train.neuma_lr_scale"]}}}}}
    applied = json.loads(json.dumps(params))
    for line in tuning.params_change(record, "tuning/record.json").splitlines():
        if line.startswith("#") or line.startswith("tuning.record"):
            continue
        key, value = line.split(": ")
        *parents, leaf = key.split(".")
        node = applied
        for name in parents:
            node = node[name]
        node[leaf] = yaml.safe_load(value)
    assert tuning.frozen_mismatches(applied, record) == []
    assert tuning.frozen_mismatches(params, record) != []  # negative control: the unapplied params differ


def test_the_report_says_when_no_record_is_cited(tmp_path):
    from gca.report.tuning import write_tuning_tables

    (md,) = write_tuning_tables("", tmp_path)
    assert "No tuning record is cited" in md.read_text()


def test_a_tiny_tuning_on_one_calibration_scene(tmp_path, monkeypatch, capsys):
    """2 trials x 1 iteration x seed 0 on calib_torus at the CI profile, GCA and NeuMA (the PAC-NeRF-style row runs
    the same code; left out for CI time): the record holds every
    trial's values, CD and term shares, the same budget for each method and the chosen values; no table scene's
    file is opened; a second call redoes nothing; the report page shows the shares."""
    from test_scenes_truth_isolation import recorder

    from gca.pipeline import evaluate

    work, record_path = tmp_path / "work", tmp_path / "record.json"
    argv = ["--work", str(work), "--profile", "ci", "--set", "tuning.trials=2", "--set", "tuning.iterations=1",
            "--set", "tuning.scenes=[calib_torus]", "--record", str(record_path), "--device", "cpu",
            "--methods", "gca", "neuma", "--set", "tuning.record=''"]  # around the checkout's values, cited or not
    evaluated, real_evaluate = [], evaluate.evaluate_trained

    def evaluate_seeing_the_checkpoint(settings, scene, method, inputs, body, runs_dir, *args, **kw):
        evaluated.append(sorted(p.name for p in runs_dir.glob("*/checkpoint.pt")))  # the unit's training's, kept
        return real_evaluate(settings, scene, method, inputs, body, runs_dir, *args, **kw)

    monkeypatch.setattr(evaluate, "evaluate_trained", evaluate_seeing_the_checkpoint)
    with recorder() as rec:
        record = tune.main(argv)
    out = capsys.readouterr().out
    # no table scene: neither its data nor its runs nor its metrics, here or in the checkout
    for scene in TABLE_SCENES:
        assert not [p for p in rec.paths if f"/{scene}/" in p or f"/{scene}." in p or p.endswith(f"/{scene}")], scene
    assert any("calib_torus" in p for p in rec.paths)  # the recorder saw the tuning's reads (not a vacuous pass)
    restricted = yaml.safe_load((work / "params.yaml").read_text())
    assert set(restricted["scenes"]) == {"calib_torus"} and set(restricted["objects"]) == {"torus"}
    assert not any((work / "data" / d / s).exists() for d in ("scenes", "prep", "gt") for s in TABLE_SCENES)
    assert not (ROOT / "tuning" / "gca").exists() and not (ROOT / "tuning" / "record.partial.json").exists()  # the
    # units live in the work folder, not in the checkout's tuning/ (a linked folder there once took them: session 18)
    assert json.loads(record_path.read_text()) == record
    assert set(record["methods"]) == {"gca", "neuma"}
    assert record["budget"] == {"trials": 2, "iterations": 1, "seeds": [0], "scenes": ["calib_torus"],
                                "runs_per_method": 2, "iterations_per_method": 2}
    assert record["profile"] == "ci" and record["overrides"][0] == "tuning.trials=2"
    assert record["mlp_kernel"] == "torch"  # what the runs used (the CI profile's; precision_decision.py reads it)
    for method, entry in record["methods"].items():
        assert [t["trial"] for t in entry["trials"]] == [0, 1]
        for t in entry["trials"]:
            (unit,) = t["units"]
            assert unit["scene"] == "calib_torus" and unit["iterations"] == 1
            assert unit["status"] == "failed" or math.isfinite(unit["chamfer_mean"])
        assert entry["chosen"]["trial"] in (0, 1) and set(entry["chosen"]["params"]) == \
            {key for k in entry["knobs"] for key in k["keys"]}
    units = [u for e in record["methods"].values() for t in e["trials"] for u in t["units"]]
    assert all(u["device"].startswith("cpu") and u["commit"] != "unknown" for u in units)
    # each trained unit's checkpoint stayed through its evaluation (a stop there resumes at the training's end: NOTES
    # s43), and none is left once the results are written
    assert len(evaluated) == 4 and evaluated.count(["checkpoint.pt"]) == sum(u["status"] != "failed" for u in units) > 0
    assert not list(work.glob("tuning/*/trial*/*/*/checkpoint.pt*"))
    assert sum(record["unit_commits"].values()) == len(units) == 4
    shares = record["methods"]["gca"]["trials"][0]["score"]["shares"]
    assert set(shares) == {"silhouette", "global", "anchor"}
    assert all(math.isfinite(v["norm_share"]) for v in shares.values())
    assert "tuning.record:" in out and "align.rdga.lambda_mask:" in out  # the params.yaml change, printed
    # the velocity is fitted once per (scene, seed), shared by every trial
    assert (work / "tuning/velocity/calib_torus/velocity.json").is_file()

    def not_again(*a, **k):
        raise AssertionError("a done unit was run again")

    monkeypatch.setattr(tune, "run_unit", not_again)
    again = tune.main(argv + ["--no-prepare"])
    strip = lambda r: {k: v for k, v in r.items() if k != "date"}  # noqa: E731
    assert strip(again) == strip(record)

    # the state carried to a fresh work directory (another machine, a later session): nothing done is redone there,
    # a unit in progress resumes with its checkpoint (then cleared), and the record is the same
    result_of = tune.unit_path(work, "gca", 1, "calib_torus", 0)
    kept = json.loads(result_of.read_text())
    result_of.unlink()  # the unit is in progress: no result, a checkpoint
    progress = tune.unit_run_dir(work, "gca", 1, "calib_torus", 0) / "checkpoint.pt"
    progress.parent.mkdir(parents=True, exist_ok=True)
    progress.write_bytes(b"ckpt")
    progress.with_name("checkpoint.pt.stamp").write_text("stamp")
    archive = tmp_path / "state.tgz"
    elsewhere = tmp_path / "elsewhere"
    carried = {p.as_posix() for p in tune.state_files(work)}
    assert tune.save_state(work, archive) == len(carried) >= 6  # 3 units, a velocity, a checkpoint and its stamp

    def resumes(work_, params, cfg, method, trial, values, scene, seed, device):
        assert (method, trial, scene, seed) == ("gca", 1, "calib_torus", 0), "a done unit was run again"
        assert (work_ / progress.relative_to(work)).read_bytes() == b"ckpt"  # its checkpoint came along
        return kept

    monkeypatch.setattr(tune, "run_unit", resumes)
    moved = tune.main(["--work", str(elsewhere), *argv[2:], "--no-prepare", "--restore-state", str(archive)])
    assert strip(moved) == strip(record)
    assert not (elsewhere / progress.relative_to(work)).exists()  # cleared once the unit's result was written
    assert (elsewhere / "tuning/velocity/calib_torus/velocity.json").is_file()
    assert not (elsewhere / "data").exists() and not (elsewhere / "tuning/gca/trial0/calib_torus/eval").exists()
    ckpt_files = {q.relative_to(work).as_posix() for q in (progress, progress.with_name("checkpoint.pt.stamp"))}
    assert {p.as_posix() for p in tune.state_files(elsewhere)} == carried - ckpt_files | {
        result_of.relative_to(work).as_posix()}

    from gca.report.tuning import write_tuning_tables
    (tmp_path / "report").mkdir()
    md, csv = write_tuning_tables(record_path, tmp_path / "report")
    text = md.read_text()
    assert "calib_torus" in text and "silhouette norm share" in text and "Chosen values" in text


def test_a_tuning_state_with_a_foreign_member_is_refused(tmp_path):
    import io
    import tarfile

    archive = tmp_path / "bad.tgz"
    with tarfile.open(archive, "w:gz") as tar:
        info = tarfile.TarInfo("../params.yaml")
        info.size = 1
        tar.addfile(info, io.BytesIO(b"x"))
    with pytest.raises(ConfigError, match="is not a tuning state file"):
        tune.restore_state(archive, tmp_path / "work")
    assert not (tmp_path / "params.yaml").exists()
    with pytest.raises(ConfigError, match="no tuning state there"):
        tune.restore_state(tmp_path / "missing.tgz", tmp_path / "work")


def _jobs(**specs):
    """grid.Job's of ``python -c`` code (the dispatcher runs stage commands without a shell, as dvc.yaml's are)."""
    import shlex

    from gca.pipeline.grid import Job

    return {name: Job(name, f"python -c {shlex.quote(code)}", [], [], 1.0, set(after))
            for name, (code, after) in specs.items()}


_WAIT = ("import pathlib, sys, time\nfor _ in range(100):\n    if pathlib.Path({f!r}).exists(): break\n"
         "    time.sleep(0.1)\nelse:\n    sys.exit(1)\n")


def test_the_inputs_stages_run_in_parallel_in_dependency_order(tmp_path):
    """tune's inputs go through the grid's dispatcher: independent chains run at once (each of a and b waits for
    the other's start file: one by one, the first would time out), a dependent job starts only after its parents,
    a job done under the same stamp is not rerun; one at a time the pair fails, named with its log."""
    from gca.pipeline import dispatch

    touch = "import pathlib; pathlib.Path({f!r}).touch()\n"
    jobs = _jobs(
        a=(touch.format(f="a.start") + _WAIT.format(f="b.start") + "print('from-a')\n" + touch.format(f="a.end"), []),
        b=(touch.format(f="b.start") + _WAIT.format(f="a.start") + touch.format(f="b.end"), []),
        c=("import os, sys\nif not (os.path.exists('a.end') and os.path.exists('b.end')):\n    sys.exit(1)\n"
           + touch.format(f="c.end"), ["a", "b"]),
        old=(touch.format(f="old.ran"), []))
    marker = dispatch.marker(tmp_path, "old")
    marker.parent.mkdir(parents=True)
    marker.write_text("1.0\ns1\n")
    lines = []
    tune.run_stages(jobs, tmp_path, "s1", workers=2, log=lines.append)
    assert (tmp_path / "c.end").is_file() and not (tmp_path / "old.ran").exists()
    assert all(dispatch.is_done(tmp_path, n, "s1") for n in "abc")
    assert any(line.startswith("tune: done  c in") for line in lines)
    # one at a time the same pair cannot finish: a waits for b's start (negative control of the parallel check)
    (tmp_path / "b.start").unlink()
    one = _jobs(a=(_WAIT.format(f="b.start"), []), b=(touch.format(f="b.start"), []))
    with pytest.raises(SystemExit, match=r"(?s)FAIL  (a|b).*log: .*stage\(s\) \['(a|b)'\] failed"):
        tune.run_stages(one, tmp_path, "s2", workers=1, log=lines.append)


def test_a_failing_inputs_stage_stops_its_chain_and_names_itself(tmp_path):
    """The failure's message has the job, its exit status, its log and its tail; a job after it never starts; an
    independent job finishes and is marked done (kept for the next call); nothing of the failed job is marked done."""
    from gca.pipeline import dispatch

    jobs = _jobs(bad=("import sys; print('broken input', file=sys.stderr); sys.exit(3)", []),
                 slow=("import pathlib, time; time.sleep(1); pathlib.Path('slow.end').touch()", []),
                 later=("import pathlib; pathlib.Path('later.ran').touch()", ["bad"]))
    with pytest.raises(SystemExit) as err:
        tune.run_stages(jobs, tmp_path, "s", workers=2, log=lambda s: None)
    msg = str(err.value)
    assert msg.startswith("FAIL  bad (") and "bad: exit 3" in msg and "failed (their logs above)" in msg, msg
    log_path = Path(msg.split("log: ")[1].splitlines()[0])
    assert "broken input" in log_path.read_text()
    assert not dispatch.is_done(tmp_path, "bad") and not (tmp_path / "later.ran").exists()
    assert (tmp_path / "slow.end").is_file() and dispatch.is_done(tmp_path, "slow", "s")


def _units_argv(work, tmp_path, *more):
    return ["--work", str(work), "--profile", "ci", "--set", "tuning.trials=2", "--set", "tuning.iterations=1",
            "--set", "tuning.scenes=[calib_torus]", "--record", str(tmp_path / "r.json"), "--device", "cpu",
            "--methods", "neuma", "--no-prepare", "--set", "tuning.record=''", *more]


def _fake_units(ran, stop_in_evaluation=()):
    """A run_unit stand-in: it "trains" (writes the unit's checkpoint, as train_method(keep_checkpoint=True) leaves
    it), then "evaluates": a unit in ``stop_in_evaluation`` is stopped there."""
    from gca import stop

    def fake_unit(work_, params, cfg, method, trial, values, scene, seed, device):
        ran.append((method, trial, scene, seed))
        run_dir = tune.unit_run_dir(work_, method, trial, scene, seed)
        run_dir.mkdir(parents=True, exist_ok=True)
        (run_dir / "checkpoint.pt").write_bytes(b"it 1")
        if (trial, seed) in stop_in_evaluation:
            raise stop.Terminated("stopped at the deadline (test)")
        return {"method": method, "trial": trial, "scene": scene, "seed": seed, "values": dict(values),
                "status": "ok", "chamfer_mean": 0.1, "term_shares": {}, "train_seconds": 0.0, "iterations": 1,
                "stamp": tune.unit_stamp(params, cfg, method, values, scene, seed)}
    return fake_unit


def test_processes_launched_together_claim_units_in_progress_first(tmp_path, monkeypatch):
    """--claim: a unit claimed by another process of the launch is not run here, a unit with a checkpoint (cut off
    in or after its training) runs before the others, and a claim is one file per unit, taken once."""
    claims, work = tmp_path / "claims", tmp_path / "work"
    assert tune.claim_unit(claims, "gca", 0, "calib_torus", 0) and not tune.claim_unit(claims, "gca", 0, "calib_torus", 0)
    for p in claims.iterdir():
        p.unlink()
    ran = []
    monkeypatch.setattr(tune, "run_unit", _fake_units(ran))
    (work / "tuning/neuma/trial1/calib_star/neuma").mkdir(parents=True)
    (work / "tuning/neuma/trial1/calib_star/neuma/checkpoint.pt").write_bytes(b"ckpt")
    assert tune.claim_unit(claims, "neuma", 0, "calib_torus", 0)  # taken by another process of this launch
    argv = ["--work", str(work), "--profile", "ci", "--set", "tuning.trials=2", "--set", "tuning.iterations=1",
            "--set", "tuning.scenes=[calib_torus,calib_star]", "--record", str(tmp_path / "r.json"), "--device", "cpu",
            "--methods", "neuma", "--no-prepare", "--claim", str(claims), "--set", "tuning.record=''"]
    record = tune.main(argv)
    assert ran[0] == ("neuma", 1, "calib_star", 0)
    assert ("neuma", 0, "calib_torus", 0) not in ran and len(ran) == 3
    assert len(list(claims.iterdir())) == 4 and not (tmp_path / "r.json").exists()  # one unit left: no record yet
    assert sum(len(t["units"]) for t in record["methods"]["neuma"]["trials"]) == 3
    # the next launch empties the claims: the unit left runs, and then the record is written
    for p in claims.iterdir():
        p.unlink()
    ran.clear()
    tune.main(argv)
    assert ran == [("neuma", 0, "calib_torus", 0)] and (tmp_path / "r.json").is_file()


def test_a_units_training_stops_at_its_iterations_end_and_before_its_evaluation(tmp_path):
    """A tuning shard stopped by its deadline (tune_bundle.sh: GCA_STOP_AT): the unit's training runs deferred (the
    stop waits for the iteration's end and checkpoint), and a stop that came during it ends the unit before its
    evaluation; without a stop the training's result comes back (control). (The checkpoint's fate is main()'s:
    test_a_units_checkpoint_stays_until_its_result_is_written.)"""
    from gca import stop

    seen = []

    def train(ask: bool):
        seen.append(stop._state["deferring"])
        if ask:
            stop._state["requested"] = True  # what the watcher or SIGTERM's handler does inside deferred
        return {"iterations": 200}

    assert tune.trained(lambda: train(False)) == {"iterations": 200}
    try:
        with pytest.raises(stop.Terminated):
            tune.trained(lambda: train(True))
    finally:
        stop.reset()
    assert seen == [1, 1]


def test_a_units_checkpoint_stays_until_its_result_is_written(tmp_path, monkeypatch):
    """A unit stopped in its evaluation keeps its training's checkpoint (the next launch resumes it at its end, not
    from scratch: session 42's trained() cleared it before the evaluation); a unit whose result is written has none
    left; a checkpoint left beside a written result (a stop between the two) goes at the next launch."""
    from gca import stop

    work, ran = tmp_path / "work", []
    monkeypatch.setattr(tune, "run_unit", _fake_units(ran, stop_in_evaluation={(1, 0)}))
    with pytest.raises(stop.Terminated):
        tune.main(_units_argv(work, tmp_path))
    assert ran == [("neuma", 0, "calib_torus", 0), ("neuma", 1, "calib_torus", 0)]
    assert tune.unit_path(work, "neuma", 0, "calib_torus", 0).is_file()
    assert not tune.in_progress(work, "neuma", 0, "calib_torus", 0)  # its result written: checkpoint cleared
    assert not tune.unit_path(work, "neuma", 1, "calib_torus", 0).exists()
    assert tune.in_progress(work, "neuma", 1, "calib_torus", 0)  # stopped in its evaluation: checkpoint kept
    left = tune.unit_run_dir(work, "neuma", 0, "calib_torus", 0) / "checkpoint.pt"
    left.write_bytes(b"left by a stop after the result's write")
    ran.clear()
    monkeypatch.setattr(tune, "run_unit", _fake_units(ran))
    tune.main(_units_argv(work, tmp_path))
    assert ran == [("neuma", 1, "calib_torus", 0)] and not left.exists() and (tmp_path / "r.json").is_file()
    assert not tune.in_progress(work, "neuma", 1, "calib_torus", 0)


def test_under_a_stop_deadline_units_start_until_shortly_before_it(tmp_path, monkeypatch, capsys):
    """Session 43: shards keeping to --deadline idled ~20 % of a call. Under GCA_STOP_AT a unit cut off at the stop
    resumes next launch, so units start while TAIL_START_S are left before it, whatever their cost; without it
    (control) the measured cost still keeps a unit from starting past --deadline."""
    from gca import stop

    assert tune.no_start(10.0, [], 5.0, None, 0.0) == ""  # no cost measured yet: start
    assert "a unit takes up to 20 s" in tune.no_start(10.0, [20.0], 25.0, None, 0.0)
    assert tune.no_start(10.0, [20.0], 35.0, None, 0.0) == ""
    assert tune.no_start(10.0, [500.0], 25.0, 1000.0 + tune.TAIL_START_S, 1000.0) == ""  # the stop keeps the work
    assert "before GCA_STOP_AT" in tune.no_start(10.0, [], None, 1000.0 + tune.TAIL_START_S - 1, 1000.0)

    ran = []
    monkeypatch.setattr(tune, "run_unit", _fake_units(ran))
    tune.main(_units_argv(tmp_path / "w0", tmp_path, "--deadline", "1e-6"))  # any unit's cost passes it
    out = capsys.readouterr().out  # control: --deadline binds (the seconds used depend on the machine's load)
    assert len(ran) == 1 and re.search(r"deadline: \d+ s used", out), out
    ran.clear()
    monkeypatch.setenv(stop.STOP_AT_ENV, str(time.time() + 3600))
    try:
        tune.main(_units_argv(tmp_path / "w1", tmp_path, "--deadline", "1e-6"))
    finally:
        stop.reset()
    assert len(ran) == 2 and (tmp_path / "r.json").is_file()


def test_a_tuning_record_holds_the_mlp_kernel_its_runs_used(tmp_path):
    """The record names the resolved train.mlp_kernel (benchmarks/precision_decision.py compares it): an override's,
    else the profile's value (the paper profile's TF32 since session 44, the CI profile's torch)."""
    for profile, overrides, expected in (("ci", ["train.mlp_kernel=simt"], "simt"), ("ci", [], "torch"),
                                         ("paper", [], "triton_tf32")):
        _, resolved, cfg = tune.load_config(ROOT / "params.yaml", profile, overrides)
        record, _ = tune.build_record(tmp_path, resolved, cfg, [], "cpu", overrides)
        assert record["mlp_kernel"] == expected, (profile, overrides)
