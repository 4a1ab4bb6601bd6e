"""Procedural, textured objects for the paper's scenes, and static 3DGS scans of them.

Synthetic objects (Table 1): ball, duck, pawn, cat, fish, bottle. Real-to-sim objects (Table 2) are
procedural stand-ins with the geometric complexity of the captured ones: ``dragon`` (sinuous body,
horns, wings, legs, tail), ``wolf`` (quadruped with a bushy tail), ``pudding`` (a wobbly displaced
flan). Meshes are unions of primitives (manifold3d boolean engine) or surfaces of revolution, always
watertight, y up, centred on the origin, scaled so their largest bounding-box side is ``size`` metres.
"""

from __future__ import annotations

import dataclasses
from typing import Callable

import numpy as np
import trimesh

from gca.assets.inside import mesh_contains
from gca.assets.ply import GaussianCloud, rgb_to_sh0, rotmats_to_quats, SH_REST_COUNTS
from gca.assets.texture import SolidTexture

ColourFn = Callable[[np.ndarray], np.ndarray]


# ----------------------------------------------------------------------------- primitives


def _ellipsoid(centre, radii, subdivisions: int = 3) -> trimesh.Trimesh:
    mesh = trimesh.creation.icosphere(subdivisions=subdivisions, radius=1.0)
    mesh.apply_scale(radii)
    return mesh.apply_translation(centre)


