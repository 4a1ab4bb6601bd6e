"""The claims table: each claim of the paper judged on the measured metrics alone (``claims.md``, ``claims.csv``).

Every claim is a statistic of paired per-unit measurements with a seeded percentile bootstrap interval and a
verdict computed from that interval; nothing here is written by hand.

- **Units.** A unit is one (scene, seed) where both methods of a comparison left a finite value (the measured
  value, diverged runs included: their kept law's CD). A method that does not train (``nclaw``) runs every seed
  too (its launch velocity is estimated from the seed's own nuisance draw); a single record of it (results made
  before that) is paired with every seed of the other method on that scene. A trained method's single record
  is one unit (session 23: Table 3's first ablations, seed 0 only, counted three units each before). The
  bootstrap resamples units with replacement (``ClaimsConfig.resamples`` times, ``numpy.random.default_rng(ClaimsConfig.seed)``).
- **Kinds** (the statistic, and how its ``confidence`` interval [lo, hi] decides):
  - ``less``: mean of the paired differences d = a - b; *holds* when hi < 0, *does not hold* when lo > 0.
  - ``reduction``: relative change mean(a) / mean(b) - 1 against the paper's value r (< 0): *holds* when the
    interval excludes 0 and reaches r (lo <= r, hi < 0), *does not hold* when lo > r (a smaller reduction
    than claimed, or none).
  - ``parity``: relative change mean(a) / mean(b) - 1 against ``parity_margin`` m: *holds* when hi < m
    (a is not worse than b by more than m), *does not hold* when lo > m.
  - ``diverges`` / ``stable``: the share of a method's runs with status ``diverged`` (resp. not diverged);
    *holds* when lo > 1/2, *does not hold* when hi < 1/2.
  Otherwise the verdict is *inconclusive*; it is also inconclusive, whatever the interval, with fewer than
  ``ClaimsConfig.min_units`` units (too few scenes or seeds), and says so.
- **Without one scene** (a sensitivity check beside the verdict, never replacing it): a claim measured on several
  scenes is judged again with each scene's units left out, by the same rule and bootstrap; the column names the
  scenes whose removal changes the verdict. A verdict that one scene carries (a baseline diverging there, say)
  reads so at once (session 23: Table 1's "48 % below NeuMA" holds on six scenes and is inconclusive without pawn).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Callable, Mapping, Sequence

import numpy as np
import pandas as pd

from gca.report import paper
from gca.report.runs import Runs, finite, format_number

HOLDS, FAILS, INCONCLUSIVE = "holds", "does not hold", "inconclusive"
CD_KEY = "chamfer_mean"
LAW_KEY = "law_error_average_pct"  # (uniaxial + shear) / 2 of one record (derived here)


@dataclass(frozen=True)
class ClaimsConfig:
    """Knobs of the claims table (params ``report.claims``)."""

    resamples: int = 10000  # bootstrap resamples of the units
    seed: int = 0  # numpy Generator seed of the bootstrap
    confidence: float = 0.95  # two-sided percentile interval
    min_units: int = 3  # fewer paired (scene, seed) units: inconclusive whatever the interval
    parity_margin: float = 0.1  # "accuracy parity": a may be worse than b by at most this fraction


@dataclass(frozen=True)
class Claim:
    """One claim of the paper: ``kind`` (see the module doc) of methods ``a`` vs ``b`` on ``scenes``."""

    table: str
    text: str
    kind: str
    a: str
    b: str | None
    scenes: tuple[str, ...]
    key: str = CD_KEY
    paper_value: float | None = None  # the published effect (reduction: relative change)
    paper_text: str = ""


@dataclass(frozen=True)
class Judgement:
    """A claim's measured effect, its interval, its units and its verdict (with the reason)."""

    claim: Claim
    effect: float | None
    lo: float | None
    hi: float | None
    n_units: int
    n_scenes: int
    n_seeds: int
    verdict: str
    why: str
    without_one: tuple[tuple[str, str], ...] = ()  # (scene left out, verdict without it), scenes measured >= 2


def _value(record: Mapping, key: str) -> float | None:
    if key == LAW_KEY:
        uni, shear = finite(record.get("law_error_uniaxial_pct")), finite(record.get("law_error_shear_pct"))
        return None if uni is None or shear is None else (uni + shear) / 2
    return finite(record.get(key))


def _usable(records: Sequence[Mapping] | None) -> list[Mapping]:
    return [r for r in records or () if r["status"] != "failed"]


