"""Issue 22, items 5 and 6: honest cells (measured values with their status, the divergence rule, three
significant digits, NCLaw in the law-level table, LPIPS marked) and the claims table, on metrics JSON written here
with known answers."""

import json
from pathlib import Path

import pytest

from gca.report import ReportConfig, build_reports, claims, tables
from gca.report.runs import DivergenceRule, format_cell, format_number, load_runs, mark_divergence, Cell

SYN = ("ball", "duck", "pawn", "cat", "fish", "bottle")


def _write(root: Path, scene: str, method: str, seed: int = 0, status: str = "ok", profile: str = "ci", **values):
    record = {"scene": scene, "method": method, "seed": seed, "status": status, "profile": profile, "device": "cpu",
              "chamfer_definition": "test", **values}
    name = f"{method}.json" if seed == 0 else f"{method}@seed{seed}.json"
    path = root / scene / name
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(record))


# ------------------------------------------------------------------------------------------ honest cells

def test_three_significant_digits_everywhere():
    assert format_number(0.00123, 2) == "0.00123"  # Table 5 printed 0.00 before
    assert format_number(0.5, 2) == "0.500"
    assert format_number(123.456, 1) == "123.5"  # never fewer decimals than asked
    assert format_cell(Cell("ok", 0.000456, 0.0000123, 3), 2) == "0.000456 ± 0.000012"
    assert format_cell(Cell("diverged", 0.0123, None, 1), 2) == "0.0123 (diverged)"
    assert format_cell(Cell("diverged"), 2) == "diverged (no finite value)"


def test_a_cell_over_fewer_seeds_than_the_table_says_so(tmp_path):
    """Session 27: Table 3's duck Rank->L1 cell averaged two seeds beside cells of three and read like them. A cell
    with fewer seeds than the table's most (here a seed not run, or failed) is marked; a full cell is not, nor is a
    table whose cells all have one seed (negative control)."""
    for seed in (0, 1, 2):
        _write(tmp_path, "ball", "gca", seed, chamfer_mean=0.005 + 0.001 * seed)
        _write(tmp_path, "ball", "no_global", seed, chamfer_mean=0.006, status="failed" if seed == 2 else "ok")
        if seed < 2:
            _write(tmp_path, "ball", "rank_to_l1", seed, chamfer_mean=0.007 + 0.001 * seed)
    t3 = tables.table3_ablation_cd(load_runs(tmp_path)).df
    cell = lambda label: t3[(t3["Method"] == label) & (t3["Source"] == "measured")].iloc[0]["Ball (Elastomer)"]  # noqa: E731
    assert cell("Replace Rank w/ L1") == "0.00750 ± 0.00071 (2 of 3 seeds)"
    assert cell("w/o Global Align.") == "0.00600 ± 0.00000 (2 of 3 seeds)"  # its failed seed has no value
    assert cell("Ours (Full)") == "0.00600 ± 0.00100"
    assert format_cell(Cell("ok", 0.0123, None, 1), 2, seeds=1) == "0.0123"
    one = tmp_path / "one"
    _write(one, "ball", "gca", chamfer_mean=0.005)
    _write(one, "ball", "rank_to_l1", chamfer_mean=0.007)
    t3 = tables.table3_ablation_cd(load_runs(one)).df
    assert "seeds" not in " ".join(t3["Ball (Elastomer)"].astype(str))