def _align_z(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """4x4 transform taking the +z axis at the origin to the segment a -> b's midpoint/direction."""
    T = trimesh.geometry.align_vectors([0, 0, 1], (b - a) / np.linalg.norm(b - a))
    T[:3, 3] = (a + b) / 2
    return T


def _capsule(a, b, radius: float) -> trimesh.Trimesh:
    a, b = np.asarray(a, float), np.asarray(b, float)
    mesh = trimesh.creation.capsule(height=np.linalg.norm(b - a), radius=radius, count=[16, 16])
    return mesh.apply_transform(_align_z(a, b))


def _cone(base, apex, radius: float) -> trimesh.Trimesh:
    base, apex = np.asarray(base, float), np.asarray(apex, float)
    mesh = trimesh.creation.cone(radius=radius, height=np.linalg.norm(apex - base), sections=24)
    mesh.apply_translation([0, 0, -np.linalg.norm(apex - base) / 2])
    return mesh.apply_transform(_align_z(base, apex))


def _chain(points, radii) -> list[trimesh.Trimesh]:
    """Capsules joining consecutive points, radius tapering along the chain."""
    points = np.asarray(points, float)
    return [_capsule(points[i], points[i + 1], radii[i]) for i in range(len(points) - 1)]


def _plate(polygon_xy, thickness: float, transform: np.ndarray) -> trimesh.Trimesh:
    """A thin extruded polygon (fin, wing), centred on its plane, then transformed."""
    from shapely.geometry import Polygon

    mesh = trimesh.creation.extrude_polygon(Polygon(polygon_xy), height=thickness)
    mesh.apply_translation([0, 0, -thickness / 2])
    return mesh.apply_transform(transform)


def _revolve(profile_ry) -> trimesh.Trimesh:
    """Surface of revolution about +y of a profile [(r, y), ...] starting and ending on the axis."""
    mesh = trimesh.creation.revolve(np.asarray(profile_ry, float), sections=64)
    return mesh.apply_transform(trimesh.transformations.rotation_matrix(-np.pi / 2, [1, 0, 0]))


def _union(parts: list[trimesh.Trimesh]) -> trimesh.Trimesh:
    return trimesh.boolean.union(parts, engine="manifold")


# ----------------------------------------------------------------------------- shapes


def _ball(rng) -> trimesh.Trimesh:
    return trimesh.creation.icosphere(subdivisions=4, radius=1.0)


def _duck(rng) -> trimesh.Trimesh:
    return _union([_ellipsoid([0, 0, 0], [1.0, 0.62, 0.7]), _ellipsoid([0.62, 0.62, 0], [0.42, 0.42, 0.4]),
                   _ellipsoid([1.05, 0.56, 0], [0.26, 0.07, 0.16]), _cone([-0.7, 0.1, 0], [-1.15, 0.5, 0], 0.3)])


def _pawn(rng) -> trimesh.Trimesh:
    profile = [(0, 0), (0.5, 0), (0.5, 0.12), (0.42, 0.2), (0.3, 0.26), (0.22, 0.5), (0.17, 0.75), (0.3, 0.8),
               (0.3, 0.86), (0.15, 0.9), (0.2, 0.95), (0.24, 1.02), (0.25, 1.1), (0.22, 1.2), (0.15, 1.27),
               (0, 1.3)]
    return _revolve(profile)


def _cat(rng) -> trimesh.Trimesh:
    legs = [_capsule([x, -0.1, z], [x, -0.75, z], 0.13) for x in (-0.55, 0.55) for z in (-0.25, 0.25)]
    t = np.linspace(0, 1, 6)
    tail = _chain(np.stack([-0.8 - 0.35 * t, 0.1 + 0.8 * t**0.7, 0.15 * np.sin(3 * t)], 1), 0.1 - 0.04 * t)
    ears = [_cone([0.95, 0.55, z], [1.0, 0.85, 1.3 * z], 0.12) for z in (-0.15, 0.15)]
    return _union([_ellipsoid([0, 0, 0], [0.9, 0.38, 0.38]), _ellipsoid([0.95, 0.38, 0], [0.32, 0.3, 0.3])]
                  + legs + tail + ears)


def _fish(rng) -> trimesh.Trimesh:
    tail = _plate([(0, 0), (-0.55, 0.45), (-0.45, 0), (-0.55, -0.45)], 0.08, trimesh.transformations.translation_matrix([-0.85, 0, 0]))
    dorsal = _plate([(-0.4, 0.0), (0.1, 0.0), (-0.25, 0.35)], 0.06, trimesh.transformations.translation_matrix([0, 0.3, 0]))
    fins = [_plate([(0, 0), (-0.3, -0.1), (-0.1, 0.12)], 0.05,
                   trimesh.transformations.translation_matrix([0.3, -0.12, z])) for z in (-0.2, 0.2)]
    return _union([_ellipsoid([0, 0, 0], [1.0, 0.4, 0.22]), tail, dorsal] + fins)


def _bottle(rng) -> trimesh.Trimesh:
    profile = [(0, 0), (0.32, 0), (0.35, 0.04), (0.35, 0.6), (0.3, 0.72), (0.14, 0.85), (0.12, 1.05),
               (0.15, 1.07), (0.15, 1.12), (0.0, 1.12)]
    return _revolve(profile)


def _dragon(rng) -> trimesh.Trimesh:
    t = np.linspace(0, 1, 14)
    spine = np.stack([1.6 * t - 0.8, 0.25 * np.sin(2 * np.pi * t) + 0.5 * t**3, 0.3 * np.sin(3 * np.pi * t)], 1)
    body = _chain(spine, 0.07 + 0.16 * np.sin(np.pi * np.clip(t, 0.05, 0.95)) ** 0.8)
    head = spine[-1] + [0.15, 0.05, 0]
    parts = body + [_ellipsoid(head, [0.2, 0.12, 0.12]), _capsule(head, head + [0.25, -0.04, 0], 0.07)]
    parts += [_cone(head + [0, 0.08, z], head + [-0.2, 0.35, 2.5 * z], 0.045) for z in (-0.06, 0.06)]
    for i, z in ((5, -1), (5, 1), (9, -1), (9, 1)):  # legs hanging from the spine
        hip = spine[i] + [0, -0.05, 0.12 * z]
        parts += _chain([hip, hip + [0.1, -0.3, 0.1 * z], hip + [0.05, -0.55, 0.12 * z]], [0.07, 0.055])
    for z in (-1, 1):  # wings: thin plates rising from the back
        T = trimesh.transformations.rotation_matrix(z * 0.9, [1, 0, 0])
        T[:3, 3] = spine[7] + [0, 0.1, 0.05 * z]
        parts.append(_plate([(-0.2, 0), (0.25, 0), (0.05, 0.6), (-0.35, 0.45)], 0.04, T))
    return _union(parts)


def _wolf(rng) -> trimesh.Trimesh:
    parts = [_ellipsoid([0, 0, 0], [0.75, 0.32, 0.3]), _ellipsoid([0.45, 0.08, 0], [0.38, 0.38, 0.33]),
             _capsule([0.6, 0.2, 0], [0.95, 0.5, 0], 0.17), _ellipsoid([1.05, 0.55, 0], [0.22, 0.2, 0.18]),
             _capsule([1.1, 0.5, 0], [1.4, 0.42, 0], 0.08)]
    parts += [_cone([1.0, 0.68, z], [0.98, 0.95, 1.2 * z], 0.07) for z in (-0.1, 0.1)]
    for x, z in ((0.5, -0.18), (0.5, 0.18), (-0.5, -0.17), (-0.5, 0.17)):
        knee = [x + 0.05 * np.sign(-x), -0.55, z]
        parts += _chain([[x, -0.1, z], knee, [x + 0.08, -1.0, z]], [0.09, 0.07])
    t = np.linspace(0, 1, 7)
    parts += _chain(np.stack([-0.7 - 0.6 * t, 0.1 - 0.35 * t**1.5, 0.1 * np.sin(4 * t)], 1), 0.07 + 0.1 * np.sin(np.pi * t))
    return _union(parts)


def _pudding(rng) -> trimesh.Trimesh:
    profile = [(0, 0), (0.9, 0), (0.95, 0.05), (0.78, 0.7), (0.68, 0.8), (0.4, 0.86), (0, 0.87)]
    mesh = _revolve(profile)
    vertices = mesh.vertices.copy()
    theta, y = np.arctan2(vertices[:, 2], vertices[:, 0]), vertices[:, 1]
    k, phase = rng.integers(3, 7, size=3), rng.uniform(0, 2 * np.pi, size=3)
    wobble = sum(0.05 * np.sin(ki * theta + p + 4 * y) for ki, p in zip(k, phase))
    vertices[:, [0, 2]] *= (1 + wobble)[:, None]  # radial displacement: topology (and watertightness) kept
    mesh = trimesh.Trimesh(vertices, mesh.faces, process=True)
    drip = [_ellipsoid([0.55 * np.cos(a), 0.6, 0.55 * np.sin(a)], [0.22, 0.3, 0.22], 2)
            for a in rng.uniform(0, 2 * np.pi, size=4)]
    return _union([mesh] + drip)


# calibration objects (issue 21, item 5): in no paper table; thin parts, holes and overhangs that stress
# segmentation, depth and shadows in ways the table objects do not
def _torus(rng) -> trimesh.Trimesh:
    ring = trimesh.creation.torus(major_radius=0.7, minor_radius=0.22, major_sections=48, minor_sections=16)
    ring.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 2 * 0.8, [1, 0, 0]))
    return ring


