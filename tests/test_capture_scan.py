"""gca.assets.scan: a user's scan as it comes (floaters, a Gaussian at 1e30 m, crop, up axis, size,
SH rotation, non-watertight meshes, the Mahalanobis binding share); gca.assets.particles' outlier check."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch
import trimesh

from gca.assets import particles as pa, scan
from gca.assets.testscan import torus_scan, torus_volume
from gca import sh

R, r = 0.05, 0.02  # torus radii [m]
CFG = pa.ParticleConfig(spacing=0.012, target_count=4000)


@pytest.fixture(scope="module")
def dirty():
    """A 6000-Gaussian torus with 22 floaters scattered over a box 12x its size and one Gaussian at 1e30 m."""
    return torus_scan(n=6000, R=R, r=r, n_floaters=22, floater_box=12, far_outlier=1e30)


def test_outliers_make_conversion_fail_with_the_real_cause(dirty):
    with pytest.raises(ValueError, match=r"lie far outside the bulk.*floaters or outliers.*far_factor"):
        pa.convert(dirty, CFG, density=1000.0)
    floaters_only = torus_scan(n=6000, R=R, r=r, n_floaters=5, floater_box=12)
    with pytest.raises(ValueError, match=r"5 of 6005 Gaussians lie far outside"):
        pa.convert(floaters_only, CFG, density=1000.0)


def test_cleaning_removes_exactly_the_defects_and_conversion_then_works(dirty):
    clean, T, report = scan.prepare_scan(dirty, scan.ScanConfig())
    assert report["removed"]["far"] == 1 and report["removed"]["statistical"] == 22
    assert report["removed_total"] == 23 and clean.n == 6000
    np.testing.assert_array_equal(clean.means, dirty.means[:6000])  # the torus itself untouched
    np.testing.assert_allclose(T, np.eye(4))
    p = pa.convert(clean, CFG, density=1000.0)
    volume_m3 = p.vol.sum() / p.sim_from_world[0, 0] ** 3
    assert abs(volume_m3 / torus_volume(R, r) - 1) < 0.1


def test_component_test_removes_a_floater_cluster():
    """Ten floaters packed together pass the neighbour-distance test; the component test drops them."""
    base = torus_scan(n=6000, R=R, r=r)
    blob = dataclasses.replace(base.subset(np.arange(10)), means=(base.means[:10] - base.means[:10].mean(0)) * 0.05
                               + np.float32([0.3, 0.3, 0.3]))
    cloud = type(base)(**{f.name: np.concatenate([getattr(base, f.name), getattr(blob, f.name)])
                          for f in dataclasses.fields(base)})
    masks = scan.outlier_masks(cloud.means, scan.ScanConfig(outlier_factor=1e9))
    assert masks["component"].sum() == 10 and masks["component"][6000:].all()
    off = scan.outlier_masks(cloud.means, scan.ScanConfig(outlier_factor=1e9, min_component=0))
    assert "component" not in off


def test_crop_box_and_all_removed_error(dirty):
    _, _, report = scan.prepare_scan(dirty, scan.ScanConfig(crop=[[-1, -1, -1], [1, 1, 1]]))
    assert report["removed"]["crop"] >= 1  # the 1e30 one at least
    assert report["removed"]["far"] == 0
    with pytest.raises(scan.ScanError, match=r"scan.ply: 0 of 6023 Gaussians left.*'crop'"):
        scan.prepare_scan(dirty, scan.ScanConfig(crop=[[5, 5, 5], [6, 6, 6]]), name="scan.ply")
    with pytest.raises(scan.ScanError, match="crop"):
        scan.ScanConfig(crop=[[1, 1, 1], [0, 0, 0]])


def test_up_axis_lays_a_z_up_scan_flat_and_real_size_scales_it():
    z_up = torus_scan(n=3000, R=R, r=r, up="z")
    wrong, _, _ = scan.prepare_scan(z_up, scan.ScanConfig(up="+y"))
    right, T, report = scan.prepare_scan(z_up, scan.ScanConfig(up="+z", real_size=0.28))
    ext_wrong = np.ptp(wrong.means, axis=0)
    ext = np.ptp(right.means, axis=0)
    assert ext_wrong[1] > 0.1  # standing on its rim
    assert ext[1] < 0.3 * ext.max()  # lying flat: y is the thin axis
    assert abs(ext.max() - 0.28) < 1e-4 and abs(report["metres_per_unit"] - 2.0) < 0.01  # 0.14 m -> 0.28 m
    np.testing.assert_allclose(right.log_scales, z_up.log_scales + np.log(report["metres_per_unit"]), atol=1e-5)
    np.testing.assert_allclose(pa.apply_affine(T, z_up.means), right.means, atol=1e-5)
    assert np.linalg.det(T[:3, :3]) > 0


@pytest.mark.parametrize("degree", [1, 2, 3])
def test_rotating_a_scan_rotates_its_view_dependent_colour(degree):
    """rgb'(Q d) = rgb(d): the rotated scan seen along the rotated direction looks the same."""
    rng = np.random.default_rng(degree)
    K = (degree + 1) ** 2 - 1
    rest = rng.standard_normal((5, K, 3)).astype(np.float32)
    Q = scan.rotation_from_euler_deg([30.0, -70.0, 120.0])
    rotated = sh.rotate_sh(rest, Q)
    d = rng.standard_normal((5, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    before = sh.view_term(torch.tensor(rest, dtype=torch.float64), torch.tensor(d), torch.zeros(3))
    after = sh.view_term(torch.tensor(rotated, dtype=torch.float64), torch.tensor(d @ Q.T), torch.zeros(3))
    np.testing.assert_allclose(after.numpy(), before.numpy(), atol=1e-4)
    assert not np.allclose(rotated, rest, atol=1e-2)


def test_sh_basis_band1_is_the_3dgs_one():
    d = torch.tensor([[0.0, 0.0, 1.0]], dtype=torch.float64)
    np.testing.assert_allclose(sh.basis(d, 1).numpy(), [[0.0, sh.SH_C1, 0.0]])
    assert sh.basis(d, 3).shape == (1, 15)


def test_check_mesh_repairs_a_small_hole_and_ignores_an_open_mesh():
    sphere = trimesh.creation.icosphere(subdivisions=3, radius=0.1)
    used, rep = scan.check_mesh(sphere)
    assert used is sphere and rep["watertight"] and rep["used"]
    holed = trimesh.Trimesh(sphere.vertices, sphere.faces[1:], process=False)
    fixed, rep = scan.check_mesh(holed)
    assert not rep["watertight"] and rep["repaired"] and rep["used"] and fixed.is_watertight
    half = trimesh.Trimesh(sphere.vertices, sphere.faces[sphere.triangles_center[:, 1] > 0], process=False)
    none, rep = scan.check_mesh(half, "mesh.ply")
    assert none is None and not rep["used"] and "ignored" in rep["reason"]


def test_binding_share_counts_the_fallbacks():
    clean = torus_scan(n=4000, R=R, r=r)
    p = pa.convert(clean, CFG, density=1000.0)
    share = scan.binding_share(p, clean, CFG.mahalanobis_chi2)
    kept = clean.subset(p.gaussian_index)
    means = pa.apply_affine(p.sim_from_world, kept.means)
    Rm = pa.quats_to_rotmats(pa.normalized_quats(kept))
    *_, unbound = pa.bind_gaussians(means, Rm, pa.scales(kept) * p.sim_from_world[0, 0], p.x.astype(np.float64), CFG)
    assert share["n_fallback_nearest"] == int(unbound.sum()) > 0
    assert share["share_bound_within_mahalanobis"] == pytest.approx(1 - unbound.mean())
