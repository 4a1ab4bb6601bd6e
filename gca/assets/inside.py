"""Which points lie inside a closed triangle mesh: vertical-ray parity, in bounded memory.

``trimesh.Trimesh.contains`` casts a ray per point along a fixed oblique direction, both ways. Without
embree (``embreex`` is optional, and the GPU hosts' environment lacks it) trimesh's fallback
(``trimesh.ray.ray_triangle``) first lists, for every ray at once, each triangle whose bounding box meets
the ray's bounding box: a Python list and then ~10 float64 arrays over all (ray, triangle) pairs, ~330 B
a pair. The ray's box is the oblique ray clipped to the mesh's box, so a point meets hundreds of triangles
(the paper dragon, 8474 faces: ~500 a ray; its particle lattice, 405k points over a box its body fills to
7.7 %: ~4e8 pairs, ~130 GB), and the pairs are listed by a Python loop over the rays (minutes).

Here the ray is vertical (+z). Its candidates are the triangles whose xy bounding box holds the point's
(x, y): a uniform xy grid of bins over the mesh, each triangle listed in the bins its xy box overlaps,
and a point's candidates are its bin's list (a few times the mesh's depth complexity; tens). The pairs
are processed in blocks of at most ``budget``, so memory is bounded whatever the number of points.

The crossing test is watertight: a vertical line through a shared edge or vertex is counted by exactly
one of the triangles around it (the edge functions are computed from the edge's vertices in one order,
so the two triangles of an edge see exactly opposite values, and zeros are broken by the rule of an
infinitesimal shift of the point by (eps, eps^2), the rasterisers' top-left rule). A point is inside
when the number of crossings strictly above it is odd (trimesh's parity rule); points on the surface,
as with trimesh, may go either way.
"""

from __future__ import annotations

import numpy as np

PAIR_BUDGET = 1 << 19  # (point, candidate triangle) pairs per vectorised block (~150 MB of temporaries)


def _triangle_tables(vertices: np.ndarray, faces: np.ndarray) -> dict[str, np.ndarray]:
    """Per triangle and edge (a->b, b->c, c->a): the edge's base vertex (the lower index), its oriented
    direction, the tie-break sign; and the corners' z."""
    i = faces
    j = np.roll(faces, -1, axis=1)  # edge e runs from corner e to corner e + 1
    flip = i > j
    base = np.where(flip, j, i)
    tip = np.where(flip, i, j)
    sign = np.where(flip, -1.0, 1.0)
    ux, uy = vertices[base, 0], vertices[base, 1]
    # (tip - base) * sign: exactly the negation of the neighbour's value for a shared edge
    dx = (vertices[tip, 0] - ux) * sign
    dy = (vertices[tip, 1] - uy) * sign
    # E(p + (eps, eps^2)) = E(p) - dy eps + dx eps^2: the sign of a zero edge function
    tie = np.where(dy != 0, np.sign(-dy), np.sign(dx))
    z = vertices[faces, 2]
    return {"ux": ux, "uy": uy, "dx": dx, "dy": dy, "tie": tie, "z": z, "zmin": z.min(axis=1), "zmax": z.max(axis=1)}