def _mushroom(rng) -> trimesh.Trimesh:
    profile = [(0, 0), (0.24, 0), (0.2, 0.35), (0.18, 0.62), (0.75, 0.66), (0.8, 0.74), (0.65, 0.92),
               (0.35, 1.05), (0, 1.08)]
    return _revolve(profile)


def _star(rng) -> trimesh.Trimesh:
    angles = np.pi / 2 + np.arange(10) * np.pi / 5
    radii = np.where(np.arange(10) % 2 == 0, 1.0, 0.42)
    polygon = [(r * np.cos(a), r * np.sin(a)) for r, a in zip(radii, angles)]
    return _plate(polygon, 0.3, trimesh.transformations.rotation_matrix(-0.35, [1, 0, 0]))


SHAPES: dict[str, Callable[[np.random.Generator], trimesh.Trimesh]] = {
    "ball": _ball, "duck": _duck, "pawn": _pawn, "cat": _cat, "fish": _fish, "bottle": _bottle,
    "dragon": _dragon, "wolf": _wolf, "pudding": _pudding,
    "torus": _torus, "mushroom": _mushroom, "star": _star,
}
BASE_RGB = {"ball": (0.8, 0.25, 0.2), "duck": (0.95, 0.8, 0.2), "pawn": (0.85, 0.8, 0.7),
            "cat": (0.6, 0.45, 0.35), "fish": (0.3, 0.55, 0.8), "bottle": (0.3, 0.7, 0.45),
            "dragon": (0.35, 0.6, 0.3), "wolf": (0.55, 0.55, 0.6), "pudding": (0.95, 0.75, 0.4),
            "torus": (0.75, 0.7, 0.65), "mushroom": (0.7, 0.3, 0.25), "star": (0.45, 0.4, 0.75)}


