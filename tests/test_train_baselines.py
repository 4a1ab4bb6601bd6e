"""Issue 22 item 3: the baselines as their authors run them, labelled honestly.

The L1 depth terms of the PAC-NeRF + depth rows (raw and aligned), ...
"""

import pytest
import torch

from gca.train.objective import depth_l1_aligned, depth_l1_raw


def _frame(seed=0, dtype=torch.float64, h=12, w=10):
    g = torch.Generator().manual_seed(seed)
    depth = 1.0 + 0.3 * torch.rand(h, w, generator=g, dtype=dtype)  # rendered metric depth [m]
    est = 2.0 - 0.5 * depth + 0.02 * torch.randn(h, w, generator=g, dtype=dtype)  # affine-ish estimate, noisy
    mask = torch.zeros(h, w, dtype=torch.bool)
    mask[2:10, 1:8] = True
    return depth, est, mask


@pytest.mark.parametrize("a, b", [(3.0, 0.7), (0.01, -5.0), (-2.0, 1.0)])
def test_aligned_depth_is_invariant_to_an_affine_change_of_the_estimate(a, b):
    depth, est, mask = _frame()
    ref = depth_l1_aligned(depth, est, mask)
    moved = depth_l1_aligned(depth, a * est + b, mask)
    torch.testing.assert_close(moved, ref, rtol=1e-9, atol=1e-12)
    assert float(ref) > 0  # the estimate is not exactly affine in the render: a real residual remains
    # negative control: the raw L1 is not invariant
    assert abs(float(depth_l1_raw(depth, a * est + b, mask)) - float(depth_l1_raw(depth, est, mask))) > 1e-2


def test_aligned_depth_is_zero_for_an_exactly_affine_estimate_and_sees_shape():
    depth, _, mask = _frame()
    assert float(depth_l1_aligned(depth, 4.0 * depth - 3.0, mask)) < 1e-12
    assert float(depth_l1_raw(depth, 4.0 * depth - 3.0, mask)) > 0.1  # raw: the units differ
    # a different shape (not affine in the render) is penalised
    assert float(depth_l1_aligned(depth, depth.square().flip(0), mask)) > 1e-3


def test_aligned_depth_ignores_pixels_outside_the_mask():
    depth, est, mask = _frame()
    other = est.clone()
    other[~mask] = 1e6
    torch.testing.assert_close(depth_l1_aligned(depth, other, mask), depth_l1_aligned(depth, est, mask))


@pytest.mark.parametrize("fn", [depth_l1_aligned, depth_l1_raw])
def test_a_zero_mask_frame_contributes_zero_with_a_finite_gradient(fn):
    depth, est, _ = _frame()
    depth.requires_grad_(True)
    value = fn(depth, est, torch.zeros_like(depth, dtype=torch.bool))
    assert float(value.detach()) == 0.0
    value.backward()
    assert torch.equal(depth.grad, torch.zeros_like(depth))


def _selected(fn_name, depth, est, mask):
    """The terms as written for one frame with boolean selection (session 39's code): the reference of the masked,
    batched forms."""
    if not bool(mask.any()):
        return depth.sum() * 0.0
    d, e = depth[mask], est[mask]
    if fn_name == "depth_l1_raw":
        return (d - e).abs().mean()
    e_c, d_c = e - e.mean(), d - d.mean()
    s = (e_c * d_c).mean() / (e_c * e_c).mean().clamp(min=1e-12)
    return (s * e_c - d_c).abs().mean()


@pytest.mark.parametrize("fn", [depth_l1_aligned, depth_l1_raw])
def test_frames_at_once_equal_the_selected_formula_per_frame(fn):
    """[T, H, W] depth terms (a training chunk's frames in one call, session 40; masked sums, no boolean selection,
    no host read) equal the boolean-selection formula frame by frame, values and gradients, with a frame whose mask is
    empty (0, no gradient) and a render that is non-finite outside the mask (not read: the gradient stays finite)."""
    frames = [_frame(seed=t) for t in range(3)]
    depth = torch.stack([f[0] for f in frames])
    depth[0, 0, 0] = float("inf")  # outside frame 0's mask
    depth.requires_grad_(True)
    est = torch.stack([f[1] for f in frames])
    mask = torch.stack([f[2] for f in frames])
    mask[1] = False  # an empty frame
    values = fn(depth, est, mask)
    assert values.shape == (3,) and float(values[1].detach()) == 0.0
    weights = torch.tensor([1.0, 2.0, -0.5], dtype=depth.dtype)
    (grad,) = torch.autograd.grad(values @ weights, depth)
    assert bool(torch.isfinite(grad).all())
    for t in range(3):
        d = depth[t].detach().clone().requires_grad_(True)
        ref = _selected(fn.__name__, d, est[t], mask[t])
        torch.testing.assert_close(values[t].detach(), ref.detach(), rtol=1e-12, atol=1e-15)
        if ref.requires_grad:
            (r,) = torch.autograd.grad(ref, d)
            torch.testing.assert_close(grad[t], weights[t] * r, rtol=1e-10, atol=1e-14)


