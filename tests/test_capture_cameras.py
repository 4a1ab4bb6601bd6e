"""gca.capture.cameras and gca.capture.spring_gaus: small samples written in each tool's layout."""

from __future__ import annotations

import json
import struct

import numpy as np
import pytest
import torch
from PIL import Image

from gca.assets.ply import rotmats_to_quats
from gca.capture import cameras as cc, spring_gaus as sg
from gca.render.camera import look_at

W, H = 64, 48


@pytest.fixture
def cam():
    """A camera looking at the origin from (0.3, 0.2, -0.8), focal 60 px, principal point off-centre."""
    c = look_at([0.3, 0.2, -0.8], [0, 0, 0], [0, -1, 0], 50.0, W, H)
    K = c.K.copy()
    K[0, 2], K[1, 2] = 30.5, 25.0
    return cc.Camera(K=K, w2c=c.w2c, width=W, height=H)


def _pixels(camera, points):
    uv, depth = camera.project(torch.tensor(points, dtype=torch.float64))
    return uv.numpy(), depth.numpy()


POINTS = np.array([[0.0, 0.0, 0.0], [0.05, -0.02, 0.03], [-0.04, 0.06, -0.01]])


def _colmap_pose(camera):
    q = rotmats_to_quats(camera.w2c[None, :3, :3])[0]
    return q, camera.w2c[:3, 3]


def test_colmap_text_round_trip(tmp_path, cam):
    q, t = _colmap_pose(cam)
    fx, fy, cx, cy = cam.K[0, 0], cam.K[1, 1], cam.K[0, 2], cam.K[1, 2]
    (tmp_path / "cameras.txt").write_text(f"# Camera list\n1 PINHOLE {W} {H} {fx} {fy} {cx} {cy}\n"
                                          f"2 SIMPLE_RADIAL {W} {H} {fx} {cx} {cy} 0.0\n")
    (tmp_path / "images.txt").write_text(
        "# Image list with two lines of data per image:\n"
        f"1 {' '.join(map(str, q))} {' '.join(map(str, t))} 1 frame_000.png\n"
        "10.0 20.0 -1 30.0 40.0 5\n"
        f"2 {' '.join(map(str, q))} {' '.join(map(str, t))} 2 frame_001.png\n\n")
    cams = cc.read_colmap_text(tmp_path)
    assert list(cams) == ["frame_000.png", "frame_001.png"]
    np.testing.assert_allclose(cams["frame_000.png"].w2c, cam.w2c, atol=1e-9)
    np.testing.assert_allclose(_pixels(cams["frame_000.png"], POINTS)[0], _pixels(cam, POINTS)[0], atol=1e-6)
    assert cams["frame_001.png"].K[0, 0] == cams["frame_001.png"].K[1, 1] == pytest.approx(fx)


def test_colmap_text_errors_name_file_and_line(tmp_path, cam):
    (tmp_path / "cameras.txt").write_text(f"1 OPENCV {W} {H} 60 60 32 24 0.1 0 0 0\n")
    (tmp_path / "images.txt").write_text("")
    with pytest.raises(cc.CaptureError, match=r"cameras.txt:1: .*lens distortion.*image_undistorter"):
        cc.read_colmap_text(tmp_path)
    (tmp_path / "cameras.txt").write_text(f"1 PINHOLE {W} {H} 60 60 32 24\n")
    (tmp_path / "images.txt").write_text("1 1 0 0 0 0 0 1 7 a.png\n\n")
    with pytest.raises(cc.CaptureError, match=r"images.txt:1: camera 7 is not in cameras.txt"):
        cc.read_colmap_text(tmp_path)
    with pytest.raises(cc.CaptureError, match=r"nowhere/cameras.txt: file not found"):
        cc.read_colmap_text(tmp_path / "nowhere")


def test_transforms_json_converts_opengl_axes(tmp_path, cam):
    """A nerfstudio file written with the OpenGL c2w of ``cam`` reads back as ``cam``; the same matrix
    read as if it were OpenCV would put the object behind the camera."""
    cc.write_transforms_json(tmp_path / "transforms.json", {"frames/0000.png": cam})
    raw = json.loads((tmp_path / "transforms.json").read_text())
    c2w_gl = np.array(raw["frames"][0]["transform_matrix"])
    np.testing.assert_allclose(c2w_gl[:3, 2], -cam.c2w[:3, 2])  # OpenGL looks down -z
    back = cc.read_transforms_json(tmp_path / "transforms.json")["frames/0000.png"]
    np.testing.assert_allclose(back.w2c, cam.w2c, atol=1e-9)
    np.testing.assert_allclose(back.K, cam.K)
    assert (_pixels(back, POINTS)[1] > 0).all()
    assert (np.linalg.inv(c2w_gl)[2, :3] @ POINTS.T + np.linalg.inv(c2w_gl)[2, 3] < 0).all()


