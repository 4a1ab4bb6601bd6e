"""Probe a learned neural law for what makes a rollout blow up (a script, not a test).

Given a prior checkpoint (``models/prior/<family>.pt`` or a timing prior) and optionally a training run's
``law.pt`` (its LoRA adapter), prints for the prior and the learned law:

- the CFL wave-speed estimate the simulator uses (``NeuralElasticity.wave_speed``: 1% strain probes);
- the tangent d tau / d F along uniaxial strain (F = I + s e_x e_x: the P-wave modulus lam + 2 mu at s = 0),
  volumetric (F = (1 + s) I: 3K at s = 0) and simple shear (F = I + s e_x e_y: mu), for s in -40% .. +30%: a
  negative entry is a material instability (the law stops resisting that deformation); a large one a wave speed
  sqrt(M / rho) above the estimate;
- the plastic return map F_e = P(F): on how many random states near I (scales 0.05, 0.2, 0.4) one map, and 20 maps in a
  row, *increase* the elastic log-strain |log sigma(F_e)| - |log sigma(F)|. A return map should not (plasticity
  dissipates); one that does injects energy every step.

Usage::

    python benchmarks/law_stability.py --prior models/prior/jelly.pt [--adapter runs/ball/gca/law.pt]
        [--checkpoint runs/ball/gca/checkpoint.pt ...] [--rho 1000]
"""

from __future__ import annotations

import argparse
import math

import torch

from gca.laws.checkpoint import load_adapter, load_prior
from gca.laws.lora import apply_lora

STRAINS = (-0.4, -0.3, -0.2, -0.1, -0.01, 0.01, 0.1, 0.2, 0.3)


def load(prior: str, adapter: str | None, family: str | None):
    """(elasticity, plasticity) in float64 on the CPU, torch reference path; with the adapter when given."""
    p = load_prior(prior)
    e, pl = p.elasticity, p.plasticity
    if adapter:
        apply_lora(e, 16, 16.0)
        apply_lora(pl, 16, 16.0)
        load_adapter(adapter, e, pl, family or p.family)
    e, pl = e.double(), pl.double()
    e.fast_path = pl.fast_path = False
    return e, pl


def load_checkpoint(prior: str, checkpoint: str, family: str | None):
    """(elasticity, plasticity) of a LoRA run's *training* checkpoint (``runs/<scene>/<run>/checkpoint.pt``, written
    every ``train.checkpoint_every`` iterations): the law at that iteration, even of a run that later diverged."""
    e, pl = load(prior, None, family)
    state = torch.load(checkpoint, map_location="cpu", weights_only=False)["law"]
    for name, module in (("elasticity", e), ("plasticity", pl)):
        apply_lora(module, 16, 16.0)
        entries = {k[len(name) + 1:]: v.double() for k, v in state.items() if k.startswith(name + ".")}
        missing = [k for k in module.state_dict() if k.rsplit(".", 1)[-1] in ("lora_A", "lora_B") and k not in entries]
        if missing or not entries:
            raise SystemExit(f"{checkpoint}: not a LoRA run's checkpoint of this prior ({name}: missing {missing[:2]})")
        module.load_state_dict(entries, strict=False)
        module.fast_path = False
    return e.double(), pl.double()


def tangents(law) -> dict:
    """{path: [(s, tangent component)]} for the uniaxial, volumetric and shear paths [Pa]."""
    eye = torch.eye(3, dtype=torch.float64)
    ex, exy = torch.outer(eye[0], eye[0]), torch.outer(eye[0], eye[1])
    paths = {"uniaxial (lam+2mu)": (lambda s: eye + s * ex, ex, lambda M: M[0, 0]),
             "volumetric (3K)": (lambda s: (1 + s) * eye, eye, lambda M: torch.trace(M) / 3),
             "shear (mu)": (lambda s: eye + s * exy, exy, lambda M: M[0, 1])}
    out = {}
    h = 1e-5
    for name, (F_of, dF, pick) in paths.items():
        rows = []
        for s in STRAINS:
            F0 = F_of(s)
            with torch.no_grad():
                M = (law((F0 + h * dF)[None]) - law((F0 - h * dF)[None]))[0] / (2 * h)
            rows.append((s, float(pick(M))))
        out[name] = rows
    return out


def strain_growth(plasticity, seed: int = 0) -> list[tuple[float, float, float]]:
    """[(scale, share of states whose elastic log-strain one map increases, share for 20 maps)]."""
    g = torch.Generator().manual_seed(seed)
    rows = []
    for scale in (0.05, 0.2, 0.4):
        F = torch.eye(3, dtype=torch.float64) + scale * torch.randn(20000, 3, 3, generator=g, dtype=torch.float64)
        F = F[torch.linalg.det(F) > 0.2]
        norm = lambda A: torch.linalg.svdvals(A).log().norm(dim=1)  # noqa: E731
        with torch.no_grad():
            one = plasticity(F)
            many = F
            for _ in range(20):
                many = plasticity(many)
        rows.append((scale, float((norm(one) > norm(F) + 1e-12).double().mean()),
                     float((norm(many) > norm(F) + 1e-12).double().mean())))
    return rows


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--prior", required=True)
    ap.add_argument("--adapter", default=None, help="a run's law.pt (LoRA adapter, rank 16, alpha 16)")
    ap.add_argument("--checkpoint", action="append", default=[],
                    help="a LoRA run's training checkpoint.pt (repeatable): the law at its last saved iteration")
    ap.add_argument("--family", default=None, help="the prior family (default: the prior's)")
    ap.add_argument("--rho", type=float, default=1000.0, help="density [kg/m^3]")
    a = ap.parse_args(argv)
    laws = {"prior": load(a.prior, None, a.family)}
    if a.adapter:
        laws["learned"] = load(a.prior, a.adapter, a.family)
    for path in a.checkpoint:
        laws[path] = load_checkpoint(a.prior, path, a.family)
    for name, (e, pl) in laws.items():
        print(f"== {name}: CFL wave-speed estimate {e.wave_speed(a.rho):.4g} m/s (rho {a.rho:g})")
        for path, rows in tangents(e).items():
            cells = "  ".join(f"{s:+.2f}:{v:9.3g}{'!' if v < 0 else ''}" for s, v in rows)
            top = max(v for _, v in rows)
            print(f"  {path:<20} {cells}   max sqrt(M/rho) {math.sqrt(max(top, 0) / a.rho):.3g} m/s")
        for scale, one, many in strain_growth(pl):
            print(f"  plastic map, |F - I| ~ {scale}: elastic strain grows on {one:.3f} of states (one map), "
                  f"{many:.3f} (20 maps)")


if __name__ == "__main__":
    main()
