"""gca.assets.ply: exact round trip, activations, and one specific error per defect of a real scan."""

from __future__ import annotations

import numpy as np
import pytest
from plyfile import PlyData, PlyElement

from gca.assets import ply
from gca.assets.ply import GaussianCloud, PlyFormatError, read_ply, write_ply


def random_cloud(G: int, degree: int, seed: int = 0) -> GaussianCloud:
    rng = np.random.default_rng(seed)
    K = (degree + 1) ** 2 - 1
    f = lambda *s: rng.normal(size=s).astype(np.float32)  # noqa: E731
    return GaussianCloud(means=f(G, 3), normals=f(G, 3), sh_dc=f(G, 3), sh_rest=f(G, K, 3), opacity_logit=f(G),
                         log_scales=f(G, 3), quats_wxyz=f(G, 4))


def write_rows(path, columns: dict[str, np.ndarray], dtype: str = "<f4", text: bool = False) -> None:
    rows = np.empty(len(next(iter(columns.values()))), dtype=[(k, dtype) for k in columns])
    for k, v in columns.items():
        rows[k] = v
    PlyData([PlyElement.describe(rows, "vertex")], text=text).write(str(path))


def columns_of(cloud: GaussianCloud) -> dict[str, np.ndarray]:
    G, K = cloud.n, cloud.sh_rest.shape[1]
    cols = {n: cloud.means[:, i] for i, n in enumerate("xyz")}
    cols |= {f"n{a}": cloud.normals[:, i] for i, a in enumerate("xyz")}
    cols |= {f"f_dc_{i}": cloud.sh_dc[:, i] for i in range(3)}
    cols |= {f"f_rest_{c * K + k}": cloud.sh_rest[:, k, c] for c in range(3) for k in range(K)}
    cols |= {"opacity": cloud.opacity_logit} | {f"scale_{i}": cloud.log_scales[:, i] for i in range(3)}
    return cols | {f"rot_{i}": cloud.quats_wxyz[:, i] for i in range(4)}


@pytest.mark.parametrize("degree", [0, 1, 2, 3])
def test_round_trip_exact(tmp_path, degree):
    cloud = random_cloud(50, degree, seed=degree)
    back = read_ply(write_ply(tmp_path / "g.ply", cloud))
    assert back.sh_degree == degree
    for name in ("means", "normals", "sh_dc", "sh_rest", "opacity_logit", "log_scales", "quats_wxyz"):
        np.testing.assert_array_equal(getattr(back, name), getattr(cloud, name), err_msg=name)


def test_f_rest_is_channel_major_on_disk(tmp_path):
    """Reference 3DGS layout: f_rest index c * K + k holds channel c of coefficient k."""
    cloud = random_cloud(4, 2)
    write_ply(tmp_path / "g.ply", cloud)
    vertex = PlyData.read(str(tmp_path / "g.ply"))["vertex"]
    K = 8
    assert vertex.data.dtype.names.index("f_rest_0") == 9  # after x y z nx ny nz f_dc_0..2
    np.testing.assert_array_equal(vertex["f_rest_" + str(2 * K + 5)], cloud.sh_rest[:, 5, 2])
    assert vertex.data.dtype["x"] == np.dtype("<f4")
    assert PlyData.read(str(tmp_path / "g.ply")).byte_order == "<"


def test_activations_hand_computed():
    cloud = random_cloud(3, 0)
    cloud = GaussianCloud(**{**cloud.__dict__, "opacity_logit": np.array([0.0, np.log(3.0), -np.log(3.0)], np.float32),
                             "log_scales": np.log(np.array([[1, 2, 3]] * 3, np.float32)),
                             "quats_wxyz": np.array([[2, 0, 0, 0], [0, 0, 0, 5], [1, 1, 0, 0]], np.float32)})
    np.testing.assert_allclose(ply.opacities(cloud), [0.5, 0.75, 0.25], rtol=1e-6)
    np.testing.assert_allclose(ply.scales(cloud)[0], [1, 2, 3], rtol=1e-6)
    R = ply.quats_to_rotmats(ply.normalized_quats(cloud))
    np.testing.assert_allclose(R[1], np.diag([-1.0, -1.0, 1.0]), atol=1e-12)  # 180 deg about z
    np.testing.assert_allclose(R[2], [[1, 0, 0], [0, 0, -1], [0, 1, 0]], atol=1e-12)  # 90 deg about x
    np.testing.assert_allclose(ply.covariances(cloud)[2], R[2] @ np.diag([1, 4, 9]) @ R[2].T, atol=1e-12)
    np.testing.assert_allclose(ply.sh0_to_rgb([[0.0, 1.0, -1.0]]), [[0.5, 0.5 + ply.SH_C0, 0.5 - ply.SH_C0]])
    np.testing.assert_allclose(ply.rgb_to_sh0(ply.sh0_to_rgb([[0.3, -2.0, 7.0]])), [[0.3, -2.0, 7.0]])


