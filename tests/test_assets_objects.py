"""gca.assets.objects / texture: watertight objects, varied textures, well-formed scans."""

from __future__ import annotations

import numpy as np
import pytest

from gca.assets import objects
from gca.assets.ply import opacities, quats_to_rotmats, normalized_quats, scales, sh0_to_rgb


@pytest.mark.parametrize("name", sorted(objects.SHAPES))
def test_object_watertight_sized_and_textured(name):
    mesh, colour_fn = objects.make_object(name, seed=3, size=0.2)
    assert mesh.is_watertight and mesh.is_volume and mesh.volume > 0
    np.testing.assert_allclose(mesh.extents.max(), 0.2, rtol=1e-9)
    np.testing.assert_allclose(mesh.bounds.mean(axis=0), 0.0, atol=1e-9)
    rgb = colour_fn(mesh.sample(2000, seed=0))
    assert rgb.shape == (2000, 3) and rgb.min() >= 0 and rgb.max() <= 1
    assert rgb.std(axis=0).min() > 0.05, "texture too uniform for feature matching"
    # non-repeating: colours quantised to 1/8 take many distinct values
    assert len(np.unique(np.floor(rgb * 8), axis=0)) > 40


def test_texture_seeded_and_local():
    _, tex_a = objects.make_object("ball", seed=1, size=0.2)
    _, tex_b = objects.make_object("ball", seed=2, size=0.2)
    p = np.random.default_rng(0).uniform(-0.1, 0.1, size=(500, 3))
    _, tex_a_again = objects.make_object("ball", seed=1, size=0.2)
    np.testing.assert_array_equal(tex_a(p), tex_a_again(p))  # the seed alone fixes the texture
    assert np.abs(tex_a(p) - tex_b(p)).mean() > 0.05
    # neighbouring points agree more than distant ones (a texture, not white noise)
    near = np.abs(tex_a(p) - tex_a(p + 1e-4)).mean()
    far = np.abs(tex_a(p) - tex_a(p[::-1])).mean()
    assert near < 0.2 * far


def test_unknown_object_lists_valid_names():
    with pytest.raises(ValueError, match="unknown object 'teapot'.*'ball'.*'wolf'"):
        objects.make_object("teapot", 0, 0.2)


def test_gaussians_from_mesh_surface_flat_and_normal_aligned():
    mesh, colour_fn = objects.make_object("duck", seed=0, size=0.3)
    cloud = objects.gaussians_from_mesh(mesh, colour_fn, n_surface=400, n_interior=100, seed=0, sh_degree=2)
    assert cloud.n == 500 and cloud.sh_degree == 2 and np.all(cloud.sh_rest == 0)
    assert np.all(opacities(cloud) > 0.9)
    s, R = scales(cloud), quats_to_rotmats(normalized_quats(cloud))
    surface_axis = R[:400, :, 2]  # third local axis (smallest scale) of surface Gaussians
    np.testing.assert_allclose(np.abs(np.sum(surface_axis * cloud.normals[:400], axis=1)), 1.0, atol=1e-5)
    assert np.all(s[:400, 2] < 0.2 * s[:400, 0])
    _, dist, _ = mesh.nearest.on_surface(cloud.means[:400])
    assert dist.max() < 1e-4 * 0.3  # float32 storage of means
    assert mesh.contains(cloud.means[400:]).all()
    np.testing.assert_allclose(sh0_to_rgb(cloud.sh_dc), colour_fn(cloud.means), atol=1e-6)