def test_transforms_json_blender_fov_and_errors(tmp_path, cam):
    c2w_gl = (cam.c2w @ cc.OPENGL_TO_OPENCV).tolist()
    path = tmp_path / "transforms.json"
    path.write_text(json.dumps({"camera_angle_x": 2 * np.arctan(W / 2 / 60.0), "w": W, "h": H,
                                "frames": [{"file_path": "./r_0", "transform_matrix": c2w_gl}]}))
    blender = cc.read_transforms_json(path)["./r_0"]
    np.testing.assert_allclose(blender.K, [[60, 0, W / 2], [0, 60, H / 2], [0, 0, 1]])
    path.write_text(json.dumps({"frames": [{"file_path": "a", "transform_matrix": c2w_gl}]}))
    with pytest.raises(cc.CaptureError, match=r"transforms.json \(frames\[0\]\): needs the image size"):
        cc.read_transforms_json(path)
    path.write_text("{not json")
    with pytest.raises(cc.CaptureError, match="transforms.json: malformed JSON"):
        cc.read_transforms_json(path)


def test_transform_camera_keeps_pixels_and_scales_depth(cam):
    from gca.assets.scan import rotation_from_euler_deg

    s, Q, a = 2.5, rotation_from_euler_deg([10, 80, -30]), np.array([0.3, -0.1, 0.2])
    A = np.eye(4)
    A[:3, :3], A[:3, 3] = s * Q, a
    moved = cc.transform_camera(cam, A)
    uv0, d0 = _pixels(cam, POINTS)
    uv1, d1 = _pixels(moved, POINTS @ (s * Q).T + a)
    np.testing.assert_allclose(uv1, uv0, atol=1e-6)
    np.testing.assert_allclose(d1, s * d0, rtol=1e-9)
    half = cc.rescale(cam, W // 2, H // 2)
    np.testing.assert_allclose(_pixels(half, POINTS)[0], _pixels(cam, POINTS)[0] / 2, atol=1e-9)


def _write_colmap_bin(folder, K, size, poses):
    folder.mkdir(parents=True)
    with open(folder / "cameras.bin", "wb") as fh:
        fh.write(struct.pack("<Q", 1) + struct.pack("<iiQQ", 1, 1, *size)
                 + struct.pack("<4d", K[0, 0], K[1, 1], K[0, 2], K[1, 2]))
    with open(folder / "images.bin", "wb") as fh:
        fh.write(struct.pack("<Q", len(poses)))
        for i, (name, w2c) in enumerate(poses.items(), 1):
            q = rotmats_to_quats(w2c[None, :3, :3])[0]
            fh.write(struct.pack("<idddddddi", i, *q, *w2c[:3, 3], 1) + name.encode() + b"\x00")
            fh.write(struct.pack("<Q", 1) + struct.pack("<ddq", 1.0, 2.0, -1))


def test_spring_gaus_layout_one_training_view(tmp_path, cam):
    """A tiny dataset in the Spring-Gaus real_capture layout: 3 video cameras, 4 frames each."""
    from scipy.spatial.transform import Rotation

    root = tmp_path / "real_capture"
    photo_K = np.array([[4000.0, 0, 2376], [0, 4000.0, 1336], [0, 0, 1]])
    _write_colmap_bin(root / "static/colmap/bun", photo_K, (4752, 2672), {"DSC0001.JPG": cam.w2c})
    calib, seq = {}, {"hit_frame": 2}
    for k, name in enumerate(sg.VIDEO_CAMERAS):
        w2c = look_at([np.cos(k), 0.3, np.sin(k)], [0, 0, 0], [0, -1, 0], 40.0, 96, 54).w2c
        calib[name] = {"rvecs": Rotation.from_matrix(w2c[:3, :3]).as_rotvec().tolist(), "tvecs": w2c[:3, 3].tolist()}
        seq[name] = [f"{name}_{i:04d}.jpg" for i in range(4)]
        for f in seq[name]:
            for sub, ext, mode in (("videos_images", ".jpg", "RGB"), ("videos_masks", ".png", "L")):
                p = root / "dynamic" / sub / name / (f[:-4] + ext)
                p.parent.mkdir(parents=True, exist_ok=True)
                Image.new(mode, (96, 54)).save(p)
    (root / "dynamic/sequences/bun").mkdir(parents=True)
    (root / "dynamic/sequences/bun/0.json").write_text(json.dumps(seq))
    (root / "dynamic/cameras_calib.json").write_text(json.dumps(calib))
    (root / "dynamic/sync.json").write_text("{}")

    s = sg.load_sequence(root, "bun", 0, train_view="C0787")
    assert s.train.name == "C0787" and [v.name for v in s.held_out] == ["C0733", "C0801"]
    assert s.hit_frame == 2 and s.fps == 120.0 and len(s.train.frames) == 4 == len(s.train.masks)
    assert s.train.masks[0].name == "C0787_0000.png"
    np.testing.assert_allclose(s.train.camera.K, [[4000 * 96 / 4752, 0, 48], [0, 4000 * 54 / 2672, 27], [0, 0, 1]])
    expected = look_at([np.cos(1), 0.3, np.sin(1)], [0, 0, 0], [0, -1, 0], 40.0, 96, 54).w2c
    np.testing.assert_allclose(s.train.camera.w2c, expected, atol=1e-9)
    (root / "dynamic/videos_masks/C0801/C0801_0003.png").unlink()
    with pytest.raises(cc.CaptureError, match=r"C0801_0003.png: file not found"):
        sg.load_sequence(root, "bun", 0)
    with pytest.raises(cc.CaptureError, match=r"no frame list for the training camera 'C9999'"):
        sg.load_sequence(root, "bun", 0, train_view="C9999")