def test_aligned_depth_gradient_is_finite_even_for_a_constant_estimate():
    depth, _, mask = _frame()
    depth.requires_grad_(True)
    value = depth_l1_aligned(depth, torch.full_like(depth, 0.5), mask)  # var(est) = 0: s = 0, t = mean depth
    value.backward()
    assert torch.isfinite(value) and torch.isfinite(depth.grad).all()
    assert float(depth.grad[~mask].abs().sum()) == 0.0 and float(depth.grad[mask].abs().sum()) > 0


@pytest.mark.grad
def test_aligned_depth_gradcheck_float64():
    """The alignment (s, t) is differentiated through (not detached): the whole function passes gradcheck, in
    the render and in the estimate."""
    depth, est, mask = _frame(seed=3)
    depth.requires_grad_(True)
    est.requires_grad_(True)
    assert torch.autograd.gradcheck(lambda d, e: depth_l1_aligned(d, e, mask), (depth, est), eps=1e-6, atol=1e-7)


def test_aligned_gradient_differs_from_a_detached_alignment():
    """Negative control for the not-detached choice: treating (s, t) as constants gives another gradient."""
    depth, est, mask = _frame(seed=4)
    d1 = depth.clone().requires_grad_(True)
    depth_l1_aligned(d1, est, mask).backward()
    d2 = depth.clone().requires_grad_(True)
    dm, em = d2[mask], est[mask]
    with torch.no_grad():
        s = ((em - em.mean()) * (dm - dm.mean())).mean() / (em - em.mean()).square().mean()
        t = dm.mean() - s * em.mean()
    (s * em + t - dm).abs().mean().backward()
    assert not torch.allclose(d1.grad, d2.grad)


# ------------------------------------------------------------------ the depth rows inside the objective

import dataclasses  # noqa: E402
import sys  # noqa: E402
from pathlib import Path  # noqa: E402

sys.path.insert(0, str(Path(__file__).parent))
from synthetic import JELLY, ground_truth_views, observations, tiny_body, tiny_solver  # noqa: E402

from gca.align.cpr import CPRConfig  # noqa: E402
from gca.align.rdga import RDGAConfig  # noqa: E402
from gca.laws.lora import LoRAConfig  # noqa: E402
from gca.train.config import TrainConfig  # noqa: E402
from gca.train.law import build_law  # noqa: E402
from gca.train.loop import simulate  # noqa: E402
from gca.train.methods import get_method  # noqa: E402
from gca.train.objective import Objective, TrainData  # noqa: E402
from gca.vision import MatchConfig  # noqa: E402


@pytest.fixture(scope="module")
def scene():
    torch.manual_seed(0)
    body = tiny_body(n_side=4, base_y=0.08)
    view, frames, _ = ground_truth_views(body, (0.5, -2.0, 0.0), n_frames=6, frame_every=2)
    est, keypoints = observations(view)
    data = TrainData(body=body, views={"train0": view}, video_frames=frames, substeps=2, est_depth=est,
                     keypoints=keypoints, v_init=torch.tensor([0.5, -2.0, 0.0]).expand_as(body.x0),
                     background=(1.0, 1.0, 1.0))
    return data


def _depth_stat(data, name):
    method = get_method(name)
    cfg = TrainConfig(iterations=1, curriculum_start=1.0)
    law = build_law(method, "", "jelly", 1000.0, LoRAConfig(rank=4, alpha=4.0), 1e-2, 1e-3, 1e-2,
                    family_presets={"jelly": JELLY}, category="elastic")
    objective = Objective(method, data, cfg, RDGAConfig(r=5, k=5), CPRConfig(subset_size=16, n_groups=2), MatchConfig())
    n_video = len(data.video_frames)
    with torch.no_grad():
        _, stats = objective.data_loss(simulate(tiny_solver(), law, data, n_video), n_video)
    return stats[method.terms[-1]]