def test_divergence_rule_marks_cd_above_the_multiple_of_the_prior(tmp_path):
    _write(tmp_path, "ball", "nclaw", chamfer_mean=0.01)
    _write(tmp_path, "ball", "gca", chamfer_mean=0.0999)  # 9.99 x the prior: not diverged
    _write(tmp_path, "ball", "neuma", chamfer_mean=0.101)  # 10.1 x: diverged by the rule
    _write(tmp_path, "ball", "no_global", status="diverged", chamfer_mean=0.02)  # the stage said so
    _write(tmp_path, "cat", "gca", chamfer_mean=5.0)  # no prior on this scene: the stages' verdict only
    runs = mark_divergence(load_runs(tmp_path), DivergenceRule(cd_ratio=10.0))
    assert runs["ball", "gca"][0]["status"] == "ok"
    assert runs["ball", "neuma"][0]["status"] == "diverged" and runs["ball", "neuma"][0]["divergence"] == "cd_ratio"
    assert runs["ball", "no_global"][0]["divergence"] == "stage"
    assert runs["cat", "gca"][0]["status"] == "ok"
    assert runs["ball", "nclaw"][0]["status"] == "ok"
    off = mark_divergence(load_runs(tmp_path), DivergenceRule(cd_ratio=0.0))
    assert off["ball", "neuma"][0]["status"] == "ok"  # 0 = off
    df = tables.table1_synthetic_cd(runs).df
    row = df[(df["Method"] == "NeuMA") & (df["Source"] == "measured")].iloc[0]
    assert row["Ball (Elastomer)"] == "0.10100 (diverged)"  # the measured CD, never "> 100"
    t3 = tables.table3_ablation_cd(runs).df
    assert t3[(t3["Method"] == "w/o Global Align.") & (t3["Source"] == "measured")].iloc[0]["Ball (Elastomer)"] \
        == "0.02000 (diverged)"


def test_table5_law_level_and_lpips_cells(tmp_path):
    _write(tmp_path, "ball", "gca", chamfer_mean=0.00123, lpips_train=None, lpips_reason="no local LPIPS weights",
           psnr_train=25.0, ssim_train=0.9)
    _write(tmp_path, "ball", "neuma", chamfer_mean=0.00234, lpips_train=0.1234, lpips_reason=None, psnr_train=24.0)
    _write(tmp_path, "duck", "nclaw", chamfer_mean=0.01, law_error_uniaxial_pct=40.0, law_error_shear_pct=20.0)
    runs = load_runs(tmp_path)
    t5 = tables.table5_explicit(runs).df
    ours = t5[(t5["Method"] == "Ours") & (t5["Source"] == "measured")].iloc[0]
    assert ours["Ball (Elastomer)"] == "0.00123"
    law = tables.table_law_level(runs).df
    nclaw = law[(law["Method"] == "NCLaw") & (law["Source"] == "measured")].iloc[0]
    assert (nclaw["Uni. (%)"], nclaw["Avg. (%)"]) == ("40.0", "30.0")
    assert law[(law["Method"] == "NCLaw") & (law["Source"] == "paper")].iloc[0]["Avg. (%)"] == "--"
    render = tables.table_render_metrics(runs).df
    lp = dict(zip(render["Method"], render["LPIPS train"]))
    assert lp["Ours"] == tables.NO_LPIPS_WEIGHTS and lp["NeuMA"] == "0.123"


# ------------------------------------------------------------------------------------------ claims

def _cds(root, method, values, seeds=(0,), scenes=SYN, **extra):
    for seed in seeds:
        for scene, value in zip(scenes, values):
            _write(root, scene, method, seed=seed, chamfer_mean=value + 0.001 * seed, **extra)


def _judge(root, text, cfg=claims.ClaimsConfig(resamples=2000)):
    runs = load_runs(root)
    (claim,) = [c for c in claims.paper_claims() if c.text == text]
    return claims.judge(runs, claim, cfg)


GCA_LT_NEUMA = "CD(GCA) < CD(NeuMA) on the synthetic scenes"
REDUCTION = "GCA's average CD is 48% below NeuMA's"


def test_claim_holds(tmp_path):
    _cds(tmp_path, "neuma", [1.0, 2.0, 0.5, 0.8, 0.3, 1.0], seeds=(0, 1, 2))
    _cds(tmp_path, "gca", [0.5, 1.0, 0.25, 0.4, 0.15, 0.5], seeds=(0, 1, 2))  # half of NeuMA's: -50%
    j = _judge(tmp_path, GCA_LT_NEUMA)
    assert j.verdict == claims.HOLDS and j.hi < 0 and (j.n_units, j.n_scenes, j.n_seeds) == (18, 6, 3)
    r = _judge(tmp_path, REDUCTION)
    assert r.verdict == claims.HOLDS and r.effect == pytest.approx(-0.5, abs=0.01)


