"""gca.eval.demos: placing and combining bodies, the composite law per range, demo outputs and metrics.

Tiny bodies are built from the procedural objects (gca.assets) into a temporary folder; analytic
materials stand in for learned laws (the demo functions take any Material).
"""

import dataclasses

import imageio.v3 as iio
import numpy as np
import pytest
import torch
import warp as wp

from gca.assets.objects import gaussians_from_mesh, make_object
from gca.assets.particles import ParticleConfig, convert, save_particles
from gca.assets.ply import write_ply
from gca.eval.demos import (CaptureDemoConfig, DemoConfig, InteractionConfig, NewShapeConfig, arrange_pair,
                            concat_bodies, density, max_strain, motion_metrics, place_body, shown_frames, body_bounds,
                            run_capture_demo, run_interaction, run_new_shape, simulate, transform_body)
from gca.render.camera import look_at
from gca.laws.base import Elasticity, Material
from gca.laws.plastic import IdentityPlasticity
from gca.laws.presets import material_from_preset
from gca.scenes.world import gaussians_at, initial_velocity, load_body
from gca.sim.solver import MPMSolver, SimConfig

wp.config.quiet = True
SOFT = {"elasticity": "corotated", "E": 1.0e4, "nu": 0.3, "rho": 1000}
STIFF = {"elasticity": "corotated", "E": 1.0e6, "nu": 0.3, "rho": 1000}


def _write_object(folder, name, spacing=0.05):
    """Tiny particles npz + gaussians ply of a procedural object; returns the loaded body."""
    mesh, colour = make_object(name, seed=1, size=0.3)
    cloud = gaussians_from_mesh(mesh, colour, n_surface=250, n_interior=30, seed=1)
    write_ply(folder / f"{name}.ply", cloud)
    save_particles(folder / f"{name}.npz", convert(cloud, ParticleConfig(spacing=spacing, floor_gap=0.05),
                                                   1000.0, mesh=mesh))
    return load_body(folder / f"{name}.npz", folder / f"{name}.ply")


@pytest.fixture(scope="module")
def bodies(tmp_path_factory):
    folder = tmp_path_factory.mktemp("demo_bodies")
    return {name: _write_object(folder, name) for name in ("ball", "pawn")}


@pytest.fixture(scope="module")
def solver():
    return MPMSolver(SimConfig(n_grid=16, dt=5e-4, bound=2, boundary="friction", friction=0.4, max_refine=1))


def _cfg(**kw):
    base = dict(n_frames=8, steps_per_frame=4, resolution=32, strip_frames=4, sweep_deg=30.0)
    return DemoConfig(**{**base, **kw})


def test_transform_body_scales_volume_and_covariance_and_keeps_density(bodies):
    body = bodies["ball"]
    moved = transform_body(body, 0.5, [0.1, 0.0, -0.2])
    torch.testing.assert_close(moved.x0, 0.5 * body.x0 + torch.tensor([0.1, 0.0, -0.2]))
    torch.testing.assert_close(moved.vol.sum(), body.vol.sum() / 8)
    torch.testing.assert_close(moved.covs0, body.covs0 / 4)
    assert density(moved) == pytest.approx(density(body), rel=1e-5)
    with pytest.raises(ValueError, match="scale must be > 0"):
        transform_body(body, 0.0, [0, 0, 0])


@pytest.mark.parametrize("layout,axis", [("side_by_side", 0), ("stacked", 1)])
def test_arrange_pair_fits_the_cube_without_overlap(bodies, layout, axis):
    a, b, s = arrange_pair(bodies["ball"], bodies["pawn"], layout, gap=0.05, margin=0.1, floor_gap=0.08)
    (lo_a, hi_a), (lo_b, hi_b) = body_bounds(a), body_bounds(b)
    assert 0 < s <= 1
    assert lo_b[axis] - hi_a[axis] == pytest.approx(0.05, abs=1e-5), "gap along the layout axis"
    for lo, hi in ((lo_a, hi_a), (lo_b, hi_b)):
        assert lo.min() >= 0.08 - 1e-5 and hi[[0, 2]].max() <= 0.9 + 1e-5 and hi[1] <= 0.9 + 1e-5
    assert min(lo_a[1], lo_b[1]) == pytest.approx(0.08, abs=1e-5), "the pair rests floor_gap above the floor"
    # hand check of the scale: room along the axis minus the gap, and across it (side walls 0.1 m, top 0.1 m)
    ext = [np.subtract(*body_bounds(bodies[n])[::-1]) for n in ("ball", "pawn")]
    room = np.array([0.8, 1 - 0.1 - 0.08, 0.8])
    expected = min([1.0, (room[axis] - 0.05) / (ext[0][axis] + ext[1][axis])]
                   + [room[k] / max(ext[0][k], ext[1][k]) for k in range(3) if k != axis])
    assert s == pytest.approx(expected, rel=1e-6) and s < 1, "two 0.45 m objects must shrink to fit"
    assert a.vol.sum() == pytest.approx(s ** 3 * bodies["ball"].vol.sum().item(), rel=1e-5)


