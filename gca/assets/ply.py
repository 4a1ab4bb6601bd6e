"""3D Gaussian Splatting ``.ply`` files: the layout written by the reference 3DGS trainer.

One ``vertex`` element, one row per Gaussian, little-endian float32 properties::

    x y z                      mean [m, world frame]
    nx ny nz                   normal (unused by 3DGS; zeros there; optional on read)
    f_dc_0 f_dc_1 f_dc_2       SH band-0 coefficient per colour channel
    f_rest_0 ... f_rest_{3K-1} SH bands 1..deg, channel-major: f_rest index = c * K + k
    opacity                    opacity logit (pre-sigmoid)
    scale_0 scale_1 scale_2    log of the standard deviations [log m]
    rot_0 rot_1 rot_2 rot_3    rotation quaternion (w, x, y, z), not necessarily normalised

with ``K = (deg + 1)^2 - 1`` for SH degree ``deg`` in 0..3. gsplat and nerfstudio exports use the same
names; they may omit the normals, store doubles or carry extra properties (e.g. colours, ``f_*``
of a segmentation head): missing normals read as zeros, doubles are cast to float32 and unknown
properties are ignored.
"""

from __future__ import annotations

import dataclasses
import os
from pathlib import Path

import numpy as np
from plyfile import PlyData, PlyElement

from gca.io import atomic_path

SH_C0 = 0.28209479177387814  # Y_0^0 = 1 / (2 sqrt(pi)); RGB = SH_C0 * f_dc + 0.5
SH_REST_COUNTS = {0: 0, 1: 3, 2: 8, 3: 15}  # K = (deg + 1)^2 - 1 coefficients per channel
_REQUIRED = ("x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity",
             "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3")


class PlyFormatError(ValueError):
    """A ``.ply`` file is not a usable 3DGS scan (the message names the file and the property)."""


@dataclasses.dataclass(frozen=True)
class GaussianCloud:
    """A static 3DGS scan in its stored (pre-activation) parameterisation, float32 numpy arrays.

    Attributes:
        means: [G, 3] centres [m].
        normals: [G, 3] normals (zeros when unknown).
        sh_dc: [G, 3] band-0 SH coefficients per channel.
        sh_rest: [G, K, 3] higher SH bands, K = (deg + 1)^2 - 1 (K = 0 for degree 0).
        opacity_logit: [G] opacity before the sigmoid.
        log_scales: [G, 3] log standard deviations along the Gaussian's local axes [log m].
        quats_wxyz: [G, 4] rotation quaternions (w, x, y, z), any non-zero norm.
    """

    means: np.ndarray
    normals: np.ndarray
    sh_dc: np.ndarray
    sh_rest: np.ndarray
    opacity_logit: np.ndarray
    log_scales: np.ndarray
    quats_wxyz: np.ndarray

    def __post_init__(self) -> None:
        G = self.means.shape[0] if self.means.ndim == 2 else -1
        expected = {"means": (G, 3), "normals": (G, 3), "sh_dc": (G, 3), "opacity_logit": (G,),
                    "log_scales": (G, 3), "quats_wxyz": (G, 4)}
        for name, shape in expected.items():
            value = getattr(self, name)
            if value.shape != shape:
                raise ValueError(f"GaussianCloud.{name}: shape {value.shape}, expected {shape}")
        rest = self.sh_rest
        if rest.ndim != 3 or rest.shape[0] != G or rest.shape[2] != 3 or rest.shape[1] not in SH_REST_COUNTS.values():
            raise ValueError(f"GaussianCloud.sh_rest: shape {rest.shape}, expected [G, K, 3] with K in "
                             f"{sorted(SH_REST_COUNTS.values())}")

    @property
    def n(self) -> int:
        """Number of Gaussians G."""
        return int(self.means.shape[0])

    @property
    def sh_degree(self) -> int:
        """SH degree 0..3 implied by K."""
        return {k: d for d, k in SH_REST_COUNTS.items()}[self.sh_rest.shape[1]]

    def subset(self, index: np.ndarray) -> "GaussianCloud":
        """The Gaussians selected by ``index`` (integer indices or a boolean mask [G])."""
        return GaussianCloud(**{f.name: getattr(self, f.name)[index] for f in dataclasses.fields(self)})


# ----------------------------------------------------------------------------- activations


def opacities(cloud: GaussianCloud) -> np.ndarray:
    """Activated opacities sigmoid(opacity_logit), [G] in (0, 1)."""
    return 1.0 / (1.0 + np.exp(-cloud.opacity_logit.astype(np.float64)))