def test_claim_does_not_hold(tmp_path):
    _cds(tmp_path, "neuma", [0.5, 1.0, 0.25, 0.4, 0.15, 0.5], seeds=(0, 1, 2))
    _cds(tmp_path, "gca", [1.0, 2.0, 0.5, 0.8, 0.3, 1.0], seeds=(0, 1, 2))  # GCA worse everywhere
    assert _judge(tmp_path, GCA_LT_NEUMA).verdict == claims.FAILS
    assert _judge(tmp_path, REDUCTION).verdict == claims.FAILS
    # a real reduction, but far smaller than the paper's 48%: the reduction claim does not hold
    for scene in SYN:
        for seed in (0, 1, 2):
            (tmp_path / scene / ("gca.json" if seed == 0 else f"gca@seed{seed}.json")).unlink()
    _cds(tmp_path, "gca", [0.45, 0.9, 0.225, 0.36, 0.135, 0.45], seeds=(0, 1, 2))  # -10%
    assert _judge(tmp_path, GCA_LT_NEUMA).verdict == claims.HOLDS
    assert _judge(tmp_path, REDUCTION).verdict == claims.FAILS


def test_claim_inconclusive(tmp_path):
    # differences of both signs around 0: the interval contains 0
    _cds(tmp_path, "neuma", [1.0, 1.0, 1.0, 1.0, 1.0, 1.0])
    _cds(tmp_path, "gca", [0.5, 1.5, 0.6, 1.4, 0.7, 1.3])
    j = _judge(tmp_path, GCA_LT_NEUMA)
    assert j.verdict == claims.INCONCLUSIVE and j.lo < 0 < j.hi


def test_claim_too_few_units_is_inconclusive(tmp_path):
    _cds(tmp_path, "neuma", [1.0, 1.0], scenes=("ball", "duck"))
    _cds(tmp_path, "gca", [0.1, 0.1], scenes=("ball", "duck"))  # a huge effect, but 2 units < 3
    j = _judge(tmp_path, GCA_LT_NEUMA)
    assert j.verdict == claims.INCONCLUSIVE and "too few" in j.why
    assert _judge(tmp_path, "CD(GCA) < CD(NeuMA) on the synthetic scenes",
                  claims.ClaimsConfig(resamples=2000, min_units=2)).verdict == claims.HOLDS


def test_untrained_prior_pairs_with_every_seed_and_divergence_shares(tmp_path):
    _cds(tmp_path, "nclaw", [2.0] * 6)
    _cds(tmp_path, "neuma", [1.0] * 6, seeds=(0, 1, 2))
    j = _judge(tmp_path, "CD(NeuMA) < CD(NCLaw) on the synthetic scenes")
    assert j.n_units == 18 and j.verdict == claims.HOLDS
    # a trained method's one record is one unit (session 23: Table 3's first ablation, seed 0 only, made three)
    _cds(tmp_path, "gca", [0.5] * 6, seeds=(0, 1, 2))
    _write(tmp_path, "fish", "no_global", chamfer_mean=0.7)
    j = _judge(tmp_path, "removing it hurts: CD(GCA) < CD(w/o Global Align.)")
    assert (j.n_units, j.n_seeds) == (1, 1) and "too few" in j.why
    for scene in ("ball", "cat"):
        _write(tmp_path, scene, "pacnerf_depth", status="diverged", chamfer_mean=3.0)
        _write(tmp_path, scene, "pacnerf_depth", seed=1, status="diverged", chamfer_mean=None)
        _write(tmp_path, scene, "pacnerf_multiview", status="diverged", chamfer_mean=3.0)
        _write(tmp_path, scene, "pacnerf_multiview", seed=1, status="diverged", chamfer_mean=3.0)
    assert _judge(tmp_path, "PAC-NeRF + Depth (explicit, monocular) diverges").verdict == claims.HOLDS
    assert _judge(tmp_path, "PAC-NeRF (multi-view reference) does not diverge").verdict == claims.FAILS