def test_objective_aligned_depth_row_ignores_the_estimates_scale_and_shift_raw_row_does_not(scene):
    moved = dataclasses.replace(scene, est_depth=3.0 * scene.est_depth + 0.5)
    aligned = _depth_stat(scene, "pacnerf_depth_aligned")
    assert aligned > 0 and aligned == pytest.approx(_depth_stat(moved, "pacnerf_depth_aligned"), rel=1e-4)
    raw = _depth_stat(scene, "pacnerf_depth")
    assert raw != pytest.approx(_depth_stat(moved, "pacnerf_depth"), rel=1e-2)  # negative control


# ------------------------------------------------------------ PAC-NeRF-style rows: the scene's law category

import yaml  # noqa: E402

from gca.config import ConfigError  # noqa: E402
from gca.laws.ood import NeoHookeanElasticity, ViscoplasticPlasticity  # noqa: E402
from gca.laws.plastic import DruckerPragerPlasticity, IdentityPlasticity, VonMisesPlasticity  # noqa: E402
from gca.laws.presets import material_category  # noqa: E402
from gca.train.law import NU_RANGE, LaunchVelocity, _Interval, category_law  # noqa: E402
from gca.train.loop import train  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]


def test_every_homogeneous_scene_material_has_its_category():
    params = yaml.safe_load((ROOT / "params.yaml").read_text())
    cats = {name: material_category(m) for name, m in params["materials"].items() if m and "parts" not in m}  # {}: captures
    assert cats == {"elastomer": "elastic", "gel": "elastic", "rubber": "plastic", "plasticine": "plastic",
                    "granular": "granular", "non_newtonian": "viscoplastic", "plasticine_dragon": "plastic",
                    "sand_wolf": "granular", "gel_pudding": "elastic",
                    "foam": "elastic", "clay": "plastic", "snow": "granular"}  # the calibration scenes' (benchmark v2)
    with pytest.raises(ConfigError, match="composite"):
        material_category(params["materials"]["composite"])
    with pytest.raises(ConfigError, match="no material category"):
        material_category({"elasticity": "volume", "plasticity": "sigma"})  # a fluid: no PAC-NeRF row here


@pytest.mark.parametrize("category, plastic_type, constants", [
    ("elastic", IdentityPlasticity, set()),
    ("plastic", VonMisesPlasticity, {"plasticity.log_yield_stress"}),
    ("granular", DruckerPragerPlasticity, {"plasticity.parametrizations.friction_angle.original"}),
    ("viscoplastic", ViscoplasticPlasticity, {"plasticity.parametrizations.yield_stress.original",
                                              "plasticity.parametrizations.viscosity.original"}),
])
def test_category_law_form_and_what_it_learns(category, plastic_type, constants):
    m = category_law(category, {"E": 1e5, "nu": 0.2}, 1000.0, dt=1e-3)
    assert isinstance(m.plasticity, plastic_type)
    assert isinstance(m.elasticity, NeoHookeanElasticity) == (category == "elastic")
    learned = {n for n, p in m.named_parameters() if p.requires_grad}
    assert learned == {"elasticity.log_E", "elasticity.parametrizations.nu.original"} | constants
    assert float(m.elasticity.E.detach()) == pytest.approx(1e5, rel=1e-5)
    assert float(m.elasticity.nu.detach()) == pytest.approx(0.2)


def test_category_law_shares_one_E_and_one_nu_and_bounds_nu():
    m = category_law("granular", {"E": 1e5, "nu": 0.2}, 1000.0, dt=1e-3)
    e, p = m.elasticity, m.plasticity
    with torch.no_grad():
        e.log_E += 1.0
        e.parametrizations.nu.original += 50.0  # a huge step: nu stays below its bound
    assert float(p.E.detach()) == pytest.approx(float(e.E.detach()))
    assert float(p.nu.detach()) == pytest.approx(float(e.nu.detach()))
    assert NU_RANGE[0] < float(e.nu.detach()) <= NU_RANGE[1] + 1e-6 and torch.isfinite(p.lam)  # lam finite: nu < 0.5
    # negative control: two independently built laws do not share
    other = category_law("granular", {"E": 1e5, "nu": 0.2}, 1000.0, dt=1e-3)
    assert float(other.plasticity.E.detach()) != pytest.approx(float(e.E.detach()))