def scales(cloud: GaussianCloud) -> np.ndarray:
    """Standard deviations exp(log_scales), [G, 3] in metres."""
    return np.exp(cloud.log_scales.astype(np.float64))


def normalized_quats(cloud: GaussianCloud) -> np.ndarray:
    """Unit quaternions (w, x, y, z), [G, 4] float64."""
    q = cloud.quats_wxyz.astype(np.float64)
    return q / np.linalg.norm(q, axis=1, keepdims=True)


def quats_to_rotmats(quats_wxyz: np.ndarray) -> np.ndarray:
    """Rotation matrices of unit quaternions.

    Args:
        quats_wxyz: [N, 4] unit quaternions (w, x, y, z).

    Returns:
        [N, 3, 3] rotation matrices R; column j is the Gaussian's local axis j in the world.
    """
    assert quats_wxyz.ndim == 2 and quats_wxyz.shape[1] == 4, quats_wxyz.shape
    w, x, y, z = quats_wxyz.T
    R = np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
                  2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
                  2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], axis=1)
    return R.reshape(-1, 3, 3)


def rotmats_to_quats(R: np.ndarray) -> np.ndarray:
    """Unit quaternions (w, x, y, z) [N, 4] of rotation matrices R [N, 3, 3] (Shepperd's method)."""
    assert R.ndim == 3 and R.shape[1:] == (3, 3), R.shape
    m = R.reshape(-1, 9)
    trace = m[:, 0] + m[:, 4] + m[:, 8]
    # 4 q_i^2 for i = w, x, y, z; take the largest for a well-conditioned division.
    diag = np.stack([1 + trace, 1 + m[:, 0] - m[:, 4] - m[:, 8], 1 - m[:, 0] + m[:, 4] - m[:, 8],
                     1 - m[:, 0] - m[:, 4] + m[:, 8]], axis=1)
    best = np.argmax(diag, axis=1)
    s = np.sqrt(np.maximum(diag[np.arange(len(m)), best], 1e-300))  # 2 |q_best|
    off = {  # (w, x, y, z) * 2 * q_best for each choice of best
        0: (s * s, m[:, 7] - m[:, 5], m[:, 2] - m[:, 6], m[:, 3] - m[:, 1]),
        1: (m[:, 7] - m[:, 5], s * s, m[:, 1] + m[:, 3], m[:, 2] + m[:, 6]),
        2: (m[:, 2] - m[:, 6], m[:, 1] + m[:, 3], s * s, m[:, 5] + m[:, 7]),
        3: (m[:, 3] - m[:, 1], m[:, 2] + m[:, 6], m[:, 5] + m[:, 7], s * s),
    }
    q = np.zeros((len(m), 4))
    for b, comps in off.items():
        rows = best == b
        q[rows] = np.stack(comps, axis=1)[rows] / (2 * s[rows, None])
    return q * np.where(q[:, :1] < 0, -1.0, 1.0)


def covariances(cloud: GaussianCloud) -> np.ndarray:
    """World covariances Sigma = R diag(s^2) R^T, [G, 3, 3] in m^2 (float64)."""
    R = quats_to_rotmats(normalized_quats(cloud))
    return np.einsum("gij,gj,gkj->gik", R, scales(cloud) ** 2, R)


def sh0_to_rgb(sh_dc: np.ndarray) -> np.ndarray:
    """View-independent colour of band-0 SH: rgb = SH_C0 * f_dc + 0.5, same shape (not clipped)."""
    return SH_C0 * np.asarray(sh_dc, dtype=np.float64) + 0.5


def rgb_to_sh0(rgb: np.ndarray) -> np.ndarray:
    """Inverse of :func:`sh0_to_rgb`: f_dc = (rgb - 0.5) / SH_C0."""
    return (np.asarray(rgb, dtype=np.float64) - 0.5) / SH_C0


# ----------------------------------------------------------------------------- reading


def _column(vertex, props: set, name: str, path: Path) -> np.ndarray:
    """One property as float32 [G], refusing missing or non-finite values."""
    if name not in props:
        raise PlyFormatError(f"{path}: missing vertex property {name!r}")
    values = np.asarray(vertex[name], dtype=np.float64)
    bad = ~np.isfinite(values)
    if bad.any():
        raise PlyFormatError(f"{path}: property {name!r} has {int(bad.sum())} non-finite values "
                             f"(first at vertex {int(np.argmax(bad))})")
    return values.astype(np.float32)


