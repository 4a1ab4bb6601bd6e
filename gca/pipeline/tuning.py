"""Tuning on calibration scenes only (issue 22 items 1 and 2): the library side of ``python -m gca.pipeline.tune``.

The protocol, from params ``tuning`` (:class:`TuningConfig`):

- **Scenes.** Only scenes with ``calibration: true`` (docs/benchmark.md section 5: objects and materials in no
  table); any other scene is refused (:func:`check_scenes`). The tuning work directory holds only their data (its
  params are restricted to them), so no step of tuning can read a table scene.
- **Budget.** The same for every learned method: ``trials`` x ``iterations`` training iterations x ``seeds``
  on every calibration scene. Only the knobs differ (``tuning.methods.<method>``: GCA's lambda_m, lambda_1,
  lambda_2 of eq. 3 and 7 and its learning rates; NeuMA's learning rates; the PAC-NeRF-style rows' learning rate
  and depth weight). A knob names the params keys it sets; ``factor: true`` multiplies their current values
  (learning rates kept in their ratio), else it sets them.
- **Search.** Trial 0 is the frozen params as they are (the baseline a tuning must beat); trials 1..n-1 a Latin
  hypercube over the knobs' log-ranges, seeded by ``tuning.sampler_seed`` (:func:`trial_values`). Why: with a
  handful of trials in up to four dimensions, a Latin hypercube puts one trial in each of n strata of every knob
  (a grid of n points per knob needs n^d trials, plain random sampling leaves strata empty), and the values are a
  pure function of (seed, n, ranges), so a tuning is reproducible and resumable trial by trial.
- **Objective.** A trial's score is the mean over calibration scenes and seeds of the evaluated Chamfer distance
  (``chamfer_mean``, the tables' metric; a failed run scores +inf). For a method with RDGA terms (GCA) a trial is
  *feasible* only if each RDGA term carries a real share of the gradient, averaged over the calibration scenes and
  seeds: its norm share |g_T| / |g| >= ``share_floor_norm`` and its cosine with the total gradient
  >= ``share_floor_cos`` (``train.term_shares_every``; :func:`gca.train.objective.term_shares`). The chosen trial
  is the feasible one of lowest score; with none feasible, the one of least shortfall (said in the record).
- **Record.** ``tuning/record.json`` (:func:`build_record`): knobs, ranges, every trial's values with its
  per-scene CD and term shares, seeds, budget, the chosen values, date, commit, device; the frozen ``params.yaml``
  cites it (``tuning.record``) and ``tests/test_pipeline_tune.py`` checks that its chosen values are params.yaml's
  (:func:`frozen_mismatches`), so the two cannot drift.
"""

from __future__ import annotations

import copy
import dataclasses
import math
from pathlib import Path
from typing import Iterable, Mapping

import numpy as np

from gca.config import ConfigError, section
from gca.train.methods import RDGA_TERMS, get_method


DEFAULT_METHODS: dict[str, dict[str, dict]] = {
    "gca": {
        "lambda_m": {"keys": ["align.rdga.lambda_mask"], "range": [0.1, 10.0], "factor": False},
        "lambda_1": {"keys": ["align.rdga.lambda1"], "range": [1.0e-3, 10.0], "factor": False},
        "lambda_2": {"keys": ["align.rdga.lambda2"], "range": [1.0e-3, 100.0], "factor": False},
        "lr": {"keys": ["train.lr_elasticity", "train.lr_plasticity"], "range": [0.25, 4.0], "factor": True},
    },
    "neuma": {
        "lr": {"keys": ["train.neuma_lr_scale"], "range": [0.25, 4.0], "factor": False},
    },
    "pacnerf_depth": {
        "lr": {"keys": ["train.lr_explicit"], "range": [2.0e-3, 0.2], "factor": False},
        "lambda_depth": {"keys": ["train.lambda_depth_l1"], "range": [0.1, 10.0], "factor": False},
    },
}


@dataclasses.dataclass(frozen=True)
class Knob:
    """One tuned quantity: log-uniform on [low, high]; it sets ``keys`` to its value, or with ``factor``
    multiplies their frozen values by it."""

    name: str
    keys: tuple[str, ...]
    low: float
    high: float
    factor: bool = False