@pytest.mark.grad
def test_category_law_and_launch_gradcheck_float64():
    from torch.func import functional_call

    old = torch.get_default_dtype()
    torch.set_default_dtype(torch.float64)
    try:
        m = category_law("plastic", {"E": 1e5, "nu": 0.3}, 1000.0, dt=1e-3)
        launch = LaunchVelocity([0.5, -2.0, 0.0], [0.0, 0.0, 1.0])
    finally:
        torch.set_default_dtype(old)
    g = torch.Generator().manual_seed(0)
    F = torch.eye(3, dtype=torch.float64) + 0.05 * torch.randn(4, 3, 3, generator=g, dtype=torch.float64)

    def stress(log_E, raw_nu):
        return functional_call(m.elasticity, {"log_E": log_E, "parametrizations.nu.original": raw_nu}, (F,)) / 1e4

    raw = m.elasticity.parametrizations.nu.original.detach().clone().requires_grad_(True)
    log_E = m.elasticity.log_E.detach().clone().requires_grad_(True)
    assert torch.autograd.gradcheck(stress, (log_E, raw), eps=1e-6, atol=1e-6)
    interval = _Interval(*NU_RANGE)
    assert torch.autograd.gradcheck(interval, (torch.tensor([-3.0, 0.1, 2.0], dtype=torch.float64,
                                                            requires_grad=True),))
    x0 = torch.rand(6, 3, generator=g, dtype=torch.float64)
    v0 = launch.v0.detach().clone().requires_grad_(True)
    w0 = launch.w0.detach().clone().requires_grad_(True)
    assert torch.autograd.gradcheck(lambda a, b: functional_call(launch, {"v0": a, "w0": b}, (x0,)), (v0, w0))


def test_explicit_row_learns_its_launch_and_moduli_in_one_iteration(scene):
    method = get_method("pacnerf_depth_aligned")
    cfg = TrainConfig(iterations=1, curriculum_start=1.0, keep="last")
    law = build_law(method, "", "plasticine", 1000.0, LoRAConfig(rank=4, alpha=4.0), 1e-2, 1e-3, 1e-2,
                    family_presets={"plasticine": {"elasticity": "sigma", "plasticity": "von_mises", "E": 4e4,
                                                   "nu": 0.25, "yield_stress": 5e3}},
                    category="plastic", velocity=([0.5, -2.0, 0.0], [0.0, 0.0, 0.0]))
    assert [g["name"] for g in law.groups] == ["explicit", "launch"]
    before = {k: v.clone() for k, v in law.state().items()}
    objective = Objective(method, scene, cfg, RDGAConfig(r=5, k=5), CPRConfig(subset_size=16, n_groups=2), MatchConfig())
    result = train(tiny_solver(), law, scene, objective, cfg)
    assert result.status == "ok", result.message
    after = law.state()
    for key in ("elasticity.log_E", "elasticity.parametrizations.nu.original", "launch.v0"):
        assert not torch.equal(before[key], after[key]), f"{key} did not move"
    assert torch.equal(after["elasticity.log_E"], after["plasticity.log_E"])  # still one E
    v0, w0 = law.launch_velocity(([9.0] * 3, [9.0] * 3))
    assert v0 == pytest.approx(after["launch.v0"].tolist()) and v0 != [9.0] * 3  # evaluation uses the learned launch
    # the state round-trips into a fresh skeleton (launch zeros), and a state without the launch is refused
    skeleton = build_law(method, "", "plasticine", 1000.0, LoRAConfig(rank=4, alpha=4.0), 1e-2, 1e-3, 1e-2,
                         family_presets={"plasticine": {"elasticity": "sigma", "plasticity": "von_mises", "E": 4e4,
                                                        "nu": 0.25, "yield_stress": 5e3}}, category="plastic")
    skeleton.load_state(after)
    assert skeleton.launch_velocity(([9.0] * 3, [9.0] * 3))[0] == pytest.approx(v0)
    assert float(skeleton.material.plasticity.nu.detach()) == pytest.approx(float(law.material.elasticity.nu.detach()))
    with pytest.raises(Exception):
        skeleton.load_state({k: v for k, v in after.items() if not k.startswith("launch.")})
    # negative control: a neural row keeps the shared estimate
    neuma = build_law(get_method("neuma"), _prior(), "jelly", 1000.0, LoRAConfig(rank=4, alpha=4.0), 1e-2, 1e-3, 1e-2)
    assert neuma.launch is None and neuma.launch_velocity(([9.0] * 3, [1.0] * 3)) == ([9.0] * 3, [1.0] * 3)