def test_concat_bodies_offsets_the_binding(bodies):
    a, b, _ = arrange_pair(bodies["ball"], bodies["pawn"], "side_by_side", 0.05, 0.1, 0.08)
    both = concat_bodies([a, b])
    assert both.n_particles == a.n_particles + b.n_particles and both.n_gaussians == a.n_gaussians + b.n_gaussians
    g = torch.Generator().manual_seed(0)
    x = both.x0 + 0.01 * torch.randn(both.n_particles, 3, generator=g)
    F = torch.eye(3) + 0.05 * torch.randn(both.n_particles, 3, 3, generator=g)
    means, covs = gaussians_at(both, x, F)
    Pa = a.n_particles
    means_a, covs_a = gaussians_at(a, x[:Pa], F[:Pa])
    means_b, covs_b = gaussians_at(b, x[Pa:], F[Pa:])
    torch.testing.assert_close(means, torch.cat([means_a, means_b]))
    torch.testing.assert_close(covs, torch.cat([covs_a, covs_b]))


def test_max_strain_and_motion_metrics_hand_values():
    F = torch.diag(torch.tensor([1.2, 0.9, 1.0])).expand(2, 4, 3, 3)  # stretch 20 %, compress 10 %
    assert max_strain(F) == pytest.approx(0.2, abs=1e-6)
    x = torch.zeros(3, 2, 3)
    x[:, :, 1] = torch.tensor([[0.5, 0.3], [0.2, 0.2], [0.3, 0.3]])  # COM heights (mass 1:3): .35, .2, .3
    m = motion_metrics(x, torch.eye(3).expand(3, 2, 3, 3), torch.tensor([1.0, 3.0]))
    assert m["frames"] == 2 and m["finite"] and m["max_strain"] == pytest.approx(0.0, abs=1e-6)
    assert m["com_drop_m"] == pytest.approx(0.35 - 0.2, abs=1e-6)
    assert shown_frames(12, 5) == [0, 5, 10, 12] and shown_frames(4, 1) == [0, 1, 2, 3, 4]


def test_composite_assigns_each_law_to_its_range(bodies, solver):
    # Far apart, the two objects never share grid nodes: the coupled simulation must equal two
    # separate ones (reference), and swapping the laws (negative control) must not. Both are thrown
    # at the floor so the soft and the stiff law respond visibly differently.
    from gca.laws.base import CompositeMaterial
    a, b, _ = arrange_pair(bodies["ball"], bodies["pawn"], "side_by_side", gap=0.3, margin=0.1, floor_gap=0.08)
    both = concat_bodies([a, b])
    soft, stiff = material_from_preset(SOFT), material_from_preset(STIFF)
    down = lambda body: initial_velocity(body.x0, torch.tensor([0.0, -1.5, 0.0]))  # noqa: E731
    counts = [a.n_particles, b.n_particles]
    coupled, _ = simulate(solver, CompositeMaterial([soft, stiff], counts), both, down(both), 6, 4)
    alone_a, _ = simulate(solver, soft, a, down(a), 6, 4)
    alone_b, _ = simulate(solver, stiff, b, down(b), 6, 4)
    torch.testing.assert_close(coupled.x, torch.cat([alone_a.x, alone_b.x], 1), atol=1e-6, rtol=0)
    torch.testing.assert_close(coupled.F, torch.cat([alone_a.F, alone_b.F], 1), atol=1e-5, rtol=0)
    swapped, _ = simulate(solver, CompositeMaterial([stiff, soft], counts), both, down(both), 6, 4)
    assert (swapped.F[-1, :a.n_particles] - alone_a.F[-1]).abs().max() > 1e-2, "negative control"
    assert (swapped.x[-1, :a.n_particles] - alone_a.x[-1]).abs().max() > 1e-3, "negative control"


def test_interaction_demo_collides_soft_and_stiff_and_writes_outputs(bodies, solver, tmp_path):
    cfg = _cfg(interaction=InteractionConfig(v0_a=(2.0, -0.5, 0.0), v0_b=(-2.0, -0.5, 0.0), gap=0.04))
    soft, stiff = material_from_preset(SOFT), material_from_preset(STIFF)
    m = run_interaction(solver, [soft, stiff], [bodies["ball"], bodies["pawn"]], cfg, tmp_path)
    assert m["status"] == "ok" and m["a"]["finite"] and m["b"]["finite"]
    assert m["n_particles"] == bodies["ball"].n_particles + bodies["pawn"].n_particles
    assert (m["n_particles_a"], m["n_particles_b"]) == (bodies["ball"].n_particles, bodies["pawn"].n_particles)
    assert m["com_distance_min_m"] < m["com_distance_start_m"] - 0.03, "launched towards each other"
    assert m["a"]["max_strain"] > 3 * m["b"]["max_strain"], "the soft object deforms far more than the stiff one"
    assert m["a"]["frames"] == m["b"]["frames"] == cfg.n_frames
    gif = iio.imread(m["gif"], index=None)
    assert gif.shape[:3] == (cfg.n_frames + 1, 32, 32)
    strip = iio.imread(m["strip_png"])
    assert strip.shape[:2] == (32, 32 * cfg.strip_frames)
    assert (strip[..., :3] < 250).any(), "something is drawn on the white background"