# ----------------------------------------------------------------------------- public API


def make_object(name: str, seed: int, size: float) -> tuple[trimesh.Trimesh, ColourFn]:
    """Build a watertight, textured object.

    Args:
        name: one of :data:`SHAPES` (``ball duck pawn cat fish bottle dragon wolf pudding``).
        seed: seeds the shape's random details and the texture.
        size: largest side of the bounding box [m].

    Returns:
        (mesh, colour_fn): the mesh (y up, bounding box centred on the origin, metres) and its
        solid texture ``colour_fn(points [N, 3] m) -> rgb [N, 3]``.
    """
    if name not in SHAPES:
        raise ValueError(f"gca/assets/objects.py: unknown object {name!r}; valid names: {sorted(SHAPES)}")
    if not size > 0:
        raise ValueError(f"gca/assets/objects.py: object size must be > 0 m, got {size}")
    mesh = SHAPES[name](np.random.default_rng(seed))
    mesh.apply_translation(-mesh.bounds.mean(axis=0))
    mesh.apply_scale(size / mesh.extents.max())
    if not (mesh.is_watertight and mesh.is_volume):
        raise RuntimeError(f"gca/assets/objects.py: object {name!r} (seed {seed}) is not a watertight volume")
    return mesh, SolidTexture(seed=seed, size=size, base_rgb=BASE_RGB[name])


