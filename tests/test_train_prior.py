"""Teacher-forced training of the neural prior: gradients, error control, learning without a warm start."""

import math

import pytest
import torch
import warp as wp

from gca.laws.base import Material
from gca.laws.neural import NeuralLawConfig
from gca.laws.presets import material_from_preset
from gca.sim import MPMSolver, SimConfig, SimulationDiverged
from gca.train.prior import (PriorTrainConfig, heldout_rmse, make_networks, rollout_sq_error, train_teacher_forced,
                             window_loss)
from gca.train.prior_data import PriorDataConfig, make_trajectories, trajectory_seed

wp.config.quiet = True
JELLY = {"elasticity": "corotated", "plasticity": "identity", "E": 1.0e5, "nu": 0.2, "rho": 1000}
SIM = SimConfig(n_grid=16, dt=6e-4, bound=2, boundary="friction", friction=0.4, max_refine=1)
DATA = PriorDataConfig(particles_per_axis=6, n_steps=120, speed=(1.5, 3.0), max_tilt_deg=45.0, floor_gap=(0.0, 0.03))
DataConfigSmall = PriorDataConfig(particles_per_axis=4, n_steps=20, speed=(1.5, 3.0), max_tilt_deg=45.0,
                                  floor_gap=(0.0, 0.03))


@pytest.fixture(scope="module", autouse=True)
def one_thread():
    before = torch.get_num_threads()
    torch.set_num_threads(1)  # tiny tensors: more threads only contend on a busy CI box
    yield
    torch.set_num_threads(before)


@pytest.fixture(scope="module")
def solver():
    return MPMSolver(SIM)


@pytest.fixture(scope="module")
def data(solver):
    reference = material_from_preset(JELLY)
    return {split: make_trajectories(solver, reference, DATA, [trajectory_seed(0, split, i) for i in range(n)])
            for split, n in (("train", 3), ("heldout", 1))}


def neural(seed=0):
    return Material(*make_networks(NeuralLawConfig(), seed), 1000.0)


def test_window_loss_reaches_both_networks(solver, data):
    material = neural()
    traj = data["train"][0]
    loss = window_loss(solver, material, traj, traj.n_steps - 8, 8)
    loss.backward()
    for net in (material.elasticity, material.plasticity):
        grads = torch.cat([p.grad.flatten() for p in net.parameters()])
        assert torch.isfinite(grads).all() and grads.abs().max() > 0


def test_reference_law_has_zero_rollout_error_and_a_wrong_one_does_not(solver, data):
    traj = data["heldout"][0]
    assert rollout_sq_error(solver, material_from_preset(JELLY), traj) == 0.0
    soft = rollout_sq_error(solver, material_from_preset({**JELLY, "E": 5.0e4}), traj)
    assert soft > 0 and math.isfinite(soft)


def test_diverging_law_raises_with_a_diagnostic(solver, data):
    material = neural()
    with torch.no_grad():
        material.elasticity.mlp[0].weight.fill_(float("nan"))
    cfg = PriorTrainConfig(sim=SIM, data=DATA, iterations=1, window=4, batch=1, warm_start=())
    with pytest.raises(SimulationDiverged, match="teacher forcing diverged at iteration 0"):
        train_teacher_forced(material, solver, data["train"], cfg, seed=0)
    assert rollout_sq_error(solver, material, data["heldout"][0]) == math.inf


def test_teacher_forcing_alone_lowers_the_heldout_error(solver, data):
    # No warm start: trajectories alone must teach the random network the jelly's stiffness.
    # Measured at this size: held-out RMSE 0.44 -> 0.11 cells (x4.0); asserted x3.
    material = neural(seed=1)
    before = heldout_rmse(solver, material, data["heldout"])
    cfg = PriorTrainConfig(sim=SIM, data=DATA, window=8, batch=2, iterations=30, lr_elasticity=3e-2,
                           lr_plasticity=1e-3, warm_start=())
    history = train_teacher_forced(material, solver, data["train"], cfg, seed=0)
    after = heldout_rmse(solver, material, data["heldout"])
    assert len(history) == 30 and all(math.isfinite(loss) for _, loss in history)
    assert before / after >= 3.0, (before, after)


def test_config_refusals_name_the_problem():
    with pytest.raises(ValueError, match="prior.py.*warm_start"):
        PriorTrainConfig(warm_start=("stress",))
    with pytest.raises(ValueError, match="window=500 exceeds"):
        PriorTrainConfig(window=500, data=PriorDataConfig(n_steps=100, particles_per_axis=12))


def test_an_interrupted_prior_resumes_to_the_uninterrupted_one(tmp_path):
    # SIGTERM inside gca.stop.deferred at iteration 3 of 6: the checkpoint is saved and the run stops; the next run
    # finds it, skips the warm start and the earlier evaluations, makes the data again and goes on: its networks,
    # losses and metrics (but the seconds) equal the uninterrupted run's, bitwise on the CPU.
    from gca import stop
    from gca.laws.pretrain import PretrainConfig
    from gca.train.prior import pretrain_prior

    fit = PretrainConfig(lr=1e-2, steps=3, n_samples=64, batch_size=32)
    cfg = PriorTrainConfig(sim=SIM, data=DataConfigSmall, n_train=2, n_heldout=1, window=4, batch=1, iterations=6,
                           fit_elasticity=fit, fit_plasticity=fit)
    law = NeuralLawConfig(widths=(8, 8))
    whole = pretrain_prior(JELLY, law, cfg, seed=3)

    ckpt = tmp_path / "prior.pt.checkpoint"

    def sigterm_at_3(phase, i, n, **values):  # what gca.stop's handler does inside stop.deferred
        if phase == "train" and i == 3:
            stop._state["requested"] = True

    try:
        with pytest.raises(stop.Terminated):
            pretrain_prior(JELLY, law, cfg, seed=3, checkpoint=ckpt, callback=sigterm_at_3)
    finally:
        stop.reset()
    assert ckpt.is_file() and torch.load(ckpt, weights_only=False)["loop"]["iteration"] == 3
    phases = []
    resumed = pretrain_prior(JELLY, law, cfg, seed=3, checkpoint=ckpt,
                             callback=lambda phase, i, n, **v: phases.append((phase, i)))
    assert ("resume", 3) in phases and ("train", 4) in phases and ("train", 1) not in phases
    assert resumed.history == whole.history
    for a, b in ((resumed.elasticity, whole.elasticity), (resumed.plasticity, whole.plasticity)):
        for (name, x), (_, y) in zip(a.state_dict().items(), b.state_dict().items()):
            assert torch.equal(x, y), name
    drop = lambda m: {k: v for k, v in m.items() if k != "seconds"}  # noqa: E731
    assert drop(resumed.metrics) == drop(whole.metrics)
    assert resumed.curves == whole.curves