def _columns(vertex, props: set, names, path: Path) -> np.ndarray:
    return np.stack([_column(vertex, props, n, path) for n in names], axis=1)


def _sh_rest(vertex, props: set, path: Path) -> np.ndarray:
    """The f_rest_* properties as [G, K, 3] (channel-major on disk: index c * K + k)."""
    count = sum(p.startswith("f_rest_") for p in props)
    K = count // 3
    if count % 3 or K not in SH_REST_COUNTS.values():
        raise PlyFormatError(f"{path}: {count} 'f_rest_*' properties is not a valid SH degree "
                             f"(expected 3 * K with K in {sorted(SH_REST_COUNTS.values())})")
    G = len(vertex)
    if K == 0:
        return np.zeros((G, 0, 3), dtype=np.float32)
    flat = _columns(vertex, props, [f"f_rest_{i}" for i in range(count)], path)  # [G, 3K]
    return np.ascontiguousarray(flat.reshape(G, 3, K).transpose(0, 2, 1))


def read_ply(path: str | os.PathLike) -> GaussianCloud:
    """Read a 3DGS ``.ply`` (reference trainer, gsplat or nerfstudio export).

    Args:
        path: the file.

    Returns:
        The :class:`GaussianCloud` (float32; normals zero when the file has none).

    Raises:
        PlyFormatError: unreadable file, no vertex element, empty cloud, missing property,
            non-finite value, zero quaternion or an f_rest count that is no SH degree 0..3.
    """
    path = Path(path)
    try:
        ply = PlyData.read(str(path))
    except Exception as exc:  # plyfile raises several types for malformed headers/bodies
        raise PlyFormatError(f"{path}: not a readable .ply file ({type(exc).__name__}: {exc})") from exc
    if "vertex" not in [e.name for e in ply.elements]:
        raise PlyFormatError(f"{path}: no 'vertex' element")
    vertex = ply["vertex"]
    if vertex.count == 0:
        raise PlyFormatError(f"{path}: empty cloud (0 vertices)")
    props = {p.name for p in vertex.properties}
    data = vertex.data
    normals = (_columns(data, props, ("nx", "ny", "nz"), path) if {"nx", "ny", "nz"} <= props
               else np.zeros((vertex.count, 3), dtype=np.float32))
    quats = _columns(data, props, ("rot_0", "rot_1", "rot_2", "rot_3"), path)
    zero = np.linalg.norm(quats.astype(np.float64), axis=1) < 1e-12
    if zero.any():
        raise PlyFormatError(f"{path}: properties 'rot_0..rot_3' hold {int(zero.sum())} zero quaternions "
                             f"(first at vertex {int(np.argmax(zero))})")
    return GaussianCloud(
        means=_columns(data, props, ("x", "y", "z"), path), normals=normals,
        sh_dc=_columns(data, props, ("f_dc_0", "f_dc_1", "f_dc_2"), path),
        sh_rest=_sh_rest(data, props, path), opacity_logit=_column(data, props, "opacity", path),
        log_scales=_columns(data, props, ("scale_0", "scale_1", "scale_2"), path), quats_wxyz=quats)


# ----------------------------------------------------------------------------- writing


def _property_names(K: int) -> list[str]:
    return (["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
            + [f"f_rest_{i}" for i in range(3 * K)]
            + ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"])


def write_ply(path: str | os.PathLike, cloud: GaussianCloud) -> Path:
    """Write ``cloud`` as a binary little-endian 3DGS ``.ply`` (atomic: temp file, then rename).

    Args:
        path: destination file.
        cloud: the Gaussians; every array is stored as float32.

    Returns:
        ``path``.
    """
    path = Path(path)
    if cloud.n == 0:
        raise PlyFormatError(f"{path}: refusing to write an empty cloud")
    G, K = cloud.n, cloud.sh_rest.shape[1]
    rest = cloud.sh_rest.transpose(0, 2, 1).reshape(G, 3 * K)  # channel-major, index c * K + k
    table = np.concatenate([cloud.means, cloud.normals, cloud.sh_dc, rest, cloud.opacity_logit[:, None],
                            cloud.log_scales, cloud.quats_wxyz], axis=1).astype("<f4")
    names = _property_names(K)
    rows = np.empty(G, dtype=[(n, "<f4") for n in names])
    for i, name in enumerate(names):
        rows[name] = table[:, i]
    with atomic_path(path) as tmp:
        PlyData([PlyElement.describe(rows, "vertex")], text=False, byte_order="<").write(str(tmp))
    return path