def _tangent_frames(normals: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Rotation matrices [N, 3, 3] whose third column is the normal, random spin about it."""
    helper = np.where(np.abs(normals[:, :1]) < 0.9, [[1.0, 0, 0]], [[0, 1.0, 0]])
    t1 = np.cross(normals, helper)
    t1 /= np.linalg.norm(t1, axis=1, keepdims=True)
    t2 = np.cross(normals, t1)
    phi = rng.uniform(0, 2 * np.pi, size=(len(normals), 1))
    a, b = np.cos(phi) * t1 + np.sin(phi) * t2, -np.sin(phi) * t1 + np.cos(phi) * t2
    return np.stack([a, b, normals], axis=2)


def _interior_points(mesh: trimesh.Trimesh, n: int, rng: np.random.Generator) -> np.ndarray:
    """n points uniformly inside the mesh (rejection sampling in its bounding box) [n, 3].

    The inside test is :func:`gca.assets.inside.mesh_contains` (bounded memory), not ``mesh.contains``:
    without embree, trimesh's fallback took minutes and tens of GB on the dragon's 170k candidates."""
    found, fraction = [np.zeros((0, 3))], max(mesh.volume / np.prod(mesh.extents), 0.05)
    while sum(len(f) for f in found) < n:
        candidates = rng.uniform(*mesh.bounds, size=(int(1.3 * n / fraction) + 16, 3))
        found.append(candidates[mesh_contains(mesh, candidates)])
    return np.concatenate(found)[:n]


def _logit(p: float) -> float:
    return float(np.log(p / (1.0 - p)))


def gaussians_from_mesh(mesh: trimesh.Trimesh, colour_fn: ColourFn, n_surface: int, n_interior: int,
                        seed: int, sh_degree: int = 0, opacity: float = 0.95, footprint: float = 0.6,
                        flatness: float = 0.1) -> GaussianCloud:
    """A static 3DGS "scan" of a textured mesh: flat surface Gaussians plus round interior ones.

    Surface Gaussians sit at area-uniform samples, their smallest axis along the face normal:
    tangential std ``footprint * sqrt(area / n_surface)``, normal std ``flatness`` times that.
    Interior Gaussians are isotropic with std ``0.5 * (volume / n_interior)^(1/3)``.

    Args:
        mesh: watertight mesh [m].
        colour_fn: ``points [N, 3] -> rgb [N, 3]`` in [0, 1].
        n_surface, n_interior: Gaussian counts.
        seed: sampling seed.
        sh_degree: SH degree 0..3 of the stored cloud; bands above 0 are zero.
        opacity: activated opacity of every Gaussian, in (0, 1).
        footprint, flatness: surface Gaussian size factors (see above).

    Returns:
        GaussianCloud with n_surface + n_interior Gaussians (surface first; interior normals zero).
    """
    if sh_degree not in SH_REST_COUNTS:
        raise ValueError(f"gca/assets/objects.py: sh_degree must be 0..3, got {sh_degree}")
    if n_surface < 1 or n_interior < 0 or not 0 < opacity < 1:
        raise ValueError(f"gca/assets/objects.py: need n_surface >= 1, n_interior >= 0, 0 < opacity < 1; "
                         f"got {n_surface}, {n_interior}, {opacity}")
    rng = np.random.default_rng(seed)
    surface, faces = trimesh.sample.sample_surface(mesh, n_surface, seed=rng)
    normals = mesh.face_normals[faces]
    sigma_t = footprint * np.sqrt(mesh.area / n_surface)
    interior = _interior_points(mesh, n_interior, rng)
    sigma_i = 0.5 * (mesh.volume / max(n_interior, 1)) ** (1 / 3)
    means = np.concatenate([surface, interior])
    log_scales = np.concatenate([np.tile(np.log([sigma_t, sigma_t, flatness * sigma_t]), (n_surface, 1)),
                                 np.full((n_interior, 3), np.log(sigma_i))])
    quats = np.concatenate([rotmats_to_quats(_tangent_frames(normals, rng)), np.tile([1.0, 0, 0, 0], (n_interior, 1))])
    G = len(means)
    f32 = lambda a: np.ascontiguousarray(a, dtype=np.float32)  # noqa: E731
    return GaussianCloud(
        means=f32(means), normals=f32(np.concatenate([normals, np.zeros((n_interior, 3))])),
        sh_dc=f32(rgb_to_sh0(colour_fn(means))), sh_rest=np.zeros((G, SH_REST_COUNTS[sh_degree], 3), np.float32),
        opacity_logit=np.full(G, _logit(opacity), np.float32), log_scales=f32(log_scales), quats_wxyz=f32(quats))


@dataclasses.dataclass(frozen=True)
class ObjectConfig:
    """One entry of the ``objects`` section of params.yaml."""

    size: float = 0.3  # largest side of the bounding box [m]
    seed: int = 0  # shape details, texture and Gaussian sampling
    n_gaussians: int = 100_000  # Gaussians of the static scan [count]; paper ~1e5, CI ~3e3
    interior_fraction: float = 0.1  # share of them inside the volume [1]
    sh_degree: int = 3  # SH degree of the stored scan (bands > 0 are zero) [0..3]
    opacity: float = 0.95  # activated opacity of every Gaussian [1]
    density: float = 1000.0  # material density [kg/m^3], gives particle masses


def scan_object(name: str, cfg: ObjectConfig) -> tuple[trimesh.Trimesh, ColourFn, GaussianCloud]:
    """``make_object`` then ``gaussians_from_mesh`` with the counts and settings of ``cfg``."""
    mesh, colour_fn = make_object(name, cfg.seed, cfg.size)
    n_interior = int(round(cfg.interior_fraction * cfg.n_gaussians))
    cloud = gaussians_from_mesh(mesh, colour_fn, cfg.n_gaussians - n_interior, n_interior, seed=cfg.seed,
                                sh_degree=cfg.sh_degree, opacity=cfg.opacity)
    return mesh, colour_fn, cloud