def _prior():
    import tempfile

    from gca.laws.checkpoint import save_prior
    from gca.laws.neural import NeuralElasticity, NeuralPlasticity

    path = Path(tempfile.mkdtemp()) / "jelly.pt"
    save_prior(path, NeuralElasticity(), NeuralPlasticity(), family="jelly")
    return path


# --------------------------------------------------------------------------- NeuMA's published recipe

from gca.train.config import NEUMA_LR, frame_weights, neuma_recipe  # noqa: E402
from gca.train.state import make_optimizer  # noqa: E402


def test_neuma_recipe_by_prior_family_and_gca_untouched():
    base = TrainConfig(iterations=30, neuma_lr_scale=1.0)  # as published (the tuned scale: test_pipeline_tune)
    for family, (lr_e, lr_p, floor) in NEUMA_LR.items():
        cfg = neuma_recipe(base, family)
        assert (cfg.lr_elasticity, cfg.lr_plasticity, cfg.cosine_floor, cfg.optimizer) == (lr_e, lr_p, floor, "radam")
        assert cfg.iterations == base.iterations and cfg.curriculum_start == 1.0 and cfg.grad_clip == 1.0
    assert neuma_recipe(base, "plasticine").lr_elasticity == 2e-2  # clay cat / rubber pawn
    fluid = neuma_recipe(base, "fluid")  # no NeuMA base model: train's rates kept
    assert (fluid.lr_elasticity, fluid.cosine_floor) == (base.lr_elasticity, base.cosine_floor)
    assert get_method("neuma").recipe == get_method("neuma_multiview").recipe == "neuma"
    assert get_method("gca").recipe == "gca" and frame_weights(base, 0, 10) is None  # negative control


def test_gca_optimiser_comes_from_params_and_neuma_keeps_radam(scene):
    """``train.optimizer`` picks the GCA-recipe methods' optimiser; NeuMA's recipe is RAdam whatever it says."""
    law = build_law(get_method("gca"), _prior(), "jelly", 1000.0, LoRAConfig(rank=4, alpha=4.0), 8e-3, 8e-4, 1e-2)
    assert type(make_optimizer(law, TrainConfig(optimizer="adam"))[0]) is torch.optim.Adam
    assert type(make_optimizer(law, TrainConfig(optimizer="radam"))[0]) is torch.optim.RAdam
    assert neuma_recipe(TrainConfig(optimizer="adam"), "jelly").optimizer == "radam"
    with pytest.raises(ValueError, match="train.optimizer must be 'adam' or 'radam'"):
        TrainConfig(optimizer="sgd")


def test_neuma_frame_weights_decay_then_reach_one():
    cfg = neuma_recipe(TrainConfig(iterations=30), "jelly")
    w0 = frame_weights(cfg, 0, 10)  # groups of 2 frames, decay 0.5
    assert w0 == [1.0, 1.0, 0.5, 0.5, 0.25, 0.25, 0.125, 0.125, 0.0625, 0.0625]
    mid = frame_weights(cfg, 5, 10)
    assert 0.5 < mid[2] < 1.0 and mid == sorted(mid, reverse=True)
    assert frame_weights(cfg, 10, 10) == [1.0] * 10 and frame_weights(cfg, 29, 10) == [1.0] * 10


def test_neuma_recipe_steps_radam_and_weights_the_frames(scene):
    method = get_method("neuma")
    law = build_law(method, _prior(), "jelly", 1000.0, LoRAConfig(rank=4, alpha=4.0), 8e-3, 8e-4, 1e-2)
    cfg = neuma_recipe(TrainConfig(iterations=3, keep="last"), "jelly")
    opt, _ = make_optimizer(law, cfg)
    assert isinstance(opt, torch.optim.RAdam)
    assert type(make_optimizer(law, TrainConfig(optimizer="adam"))[0]) is torch.optim.Adam  # control: a GCA run with Adam
    objective = Objective(method, scene, cfg, RDGAConfig(r=5, k=5), CPRConfig(subset_size=16, n_groups=2), MatchConfig())
    n_video = len(scene.video_frames)
    with torch.no_grad():
        traj = simulate(tiny_solver(), law, scene, n_video)
        flat, _ = objective.data_loss(traj, n_video)
        objective.frame_weights = frame_weights(cfg, 0, n_video)
        weighted, _ = objective.data_loss(traj, n_video)
    assert float(weighted) < float(flat)  # later frames weigh less at the start
    result = train(tiny_solver(), law, scene, objective, cfg)
    assert result.status == "ok", result.message
    assert objective.frame_weights is None  # the final law is judged on the unweighted video