def test_new_shape_demo_falls_and_reports(bodies, solver, tmp_path):
    cfg = _cfg(new_shape=NewShapeConfig(object="pawn", v0=(0.0, -1.5, 0.0)))
    m = run_new_shape(solver, material_from_preset(SOFT), bodies["pawn"], cfg, tmp_path / "ns")
    assert m["status"] == "ok" and m["finite"] and m["frames"] == cfg.n_frames
    t = cfg.n_frames * cfg.steps_per_frame * solver.cfg.dt
    free_fall = 1.5 * t + 0.5 * 9.8 * t ** 2  # no faster than a free fall from the launch speed
    assert 0.3 * free_fall < m["com_drop_m"] <= free_fall + 1e-4, "launched downwards; the floor slows it"
    assert 0 < m["max_strain"] < 1
    assert (tmp_path / "ns" / "demo.gif").is_file() and (tmp_path / "ns" / "strip.png").is_file()
    assert m["gif_frames"] == cfg.n_frames + 1


class _NaNElasticity(Elasticity):
    def forward(self, F):
        return torch.full_like(F, float("nan"))

    def wave_speed(self, rho):
        return 1.0


def test_diverged_demo_reports_instead_of_writing_garbage(bodies, solver, tmp_path):
    material = Material(_NaNElasticity(), IdentityPlasticity(), 1000.0)
    with pytest.warns(RuntimeWarning, match="diverged"):
        m = run_new_shape(solver, material, bodies["ball"], _cfg(), tmp_path)
    assert m["status"] == "diverged" and m["finite"] is False and "non-finite" in m["message"]
    assert not (tmp_path / "demo.gif").exists()


def test_demo_config_rejects_bad_values():
    from gca.config import ConfigError
    with pytest.raises(ConfigError, match="missing_law"):
        DemoConfig(missing_law="maybe")
    with pytest.raises(ConfigError, match="layout"):
        InteractionConfig(layout="diagonal")
    with pytest.raises(ConfigError, match="v0"):
        NewShapeConfig(v0=(1.0, 2.0))
    assert dataclasses.replace(DemoConfig(), n_frames=3).n_frames == 3


def test_place_body_turns_about_the_centre_and_raises_by_lift(bodies):
    body = bodies["pawn"]
    placed = place_body(body, (0.0, 0.0, 90.0), 0.1)
    low = lambda b: float(torch.cat([b.x0, b.means0])[:, 1].min())  # noqa: E731
    assert abs(low(placed) - low(body) - 0.1) < 1e-5  # turned, set back on its old lowest height, then raised
    d0, d1 = (torch.cdist(b.x0.double(), b.x0.double(), compute_mode="donot_use_mm_for_euclid_dist") for b in (body, placed))
    assert torch.allclose(d0, d1, atol=1e-4)  # rigid
    ext0, ext1 = np.ptp(body.x0.numpy(), 0), np.ptp(placed.x0.numpy(), 0)
    assert abs(ext1[0] - ext0[1]) < 1e-5 and abs(ext1[1] - ext0[0]) < 1e-5  # 90 deg about z swaps x and y extents
    assert torch.allclose(torch.linalg.eigvalsh(placed.covs0), torch.linalg.eigvalsh(body.covs0), atol=1e-9)
    assert torch.equal(placed.mass, body.mass) and torch.equal(placed.vol, body.vol)
    assert not torch.allclose(placed.covs0, body.covs0)


def test_capture_demo_renders_from_the_given_camera_over_the_plate(bodies, solver, tmp_path):
    body = bodies["ball"]
    centre = body.x0.mean(0).numpy()
    camera = look_at(eye=centre + np.array([0.0, 0.2, 1.2]), target=centre, up=np.array([0.0, 1.0, 0.0]),
                     fov_deg=60.0, width=40, height=30)
    plate = np.full((30, 40, 3), 0.25, np.float32)
    cd = CaptureDemoConfig(object="ball", lift=0.1, rotation_deg=(0.0, 0.0, 30.0), v0=(0.3, 1.0, 0.0))
    m = run_capture_demo(solver, material_from_preset(SOFT), body, cd, camera, plate, 6, 4, _cfg(), tmp_path / "cd",
                         frame_ms=80.0)
    assert m["status"] == "ok" and m["finite"] and m["frames"] == 6 and m["lift_m"] == 0.1
    assert m["com_start"][1] > float(body.x0[:, 1].mean()) + 0.09  # raised
    frames = iio.imread(tmp_path / "cd" / "demo.gif", index=None)
    assert frames.shape[1:3] == (30, 40)
    corner = frames[0][0, 0, :3].astype(int)
    assert np.all(np.abs(corner - 64) <= 1)  # the plate shows where the object is not
    with pytest.raises(Exception, match="lift"):
        CaptureDemoConfig(lift=-0.1)