@dataclasses.dataclass(frozen=True)
class TuningConfig:
    """params ``tuning`` (module doc).

    Attributes:
        record: the tuning record the frozen params cite (``tuning/record.json``); "" = no tuning made yet.
        scenes: the calibration scenes tuned on (each must be ``calibration: true``).
        trials: trials per method, trial 0 the frozen params (the same for every method).
        iterations: training iterations per run (the same for every method; ``train.iterations`` at the paper).
        seeds: training seeds per (trial, scene) (each draws its own nuisances; the same for every method).
        sampler_seed: seed of the Latin hypercube.
        share_floor_norm: each RDGA term's mean gradient norm share |g_T| / |g| must reach this [1].
        share_floor_cos: each RDGA term's mean cosine with the total gradient must reach this [1].
        methods: per learned method, its knobs: ``{name: {keys: [dotted params keys], range: [lo, hi],
            factor: bool}}``.
    """

    record: str = "tuning/record.json"
    scenes: tuple[str, ...] = ("calib_torus", "calib_mushroom", "calib_star")
    trials: int = 8
    iterations: int = 200
    seeds: tuple[int, ...] = (0,)
    sampler_seed: int = 0
    share_floor_norm: float = 0.05
    share_floor_cos: float = 0.05
    methods: dict = dataclasses.field(default_factory=lambda: copy.deepcopy(DEFAULT_METHODS))

    def __post_init__(self):
        if self.trials < 1 or self.iterations < 1:
            raise ValueError("tuning.trials and tuning.iterations must be >= 1")
        if not self.scenes or len(set(self.scenes)) != len(self.scenes):
            raise ValueError(f"tuning.scenes must be a non-empty list of distinct scenes, got {list(self.scenes)}")
        if not self.seeds or len(set(self.seeds)) != len(self.seeds) or any(s < 0 for s in self.seeds):
            raise ValueError(f"tuning.seeds must be distinct integers >= 0, got {list(self.seeds)}")
        if not isinstance(self.methods, Mapping) or not self.methods:
            raise ValueError("tuning.methods must map each learned method to its knobs")
        owner: dict[str, str] = {}
        for method in self.methods:
            get_method(method)
            for knob in self.knobs(method):
                for key in knob.keys:  # a params key tuned for two methods could not hold both choices
                    if owner.setdefault(key, method) != method:
                        raise ValueError(f"tuning.methods: {key} is a knob of both {owner[key]} and {method}")

    def knobs(self, method: str) -> list[Knob]:
        """The knobs of ``method`` (a key of ``methods``), validated."""
        if method not in self.methods:
            raise ConfigError(f"tuning.methods has no {method!r} (tuned methods: {', '.join(self.methods)})")
        out = []
        for name, spec in self.methods[method].items():
            where = f"tuning.methods.{method}.{name}"
            if not isinstance(spec, Mapping) or set(spec) != {"keys", "range", "factor"}:
                raise ValueError(f"{where} must be {{keys: [...], range: [lo, hi], factor: bool}}, got {spec!r}")
            keys, (low, high) = tuple(spec["keys"]), (float(v) for v in spec["range"])
            if not keys or not 0 < low < high or not math.isfinite(high) or not isinstance(spec["factor"], bool):
                raise ValueError(f"{where}: needs keys, 0 < lo < hi and factor true/false, got {spec!r}")
            out.append(Knob(name, keys, low, high, spec["factor"]))
        return out

    def budget(self) -> dict:
        """What every method gets: trials x iterations x seeds on every scene."""
        return {"trials": self.trials, "iterations": self.iterations, "seeds": list(self.seeds),
                "scenes": list(self.scenes), "runs_per_method": self.trials * len(self.seeds) * len(self.scenes),
                "iterations_per_method": self.trials * len(self.seeds) * len(self.scenes) * self.iterations}


def check_scenes(params: Mapping, scenes: Iterable[str]) -> None:
    """Refuse any scene that is not a calibration scene (``calibration: true``): tuning never reads a table scene."""
    table = section(params, "scenes")
    for name in scenes:
        if name not in table:
            raise ConfigError(f"tuning: unknown scene {name!r}")
        if table[name].get("calibration") is not True:
            raise ConfigError(f"tuning: scene {name!r} is not a calibration scene (calibration: true): tuning reads "
                              "the calibration scenes only, never a table scene (issue 22)")


def latin_hypercube(n: int, d: int, seed: int) -> np.ndarray:
    """``n`` points in [0, 1)^d, one in each of the n equal strata of every dimension (seeded, reproducible)."""
    rng = np.random.default_rng(seed)
    u = (np.arange(n)[:, None] + rng.random((n, d))) / n
    for j in range(d):
        u[:, j] = u[rng.permutation(n), j]
    return u


def frozen_value(params: Mapping, knob: Knob) -> float:
    """The knob's value in ``params``: 1 for a factor knob, else its first key's value."""
    return 1.0 if knob.factor else float(section(params, knob.keys[0]))


def trial_values(cfg: TuningConfig, method: str, params: Mapping) -> list[dict[str, float]]:
    """Every trial's knob values: trial 0 the frozen params, then the Latin hypercube over the log-ranges (its
    seed: ``sampler_seed`` and the method's position in ``methods``, so each method's draw is its own)."""
    knobs = cfg.knobs(method)
    trials = [{k.name: frozen_value(params, k) for k in knobs}]
    if cfg.trials > 1:
        u = latin_hypercube(cfg.trials - 1, len(knobs), int(np.random.SeedSequence(
            [cfg.sampler_seed, list(cfg.methods).index(method)]).generate_state(1)[0]))
        for row in u:
            trials.append({k.name: float(math.exp(math.log(k.low) + x * (math.log(k.high) - math.log(k.low))))
                           for k, x in zip(knobs, row)})
    return trials