def _bin_triangles(vertices: np.ndarray, faces: np.ndarray, lo: np.ndarray, hi: np.ndarray):
    """Uniform xy grid over [lo, hi] with about one bin per triangle; each triangle listed in the bins its
    xy bounding box overlaps (the grid coarsened while the listings exceed ``8 F + 2^20``: long slivers).
    Returns (bin_of(x, y) -> bin ids, CSR starts [nbins + 1], triangles [R])."""
    extent = np.maximum(hi[:2] - lo[:2], 1e-300)
    cell = float(np.sqrt(extent[0] * extent[1] / max(len(faces), 1)))
    n = np.clip(np.ceil(extent / cell), 1, 4096).astype(np.int64)
    corners = vertices[faces]  # [F, 3, 3]
    cmin, cmax = corners[:, :, :2].min(axis=1), corners[:, :, :2].max(axis=1)

    def bin_xy(xy: np.ndarray, n: np.ndarray) -> np.ndarray:  # [.., 2] -> [.., 2] bin coordinates, monotone
        return np.clip(np.floor((xy - lo[:2]) * (n / extent)), 0, n - 1).astype(np.int64)

    while True:
        b0, b1 = bin_xy(cmin, n), bin_xy(cmax, n)
        width = b1 - b0 + 1
        count = width[:, 0] * width[:, 1]
        if count.sum() <= 8 * len(faces) + (1 << 20) or n.max() == 1:
            break
        n = np.maximum(n // 2, 1)
    tri = np.repeat(np.arange(len(faces)), count)
    offset = np.arange(len(tri)) - np.repeat(np.cumsum(count) - count, count)
    wx = width[tri, 0]
    bins = (b0[tri, 0] + offset % wx) * n[1] + b0[tri, 1] + offset // wx
    order = np.argsort(bins, kind="stable")
    starts = np.searchsorted(bins[order], np.arange(n[0] * n[1] + 1))

    def bin_of(x: np.ndarray, y: np.ndarray) -> np.ndarray:
        b = bin_xy(np.stack([x, y], axis=-1), n)
        return b[:, 0] * n[1] + b[:, 1]

    return bin_of, starts, tri[order]


def points_inside(vertices: np.ndarray, faces: np.ndarray, points: np.ndarray, budget: int = PAIR_BUDGET) -> np.ndarray:
    """Whether each point lies inside the closed mesh (vertices, faces): parity of its +z ray's crossings.

    Args:
        vertices: [V, 3] positions; faces: [F, 3] vertex indices of a closed (watertight) surface.
        points: [N, 3] query points (same frame).
        budget: (point, candidate triangle) pairs per block: bounds the temporaries (~300 B a pair).

    Returns:
        [N] bool.
    """
    V = np.asarray(vertices, dtype=np.float64)
    F = np.asarray(faces, dtype=np.int64)
    P = np.asarray(points, dtype=np.float64)
    assert V.ndim == 2 and V.shape[1] == 3 and F.ndim == 2 and F.shape[1] == 3 and P.ndim == 2 and P.shape[1] == 3, \
        (V.shape, F.shape, P.shape)
    inside = np.zeros(len(P), dtype=bool)
    if len(F) == 0 or len(P) == 0:
        return inside
    lo, hi = V.min(axis=0), V.max(axis=0)
    query = np.nonzero(np.all((P >= lo) & (P <= hi), axis=1))[0]
    if len(query) == 0:
        return inside
    tab = _triangle_tables(V, F)
    bin_of, starts, listed = _bin_triangles(V, F, lo, hi)
    qbin = bin_of(P[query, 0], P[query, 1])
    first, count = starts[qbin], starts[qbin + 1] - starts[qbin]
    ends = np.cumsum(count)
    begin = 0
    while begin < len(query):  # blocks of points whose pairs fit the budget (at least one point a block)
        stop = max(int(np.searchsorted(ends, (ends[begin - 1] if begin else 0) + budget, side="right")), begin + 1)
        c = count[begin:stop]
        local = np.repeat(np.arange(stop - begin), c)
        t = listed[np.repeat(first[begin:stop], c) + np.arange(len(local)) - np.repeat(np.cumsum(c) - c, c)]
        p = P[query[begin:stop]][local]
        E = tab["dx"][t] * (p[:, 1:2] - tab["uy"][t]) - tab["dy"][t] * (p[:, 0:1] - tab["ux"][t])  # [m, 3]
        s = np.sign(E)
        s = np.where(s == 0, tab["tie"][t], s)
        hit = (s[:, 0] == s[:, 1]) & (s[:, 1] == s[:, 2]) & (s[:, 0] != 0)
        E, t, p, local = E[hit], t[hit], p[hit], local[hit]
        zc = tab["z"][t]
        # barycentric weights: corner a <- edge b->c (1), b <- c->a (2), c <- a->b (0)
        with np.errstate(invalid="ignore", divide="ignore"):  # 0 / 0 only for a degenerate triangle: no crossing
            z = (E[:, 1] * zc[:, 0] + E[:, 2] * zc[:, 1] + E[:, 0] * zc[:, 2]) / E.sum(axis=1)
        z = np.clip(z, tab["zmin"][t], tab["zmax"][t])
        above = np.bincount(local[z > p[:, 2]], minlength=stop - begin)
        inside[query[begin:stop]] = (above % 2) == 1
        begin = stop
    return inside


def mesh_contains(mesh, points: np.ndarray, budget: int = PAIR_BUDGET) -> np.ndarray:
    """:func:`points_inside` for a ``trimesh.Trimesh`` (a drop-in for ``mesh.contains``, in bounded memory)."""
    return points_inside(mesh.vertices, mesh.faces, points, budget)