def test_claims_md_written_by_the_report_and_seeded(tmp_path):
    metrics = tmp_path / "metrics"
    _cds(metrics, "neuma", [1.0, 2.0, 0.5, 0.8, 0.3, 1.0], seeds=(0, 1, 2))
    _cds(metrics, "gca", [0.5, 1.0, 0.25, 0.4, 0.15, 0.5], seeds=(0, 1, 2))
    cfg = ReportConfig(dpi=30, claims=claims.ClaimsConfig(resamples=500))
    build_reports(metrics, tmp_path / "a", cfg)
    build_reports(metrics, tmp_path / "b", cfg)
    text = (tmp_path / "a" / "claims.md").read_text()
    assert text == (tmp_path / "b" / "claims.md").read_text()  # seeded bootstrap: byte-identical
    assert "these verdicts mean nothing" in text  # CI profile
    assert "| holds |" in text and "500 resamples" in text
    assert "| GCA best on 3/3 real-to-sim scenes |" in text  # not run: inconclusive
    assert "claims.md" in (tmp_path / "a" / "README.md").read_text()
    for path in metrics.rglob("*.json"):
        record = json.loads(path.read_text())
        path.write_text(json.dumps({**record, "profile": "paper"}))
    build_reports(metrics, tmp_path / "c", cfg)
    assert "mean nothing" not in (tmp_path / "c" / "claims.md").read_text()


def test_table2_conjunction(tmp_path):
    for scene in ("dragon", "wolf", "pudding"):
        for seed in (0, 1, 2):
            _write(tmp_path, scene, "gca", seed=seed, chamfer_mean=1.0 + 0.01 * seed)
            _write(tmp_path, scene, "neuma", seed=seed, chamfer_mean=2.0 + 0.02 * seed)
        _write(tmp_path, scene, "nclaw", chamfer_mean=3.0)
    cfg = claims.ClaimsConfig(resamples=500)
    summary = [j for j in claims.judge_all(load_runs(tmp_path), cfg) if j.claim.kind == "all"][0]
    assert summary.verdict == claims.HOLDS
    _write(tmp_path, "wolf", "nclaw", chamfer_mean=0.5)  # NCLaw beats GCA on wolf
    summary = [j for j in claims.judge_all(load_runs(tmp_path), cfg) if j.claim.kind == "all"][0]
    assert summary.verdict == claims.FAILS


def test_term_share_table(tmp_path):
    shares = {"share/silhouette/norm": 2.0, "share/silhouette/cos": 0.999, "share/global/norm": 0.001,
              "share/global/cos": 0.01, "share/cpr/norm": 0.5, "share/cpr/cos": 0.2, "share/total/norm": 2.1}
    _write(tmp_path, "ball", "gca", chamfer_mean=0.01, term_shares=shares)
    _write(tmp_path, "ball", "gca", seed=1, chamfer_mean=0.01, term_shares={**shares, "share/silhouette/norm": 4.0})
    _write(tmp_path, "ball", "neuma", chamfer_mean=0.01, term_shares={})  # no iteration measured: no row
    df = tables.table_term_shares(load_runs(tmp_path)).df
    assert list(df.columns) == ["Method", "Runs", "silhouette", "global", "cpr", "total"]
    row = df.iloc[0]
    assert (row["Method"], row["Runs"]) == ("Ours", "2") and len(df) == 1
    assert row["silhouette"] == "3.000 (cos 0.999)" and row["global"] == "0.00100 (cos 0.010)"