def _set(params: dict, dotted: str, value) -> None:
    *head, last = dotted.split(".")
    node = params
    for key in head:
        node = node[key]
    if last not in node:
        raise ConfigError(f"tuning: knob key {dotted} is not in params")
    node[last] = value


def apply_values(params: Mapping, cfg: TuningConfig, method: str, values: Mapping[str, float]) -> dict:
    """A copy of the resolved ``params`` with the knobs of ``method`` set to ``values``."""
    out = copy.deepcopy(dict(params))
    for knob in cfg.knobs(method):
        for key in knob.keys:
            _set(out, key, float(section(params, key)) * values[knob.name] if knob.factor else values[knob.name])
    return out


def param_values(params: Mapping, cfg: TuningConfig, method: str, values: Mapping[str, float]) -> dict[str, float]:
    """The params keys a trial's ``values`` set, with their values (what params.yaml would hold)."""
    applied = apply_values(params, cfg, method, values)
    return {key: float(section(applied, key)) for knob in cfg.knobs(method) for key in knob.keys}


def rdga_terms(method: str) -> list[str]:
    """The RDGA terms the method declares (GCA: silhouette, global, anchor), whose shares are constrained."""
    return [t for t in get_method(method).terms if t in RDGA_TERMS]


def score(cfg: TuningConfig, method: str, units: list[dict]) -> dict:
    """One trial's objective from its runs (``units``: one per (scene, seed): ``chamfer_mean``, ``status``,
    ``term_shares``): the mean CD (inf when a run failed or is missing), each RDGA term's mean norm share and
    cosine, whether they reach the floors, and the shortfall (0 when feasible)."""
    expected = len(cfg.scenes) * len(cfg.seeds)
    cds = [u.get("chamfer_mean") for u in units]
    ok = len(units) == expected and all(u.get("status") != "failed" and c is not None and math.isfinite(c) for u, c in
                                        zip(units, cds))
    out = {"objective": float(np.mean(cds)) if ok else math.inf, "complete": len(units) == expected, "shares": {},
           "shortfall": 0.0}
    for term in rdga_terms(method):
        norms, coss = [], []
        for u in units:
            sh = u.get("term_shares") or {}
            total = sh.get("share/total/norm")
            if total and sh.get(f"share/{term}/norm") is not None:
                norms.append(sh[f"share/{term}/norm"] / total)
                coss.append(sh[f"share/{term}/cos"])
        norm = float(np.mean(norms)) if norms else 0.0
        cos = float(np.mean(coss)) if coss else -1.0
        out["shares"][term] = {"norm_share": norm, "cos": cos}
        out["shortfall"] += max(0.0, cfg.share_floor_norm - norm) + max(0.0, cfg.share_floor_cos - cos)
    out["feasible"] = out["shortfall"] == 0.0 and math.isfinite(out["objective"])
    return out


def choose(trials: list[dict]) -> int:
    """The chosen trial: the feasible one of lowest objective; with none feasible, the least shortfall among the
    trials whose runs all finished (then the lowest objective; a failed trial last). ``trials``: each with ``score``
    (:func:`score`)."""
    feasible = [i for i, t in enumerate(trials) if t["score"]["feasible"]]
    if feasible:
        return min(feasible, key=lambda i: (trials[i]["score"]["objective"], i))
    return min(range(len(trials)), key=lambda i: (not math.isfinite(trials[i]["score"]["objective"]),
                                                  trials[i]["score"]["shortfall"], trials[i]["score"]["objective"], i))


def frozen_mismatches(params: Mapping, record: Mapping) -> list[str]:
    """The params keys whose value differs from the record's chosen value (relative 1e-9), one line each."""
    bad = []
    for method, entry in record.get("methods", {}).items():
        for key, value in entry["chosen"]["params"].items():
            have = float(section(params, key))
            if not math.isclose(have, float(value), rel_tol=1e-9, abs_tol=0.0):
                bad.append(f"{key}: params.yaml {have!r}, tuning record ({method}) {value!r}")
    return bad


def params_change(record: Mapping, record_path: str) -> str:
    """The params.yaml lines to apply the record's choice, one ``key: value`` per knob key (full precision: the
    test of the frozen params compares at 1e-9), and its citation."""
    lines = [f"tuning.record: {record_path}"]
    for method, entry in record.get("methods", {}).items():
        trial = entry["chosen"]["trial"]
        note = "" if entry["chosen"]["feasible"] else " (no trial reached the share floors: least shortfall)"
        lines.append(f"# {method}: trial {trial}{note}")
        lines += [f"{key}: {float(value)!r}" for key, value in entry["chosen"]["params"].items()]
    return "\n".join(lines)