def _trains(method: str) -> bool:
    """Whether ``method`` trains (``gca.train.methods``; an unknown name is taken as trained: no broadcast)."""
    from gca.train.methods import METHODS

    return method not in METHODS or METHODS[method].trains


def paired_units(runs: Runs, a: str, b: str, scenes: Sequence[str], key: str) -> list[tuple[str, int, float, float]]:
    """``(scene, seed, value of a, value of b)`` of every unit both methods measured (module doc)."""
    units = []
    for scene in scenes:
        ra = {r["seed"]: v for r in _usable(runs.get((scene, a))) if (v := _value(r, key)) is not None}
        rb = {r["seed"]: v for r in _usable(runs.get((scene, b))) if (v := _value(r, key)) is not None}
        # an untrained method's one record pairs with each seed of the other; a trained method's one record (a grid
        # still running: Table 3's first ablations, session 23) is one unit, never three
        if len(ra) == 1 and len(rb) > 1 and not _trains(a):
            ra = dict.fromkeys(rb, next(iter(ra.values())))
        elif len(rb) == 1 and len(ra) > 1 and not _trains(b):
            rb = dict.fromkeys(ra, next(iter(rb.values())))
        units += [(scene, seed, ra[seed], rb[seed]) for seed in sorted(set(ra) & set(rb))]
    return units


def share_units(runs: Runs, method: str, scenes: Sequence[str], diverged: bool) -> list[tuple[str, int, float]]:
    """``(scene, seed, 1.0 or 0.0)``: whether each run of ``method`` diverged (``diverged``) or not."""
    return [(scene, r["seed"], float((r["status"] == "diverged") == diverged))
            for scene in scenes for r in _usable(runs.get((scene, method)))]


def bootstrap(columns: Sequence[np.ndarray], statistic: Callable[..., np.ndarray], cfg: ClaimsConfig
              ) -> tuple[float, float, float]:
    """``(statistic on the units, lo, hi)``: the percentile interval of ``statistic`` over ``cfg.resamples``
    resamples of the units (rows of ``columns``) with replacement, seeded by ``cfg.seed``.

    ``statistic`` takes the columns, each ``[R, n]`` (R resamples) and returns ``[R]``."""
    n = len(columns[0])
    rng = np.random.default_rng(cfg.seed)
    idx = rng.integers(0, n, size=(cfg.resamples, n))
    stats = statistic(*(c[idx] for c in columns))
    point = float(statistic(*(c[None, :] for c in columns))[0])
    tail = (1 - cfg.confidence) / 2 * 100
    lo, hi = np.percentile(stats, [tail, 100 - tail])
    return point, float(lo), float(hi)