def test_table1_says_how_much_the_launch_velocity_ranks_the_prior(tmp_path):
    """Session 21: the per-seed launch estimate's error ranked the prior's CD with rho 0.92. The note computes it
    from the records; records without it (older evaluations) say so instead of a number."""
    for seed, (error, cd) in enumerate(((0.4, 0.01), (2.0, 0.05), (7.0, 0.1))):
        _write(tmp_path, "ball", "nclaw", seed=seed, chamfer_mean=cd, launch_v0_error_m_s=error)
    note = tables.table1_synthetic_cd(load_runs(tmp_path)).notes[0]
    assert "median 2 m/s (range 0.4-7)" in note and "3 (scene, seed) units" in note and "rho" in note
    assert note.rstrip(".").split("CD: ")[1].startswith("1.000")
    _write(tmp_path, "ball", "nclaw", seed=2, chamfer_mean=0.001, launch_v0_error_m_s=7.0)  # negative control
    assert "CD: -0.500" in tables.table1_synthetic_cd(load_runs(tmp_path)).notes[0]
    bare = tmp_path / "old"
    for seed in range(3):
        _write(bare, "ball", "nclaw", seed=seed, chamfer_mean=0.01)
    assert "not in these metrics" in tables.table1_synthetic_cd(load_runs(bare)).notes[0]


def test_launch_error_is_the_distance_to_the_true_launch():
    from gca.pipeline.evaluate import launch_error

    out = launch_error([0.6, -2.0, 3.0], (0.6, -2.0, -1.0))
    assert out == {"launch_v0": [0.6, -2.0, 3.0], "launch_v0_error_m_s": 4.0}


def test_a_verdict_one_scene_carries_is_named_by_the_leave_one_scene_out_check(tmp_path):
    """Session 23's Table 1: "48 % below NeuMA" held on six scenes and was inconclusive without pawn, where NeuMA
    diverged. The verdict stays the six scenes'; the check beside it names the scene that carries it."""
    seeds = tuple(range(6))  # 36 units: a resample without pawn is rare (p = (5/6)^36 ~ 0.001)
    _cds(tmp_path, "neuma", [1.0, 1.0, 10.0, 1.0, 1.0, 1.0], seeds=seeds)
    _cds(tmp_path, "gca", [1.0, 0.9, 1.0, 1.1, 0.95, 1.05], seeds=seeds)  # even, but for pawn
    j = _judge(tmp_path, GCA_LT_NEUMA)
    assert j.verdict == claims.HOLDS
    assert dict(j.without_one)["pawn"] == claims.INCONCLUSIVE
    assert all(v == claims.HOLDS for s, v in j.without_one if s != "pawn") and len(j.without_one) == 6
    text = claims.without_one_text(j)
    assert text.startswith("same without 5 of 6") and "without pawn: inconclusive" in text
    # negative control: an effect on every scene survives the removal of any one
    for f in tmp_path.glob("*/gca*.json"):
        f.unlink()
    _cds(tmp_path, "gca", [0.5, 0.5, 5.0, 0.5, 0.5, 0.5], seeds=seeds)
    j = _judge(tmp_path, GCA_LT_NEUMA)
    assert j.verdict == claims.HOLDS and claims.without_one_text(j) == "same verdict without any one of 6 scenes"
    # one scene measured: no check
    (single,) = [c for c in claims.paper_claims() if c.text == GCA_LT_NEUMA]
    one = claims.judge(load_runs(tmp_path), claims.replace(single, scenes=("ball",)), claims.ClaimsConfig(resamples=500))
    assert one.without_one == () and claims.without_one_text(one) == "—"


def test_leaving_a_scene_out_says_when_too_few_units_are_left(tmp_path):
    _cds(tmp_path, "neuma", [1.0, 1.0], scenes=("ball", "duck"), seeds=(0, 1))
    _cds(tmp_path, "gca", [0.5, 0.5], scenes=("ball", "duck"), seeds=(0, 1))  # 4 units; without one scene: 2 < 3
    j = _judge(tmp_path, GCA_LT_NEUMA)
    assert j.verdict == claims.HOLDS
    assert dict(j.without_one) == {"ball": "inconclusive (too few units)", "duck": "inconclusive (too few units)"}
