"""The analytic laws' per-step path never synchronises with the host (so a frame of MPM steps with
an analytic law can be captured in a CUDA graph, ``gca.sim.graph``).

CPU twin: every analytic elasticity x plasticity of the presets (and a composite) runs its forward
and backward under :func:`tests.host_sync.no_host_sync`, which raises on ``.item()``, ``bool(t)``,
``nonzero``, boolean-mask indexing, ... Negative controls: the validated ``lame`` and an ``.item()``
in a law's backward are caught. On CUDA: torch's sync debug mode in ``error`` and a FrameGraphs
capture that stays captured (no "capture ... failed, running eagerly" warning).
"""

from __future__ import annotations

import sys
import warnings
from pathlib import Path

import pytest
import torch

from gca.laws.base import Elasticity, Material, lame
from gca.laws.plastic import IdentityPlasticity
from gca.laws.presets import ELASTICITIES, PLASTICITIES, material_from_preset
sys.path.insert(0, str(Path(__file__).parent))
from host_sync import HostSync, no_host_sync  # noqa: E402

EXTRA = {"von_mises": {"yield_stress": 2.0e3}, "drucker_prager": {"friction_angle": 25.0},
         "viscoplastic": {"yield_stress": 2.0e3, "viscosity": 20.0, "flow_index": 0.6}}
COMPOSITE = {"parts": [
    {"fraction": 0.4, "elasticity": "neo_hookean", "plasticity": "identity", "E": 1.0e5, "nu": 0.3},
    {"fraction": 0.3, "elasticity": "sigma", "plasticity": "von_mises", "E": 3.0e5, "nu": 0.25, "yield_stress": 5.0e3},
    {"fraction": 0.3, "elasticity": "volume", "plasticity": "sigma", "E": 5.0e4, "nu": 0.3}]}


def _preset(el: str, pl: str) -> dict:
    return {"elasticity": el, "plasticity": pl, "E": 2.0e5, "nu": 0.3, **EXTRA.get(pl, {})}


def _F(n: int, device="cpu", dtype=torch.float32, seed: int = 0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    F = torch.eye(3, dtype=torch.float64) + 0.3 * torch.randn(n, 3, 3, generator=g, dtype=torch.float64)
    F[0] = torch.eye(3, dtype=torch.float64)  # rest: repeated singular values
    return F.to(device=device, dtype=dtype)


def _one_step(material, F: torch.Tensor) -> tuple[torch.Tensor, ...]:
    """stress + project and their backward (what a frame's forward and backward graphs run)."""
    F = F.detach().requires_grad_(True)
    tau = material.stress(F)
    F_e = material.project(F)
    params = [p for p in material.parameters() if p.requires_grad]
    loss = (tau * tau).sum() * 1e-10 + (F_e * F_e).sum()
    return torch.autograd.grad(loss, [F, *params], allow_unused=True)


CASES = [(e, p) for e in ELASTICITIES for p in PLASTICITIES]


@pytest.mark.parametrize("el,pl", CASES, ids=[f"{e}-{p}" for e, p in CASES])
def test_analytic_law_step_has_no_host_sync(el, pl):
    material = material_from_preset(_preset(el, pl), dt=1e-3)
    F = _F(64)
    expected = _one_step(material, F)  # outside the detector: the reference values
    with no_host_sync():
        got = _one_step(material, F)
    for g, e in zip(got, expected):
        assert (g is None) == (e is None)
        if g is not None:
            assert torch.equal(g, e)
    assert torch.isfinite(got[0]).all() and got[0].abs().sum() > 0  # the step really ran, with a gradient


def test_composite_material_step_has_no_host_sync():
    material = material_from_preset(COMPOSITE, dt=1e-3, n_particles=50)
    F = _F(50)
    with no_host_sync():
        grads = _one_step(material, F)
    assert torch.isfinite(grads[0]).all()


def test_validation_stays_at_construction():
    """A bad Poisson ratio is still refused, when the law is built (outside the per-step path)."""
    with pytest.raises(ValueError, match="Poisson"):
        material_from_preset(_preset("corotated", "identity") | {"nu": 0.5})


def test_detector_catches_syncs_negative_controls():
    x = torch.linspace(-1.0, 1.0, 8)
    for op in (lambda: x.sum().item(), lambda: bool((x > 0).any()), lambda: float(x[0]), lambda: x[x > 0],
               lambda: torch.nonzero(x), lambda: x.tolist(), lambda: torch.where(x > 0),
               lambda: lame(torch.tensor(1e5), torch.tensor(0.3))):  # the validated form: a sync
        with no_host_sync(), pytest.raises(HostSync):
            op()
    with no_host_sync():  # and sync-free ops pass
        torch.where(x > 0, x, torch.zeros_like(x)).clamp(min=0).sum()


class _SyncInBackward(torch.autograd.Function):
    @staticmethod
    def forward(ctx, F):
        return F * 2.0

    @staticmethod
    def backward(ctx, g):
        if g.abs().max().item() > 1e30:  # a host read inside a backward, as a bad law might do
            raise AssertionError
        return 2.0 * g


class _BadElasticity(Elasticity):
    def forward(self, F):
        return _SyncInBackward.apply(F)

    def wave_speed(self, rho) -> float:
        return 1.0


def test_detector_sees_a_sync_in_a_law_backward():
    material = Material(_BadElasticity(), IdentityPlasticity(), 1000.0)
    F = _F(4)
    with no_host_sync(), pytest.raises(HostSync):
        _one_step(material, F)


# -- CUDA ---------------------------------------------------------------------------------------------


@pytest.mark.gpu
@pytest.mark.parametrize("el,pl", CASES, ids=[f"{e}-{p}" for e, p in CASES])
def test_analytic_law_step_has_no_cuda_sync(el, pl):
    material = material_from_preset(_preset(el, pl), dt=1e-3).cuda()
    F = _F(256, "cuda")
    _one_step(material, F)  # warm-up (warp module load, lazy inits)
    torch.cuda.synchronize()
    torch.cuda.set_sync_debug_mode("error")
    try:
        _one_step(material, F)
    finally:
        torch.cuda.set_sync_debug_mode("default")


@pytest.mark.gpu
@pytest.mark.parametrize("name", ["elastomer", "rubber", "granular", "non_newtonian", "composite"])
def test_analytic_material_frame_is_captured(name):
    from gca.config import load
    from gca.sim.graph import FrameGraphs
    from gca.sim.solver import MPMSolver, SimConfig

    preset = load(None, "params.yaml")["materials"][name] if name != "composite" else COMPOSITE
    n = 2000
    material = material_from_preset(preset, dt=1e-4, n_particles=n).cuda()
    solver = MPMSolver(SimConfig(n_grid=16, dt=1e-4), "cuda")
    g = torch.Generator().manual_seed(0)
    x = (0.4 + 0.2 * torch.rand(n, 3, generator=g)).cuda()
    state = (x, torch.zeros_like(x), torch.zeros(n, 3, 3, device="cuda"), torch.eye(3, device="cuda").repeat(n, 1, 1))
    runner = FrameGraphs(solver, material, 4, n)
    runner.bind(torch.full((n,), 1e-6, device="cuda"), torch.full((n,), 1e-3, device="cuda"))
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)
        out = runner.forward(*state)
    assert runner.capture and runner._fwd_graph is not None
    eager = FrameGraphs(solver, material, 4, n, capture=False)
    eager.bind(runner.vol, runner.mass)
    for a, b in zip(out, eager.forward(*state)):
        torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-6)