def test_rotmats_quats_round_trip():
    q = np.random.default_rng(1).normal(size=(200, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    q *= np.sign(q[:, :1])
    np.testing.assert_allclose(ply.rotmats_to_quats(ply.quats_to_rotmats(q)), q, atol=1e-12)


def test_nerfstudio_style_file_loads(tmp_path):
    """No normals, doubles, extra properties (nerfstudio/gsplat exports): harmless, tolerated."""
    cloud = random_cloud(20, 1)
    cols = {k: v for k, v in columns_of(cloud).items() if k not in ("nx", "ny", "nz")}
    cols |= {"red": np.ones(20), "semantic_0": np.zeros(20)}
    write_rows(tmp_path / "ns.ply", cols, dtype="<f8")
    back = read_ply(tmp_path / "ns.ply")
    np.testing.assert_array_equal(back.normals, 0.0)
    np.testing.assert_array_equal(back.sh_rest, cloud.sh_rest)
    np.testing.assert_array_equal(back.means, cloud.means)
    assert back.means.dtype == np.float32


def test_ascii_file_loads(tmp_path):
    cloud = random_cloud(5, 0)
    write_rows(tmp_path / "a.ply", columns_of(cloud), text=True)
    np.testing.assert_allclose(read_ply(tmp_path / "a.ply").means, cloud.means, rtol=1e-6)


def _defect(tmp_path, edit) -> str:
    cols = columns_of(random_cloud(10, 1))
    edit(cols)
    write_rows(tmp_path / "bad.ply", cols)
    with pytest.raises(PlyFormatError) as info:
        read_ply(tmp_path / "bad.ply")
    assert "bad.ply" in str(info.value)
    return str(info.value)


def test_missing_property_named(tmp_path):
    assert "'scale_1'" in _defect(tmp_path, lambda c: c.pop("scale_1"))


def test_non_finite_named(tmp_path):
    def edit(c):
        c["opacity"] = c["opacity"].copy()
        c["opacity"][3] = np.nan
    message = _defect(tmp_path, edit)
    assert "'opacity'" in message and "non-finite" in message and "vertex 3" in message


def test_zero_quaternion_named(tmp_path):
    def edit(c):
        for i in range(4):
            c[f"rot_{i}"] = c[f"rot_{i}"].copy()
            c[f"rot_{i}"][7] = 0.0
    message = _defect(tmp_path, edit)
    assert "rot_0" in message and "zero quaternion" in message and "vertex 7" in message


def test_invalid_sh_count_named(tmp_path):
    assert "not a valid SH degree" in _defect(tmp_path, lambda c: c.update(f_rest_9=c["f_rest_0"], f_rest_10=c["f_rest_0"], f_rest_11=c["f_rest_0"]))
    assert "'f_rest_4'" in _defect(tmp_path, lambda c: c.update(f_rest_9=c.pop("f_rest_4")))


def test_empty_cloud_named(tmp_path):
    write_rows(tmp_path / "empty.ply", {k: np.zeros(0) for k in columns_of(random_cloud(1, 0))})
    with pytest.raises(PlyFormatError, match="empty.ply.*empty cloud"):
        read_ply(tmp_path / "empty.ply")


def test_not_a_ply_named(tmp_path):
    (tmp_path / "junk.ply").write_bytes(b"hello")
    with pytest.raises(PlyFormatError, match="junk.ply.*not a readable"):
        read_ply(tmp_path / "junk.ply")