def _relative(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return a.mean(axis=-1) / b.mean(axis=-1) - 1


def _decide(claim: Claim, lo: float, hi: float, cfg: ClaimsConfig) -> tuple[str, str]:
    """The verdict of the interval [lo, hi] for ``claim.kind`` (module doc) and the reason."""
    if claim.kind == "less":
        if hi < 0:
            return HOLDS, "the interval of a - b lies below 0"
        if lo > 0:
            return FAILS, "the interval of a - b lies above 0"
        return INCONCLUSIVE, "the interval of a - b contains 0"
    if claim.kind == "reduction":
        r = claim.paper_value
        if lo > r:
            return FAILS, f"the interval lies above the paper's {r:+.1%} (a smaller reduction, or none)"
        if hi < 0:
            return HOLDS, f"the interval reaches the paper's {r:+.1%} and excludes 0"
        return INCONCLUSIVE, "the interval contains 0"
    if claim.kind == "parity":
        m = cfg.parity_margin
        if hi < m:
            return HOLDS, f"a is worse than b by less than the parity margin {m:.0%}"
        if lo > m:
            return FAILS, f"a is worse than b by more than the parity margin {m:.0%}"
        return INCONCLUSIVE, f"the interval contains the parity margin {m:.0%}"
    if lo > 0.5:
        return HOLDS, "the share's interval lies above 1/2"
    if hi < 0.5:
        return FAILS, "the share's interval lies below 1/2"
    return INCONCLUSIVE, "the share's interval contains 1/2"


def judge(runs: Runs, claim: Claim, cfg: ClaimsConfig = ClaimsConfig()) -> Judgement:
    """Measure ``claim`` on ``runs`` and decide it, then again without each of its measured scenes (module doc:
    ``Judgement.without_one``) where it was measured on two scenes or more."""
    j = _judge_once(runs, claim, cfg)
    if j.n_scenes < 2:
        return j
    measured = sorted({u[0] for u in _units(runs, claim)}, key=claim.scenes.index)
    without = []
    for s in measured:
        w = _judge_once(runs, replace(claim, scenes=tuple(x for x in claim.scenes if x != s)), cfg)
        # too few units left is not the scene carrying the verdict: said so (review)
        without.append((s, w.verdict + (" (too few units)" if w.why.startswith("too few") else "")))
    return replace(j, without_one=tuple(without))


def without_one_text(j: Judgement) -> str:
    """The ``Without one scene`` cell: how many leave-one-scene-out verdicts equal the verdict, and which differ."""
    if not j.without_one:
        return "—"
    changed = [(s, v) for s, v in j.without_one if v != j.verdict]
    same = f"same verdict without any one of {len(j.without_one)} scenes"
    if not changed:
        return same
    return (f"same without {len(j.without_one) - len(changed)} of {len(j.without_one)}; "
            + "; ".join(f"without {s}: {v}" for s, v in changed))


def _units(runs: Runs, claim: Claim) -> list[tuple]:
    """The claim's units: :func:`share_units` of a share claim, else :func:`paired_units` (scene first)."""
    if claim.kind in ("diverges", "stable"):
        return share_units(runs, claim.a, claim.scenes, claim.kind == "diverges")
    return paired_units(runs, claim.a, claim.b, claim.scenes, claim.key)


def _judge_once(runs: Runs, claim: Claim, cfg: ClaimsConfig) -> Judgement:
    """Measure ``claim`` on ``runs`` and decide it (module doc), on its own scenes only."""
    units = _units(runs, claim)
    if claim.kind in ("diverges", "stable"):
        columns = [np.array([u[2] for u in units], dtype=float)]
        statistic = lambda s: s.mean(axis=-1)  # noqa: E731
    else:
        columns = [np.array([u[2] for u in units], dtype=float), np.array([u[3] for u in units], dtype=float)]
        statistic = (lambda a, b: (a - b).mean(axis=-1)) if claim.kind == "less" else _relative  # noqa: E731
    n_scenes = len({u[0] for u in units})
    n_seeds = len({u[1] for u in units})
    if not units:
        return Judgement(claim, None, None, None, 0, 0, 0, INCONCLUSIVE, "no measured units (not run)")
    effect, lo, hi = bootstrap(columns, statistic, cfg)
    if not all(math.isfinite(v) for v in (effect, lo, hi)):
        return Judgement(claim, effect, lo, hi, len(units), n_scenes, n_seeds, INCONCLUSIVE, "a non-finite statistic")
    if len(units) < cfg.min_units:
        return Judgement(claim, effect, lo, hi, len(units), n_scenes, n_seeds, INCONCLUSIVE,
                         f"too few units: {len(units)} < {cfg.min_units} (scenes x seeds)")
    verdict, why = _decide(claim, lo, hi, cfg)
    return Judgement(claim, effect, lo, hi, len(units), n_scenes, n_seeds, verdict, why)


def all_of(judgements: Sequence[Judgement], table: str, text: str, paper_text: str) -> Judgement:
    """A conjunction of the claims of ``table`` (Table 2's "best on 3/3"): holds when every one holds, does
    not hold when any does not, else inconclusive."""
    parts = [j for j in judgements if j.claim.table == table]
    verdicts = [j.verdict for j in parts]
    if parts and all(v == HOLDS for v in verdicts):
        verdict, why = HOLDS, f"all {len(parts)} comparisons hold"
    elif FAILS in verdicts:
        verdict, why = FAILS, f"{verdicts.count(FAILS)} of {len(parts)} comparisons do not hold"
    else:
        verdict, why = INCONCLUSIVE, f"{verdicts.count(HOLDS)} of {len(parts)} comparisons hold, none fails"
    claim = Claim(table, text, "all", "gca", None, tuple(sorted({s for j in parts for s in j.claim.scenes})),
                  paper_text=paper_text)
    return Judgement(claim, None, None, None, sum(j.n_units for j in parts), len(claim.scenes),
                     max((j.n_seeds for j in parts), default=0), verdict, why)


def judge_all(runs: Runs, cfg: ClaimsConfig = ClaimsConfig()) -> list[Judgement]:
    """Every claim of :func:`paper_claims` judged, with Table 2's conjunction after its comparisons."""
    judgements = [judge(runs, claim, cfg) for claim in paper_claims()]
    last = max(i for i, j in enumerate(judgements) if j.claim.table == "Table 2")
    summary = all_of(judgements, "Table 2", "GCA best on 3/3 real-to-sim scenes", "3/3")
    return judgements[:last + 1] + [summary] + judgements[last + 1:]


def _paper_reduction(table: Mapping, a: str, b: str) -> float:
    return table[a]["average"] / table[b]["average"] - 1


TRUE_LAUNCH_KEY = "chamfer_mean_true_launch"  # gca.eval.evaluate.chamfer_from_launch: each law rolled out from the
# scene's true launch velocity (session 21: the per-seed launch estimate ranked Table 1's CDs, rho 0.92)


def paper_claims() -> list[Claim]:
    """Every claim of the paper this project can measure, in the paper's order; published effects from
    :mod:`gca.report.paper`."""
    syn, real = paper.SYNTHETIC_SCENES, paper.REAL_TO_SIM_SCENES
    t1 = paper.TABLE1_SYNTHETIC_CD
    r1 = _paper_reduction(t1, "gca", "neuma")
    law = paper.LAW_LEVEL_ERROR_PCT
    r_law = law["gca"]["average"] / law["neuma"]["average"] - 1
    claims = [
        Claim("Table 1", "CD(GCA) < CD(NeuMA) on the synthetic scenes", "less", "gca", "neuma", syn,
              paper_text=f"{t1['gca']['average']} < {t1['neuma']['average']}"),
        Claim("Table 1", "CD(NeuMA) < CD(NCLaw) on the synthetic scenes", "less", "neuma", "nclaw", syn,
              paper_text=f"{t1['neuma']['average']} < {t1['nclaw']['average']}"),
        Claim("Table 1", "GCA's average CD is 48% below NeuMA's", "reduction", "gca", "neuma", syn, paper_value=r1,
              paper_text=f"{r1:+.1%}"),
        Claim("Table 1 (diagnostic)", "from the true launch (evaluation only): CD(GCA) < CD(NeuMA)", "less", "gca",
              "neuma", syn, key=TRUE_LAUNCH_KEY, paper_text="not in the paper: the laws without the launch estimate"),
    ]
    t2 = paper.TABLE2_REAL_TO_SIM_CD
    for scene in real:
        for other in ("neuma", "nclaw"):
            claims.append(Claim("Table 2", f"CD(GCA) < CD({paper.METHODS[other]}) on {scene} (best on 3/3)", "less",
                                "gca", other, (scene,), paper_text=f"{t2['gca'][scene]} < {t2[other][scene]}"))
    t3 = paper.TABLE3_ABLATION_CD
    for method in ("no_global", "no_anchor", "rank_to_l1", "no_rdga", "no_cpr"):
        published = t3[method]
        text = "diverged" if published["ball"] == paper.DIVERGED else \
            f"{np.mean([published[s] for s in syn]):.3f} > {np.mean([t3['gca'][s] for s in syn]):.3f}"
        claims.append(Claim("Table 3", f"removing it hurts: CD(GCA) < CD({paper.METHODS[method]})", "less", "gca",
                            method, syn, paper_text=text))
    claims.append(Claim("Table 3", "w/o Global Align. diverges", "diverges", "no_global", None, syn,
                        paper_text="> 100 (Diverged) on 6/6"))
    t4 = paper.TABLE4_EFFICIENCY
    claims += [
        Claim("Table 4", "LoRA's CD on par with full fine-tuning (or better)", "parity", "gca", "gca_full_ft", syn,
              paper_text=f"{t4['gca']['cd']} vs {t4['gca_full_ft']['cd']}"),
        Claim("Table 4", "LoRA's peak memory below full fine-tuning's", "less", "gca", "gca_full_ft", syn,
              key="peak_memory_gib", paper_text=f"{t4['gca']['memory_gb']} vs {t4['gca_full_ft']['memory_gb']} GB"),
        Claim("Table 4", "LoRA's training time below full fine-tuning's", "less", "gca", "gca_full_ft", syn,
              key="train_seconds", paper_text=f"{t4['gca']['train_min']} vs {t4['gca_full_ft']['train_min']} min"),
    ]
    t5 = ("ball", "cat")
    claims += [
        Claim("Table 5", "PAC-NeRF + Depth (explicit, monocular) diverges", "diverges", "pacnerf_depth", None, t5,
              paper_text="> 100 (Diverged)"),
        Claim("Table 5", "PAC-NeRF (multi-view reference) does not diverge", "stable", "pacnerf_multiview", None, t5,
              paper_text="0.85, 0.29"),
        Claim("Table 5", "NeuMA (multi-view reference) does not diverge", "stable", "neuma_multiview", None, t5,
              paper_text="0.98, 0.35"),
    ]
    t6 = paper.TABLE6_OOD
    claims += [
        Claim("Table 6", "target law removed from CPR: CD(GCA) < CD(NeuMA)", "less", "cpr_target_removed", "neuma",
              ("ball", "cat"), paper_text=f"{t6['cpr_target_removed']['ball']}, {t6['cpr_target_removed']['cat']} < "
                                          f"{t6['neuma']['ball']}, {t6['neuma']['cat']}"),
        Claim("Table 6", "composite material: CD(GCA) < CD(NeuMA)", "less", "gca", "neuma", ("composite",),
              paper_text=f"{t6['gca']['composite']} < {t6['neuma']['composite']}"),
        Claim("Law level", "law error(GCA) < law error(NeuMA)", "less", "gca", "neuma", (paper.LAW_SCENE,),
              key=LAW_KEY, paper_text=f"{law['gca']['average']}% < {law['neuma']['average']}%"),
        Claim("Law level", "law error 39.6% -> 8.0%", "reduction", "gca", "neuma", (paper.LAW_SCENE,), key=LAW_KEY,
              paper_value=r_law, paper_text=f"{r_law:+.1%}"),
    ]
    return claims


def _fmt(value: float | None, kind: str) -> str:
    if value is None:
        return "—"
    if kind in ("reduction", "parity", "diverges", "stable"):
        return f"{value:+.1%}" if kind in ("reduction", "parity") else f"{value:.3f}"
    return format_number(value, 3)


def claims_frame(judgements: Sequence[Judgement]) -> pd.DataFrame:
    """One row per claim: table, claim, paper, measured effect, interval, units, verdict, reason."""
    rows = []
    for j in judgements:
        c = j.claim
        effect = {"less": "mean(a - b)", "reduction": "mean(a)/mean(b) - 1", "parity": "mean(a)/mean(b) - 1",
                  "diverges": "share diverged", "stable": "share not diverged", "all": "all of the above"}[c.kind]
        rows.append({"Table": c.table, "Claim": c.text, "a": c.a, "b": c.b or "", "Metric": c.key,
                     "Paper": c.paper_text, "Statistic": effect, "Measured": _fmt(j.effect, c.kind),
                     "95% interval": "—" if j.lo is None else f"[{_fmt(j.lo, c.kind)}, {_fmt(j.hi, c.kind)}]",
                     "Units (scenes x seeds)": f"{j.n_units} ({j.n_scenes} x {j.n_seeds})",
                     "Verdict": j.verdict, "Why": j.why, "Without one scene": without_one_text(j)})
    return pd.DataFrame(rows)


def claims_markdown(df: pd.DataFrame, info: Mapping[str, str], cfg: ClaimsConfig, markdown_table) -> str:
    """``claims.md``: header (profile, device, bootstrap, rules), the CI warning where it applies, the table."""
    lines = ["# Claims of the paper, judged on the measured metrics", "",
             "Generated by the `report` stage from the metrics JSON only (`gca.report.claims`); do not edit by hand.",
             ""]
    if info.get("profile") != "paper":
        lines += [f"> **Profile `{info.get('profile')}`: these verdicts mean nothing.** The runs are reduced to "
                  "a smoke test of the machinery (tiny scenes, a few iterations, few seeds); only the paper "
                  "profile's claims table says whether the paper's claims hold.", ""]
    lines += [f"- Measured at: profile `{info.get('profile')}`, device `{info.get('device')}`, {info.get('runs')} "
              f"metrics files; code: evaluated at `{info.get('commit', 'unknown')}`, trained at "
              f"`{info.get('train_commit', 'unknown')}`.",
              f"- Divergence: {info.get('divergence', '')}.",
              f"- Interval: {cfg.confidence:.0%} percentile bootstrap over the paired units, {cfg.resamples} "
              f"resamples, numpy seed {cfg.seed}. A unit is one (scene, seed) both methods measured (diverged runs "
              "with their measured value); an untrained method's one record pairs with every seed.",
              f"- Verdicts: `less` holds when the interval of mean(a - b) lies below 0 and does not hold when it "
              "lies above; `reduction` holds when the interval of mean(a)/mean(b) - 1 excludes 0 and reaches the "
              "paper's value, does not hold when it lies above it; `parity` holds when the interval lies below "
              f"+{cfg.parity_margin:.0%}; a share holds above 1/2. Otherwise inconclusive, and always inconclusive "
              f"with fewer than {cfg.min_units} units.",
              "- Without one scene (a sensitivity check, not the verdict): the claim judged again by the same rule "
              "with each measured scene's units left out; the scenes whose removal changes the verdict are named.",
              ""]
    return "\n".join(lines) + "\n" + markdown_table(df)
