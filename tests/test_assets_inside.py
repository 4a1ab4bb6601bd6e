"""gca.assets.inside: point-in-mesh by vertical-ray parity (exact on convex solids, watertight through shared
edges and vertices, the same answers as trimesh's ray tests, memory bounded by the pair budget)."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from gca.assets import inside, objects
from gca.assets.particles import lattice


def _convex_reference(mesh: trimesh.Trimesh, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(inside, clear): strictly behind every face plane; clear: not within 1e-9 of any plane."""
    d = np.einsum("pfk,fk->pf", points[:, None, :] - mesh.triangles[None, :, 0, :], mesh.face_normals)
    return (d < 0).all(axis=1), (np.abs(d) > 1e-9).all(axis=1)


@pytest.mark.parametrize("budget", [1 << 19, 7])
def test_convex_solid_exact(budget):
    """An icosphere (convex): inside iff behind every face plane; a tiny pair budget gives the same answers."""
    mesh = trimesh.creation.icosphere(subdivisions=3, radius=1.0)
    points = np.random.default_rng(0).uniform(-1.2, 1.2, size=(4000, 3))
    expected, clear = _convex_reference(mesh, points)
    got = inside.points_inside(mesh.vertices, mesh.faces, points, budget=budget)
    assert clear.all() and np.array_equal(got, expected) and 0.3 < expected.mean() < 0.4


def test_rays_through_vertices_and_edges_count_once():
    """Vertical lines exactly through an octahedron's apexes and along its edges' projections, and through a box's
    face diagonals: each crossing is counted once (no double count, no miss), so the parity is right."""
    octa = trimesh.Trimesh(vertices=[[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]],
                           faces=[[0, 2, 4], [2, 1, 4], [1, 3, 4], [3, 0, 4], [2, 0, 5], [1, 2, 5], [3, 1, 5], [0, 3, 5]])
    assert octa.is_watertight and octa.volume > 0
    xy = np.array([[0, 0], [0, 0.3], [0.3, 0], [0, -0.3], [-0.3, 0], [0.25, 0.25], [-0.1, 0.6], [0.5, 0.5]])
    z = np.array([-2.0, -0.1, 0.0, 0.1, 2.0])
    points = np.array([[x, y, zz] for x, y in xy for zz in z], dtype=np.float64)
    expected = np.abs(points).sum(axis=1) < 1
    assert np.array_equal(inside.mesh_contains(octa, points), expected)
    box = trimesh.creation.box(extents=[1.0, 1.0, 1.0])  # triangulated faces: diagonals through (0, 0), (.25, .25)
    grid = np.stack(np.meshgrid([-0.25, 0.0, 0.25], [-0.25, 0.0, 0.25], [-0.75, -0.2, 0.0, 0.2, 0.75], indexing="ij"), -1)
    points = grid.reshape(-1, 3)
    assert np.array_equal(inside.mesh_contains(box, points), np.abs(points[:, 2]) < 0.5)


def test_dragon_agrees_with_trimesh_ray_tests(monkeypatch):
    """The paper dragon (8474 faces, thin wings and horns): the same answers as trimesh's float64 ray tests (its
    fallback without embree) on random points and on lattice points."""
    monkeypatch.setattr(trimesh.ray, "has_embree", False)
    mesh, _ = objects.make_object("dragon", seed=7, size=0.38)
    assert isinstance(mesh.ray, trimesh.ray.ray_triangle.RayMeshIntersector)  # not embree's
    rng = np.random.default_rng(1)
    cells, _ = lattice(*mesh.bounds, 0.0095)  # cell centres, as sample_mesh_interior queries them
    points = np.concatenate([rng.uniform(*mesh.bounds, size=(300, 3)), cells[rng.choice(len(cells), 300, replace=False)]])
    expected = mesh.contains(points)
    assert 0.03 < expected.mean() < 0.3
    assert np.array_equal(inside.mesh_contains(mesh, points), expected)
