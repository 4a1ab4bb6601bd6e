"""The capture scene kind (issue 23): a user's video imported into the scene layout, preprocessed from frames
only, and scored without ground truth."""

from __future__ import annotations

import numpy as np
import pytest
from PIL import Image

from gca.capture.cameras import CaptureError, write_transforms_json
from gca.capture.video import CaptureVideoConfig, median_plate, read_frames, split_heldout
from gca.eval.capture import mask_iou, silhouette_chamfer_px
from gca.render.camera import look_at
from gca.scenes.capture import capture_timing, is_capture, load_heldout, write_capture
from gca.scenes.store import load_view
from gca.vision.depth import silhouette_depth


def _video(folder, n=6, w=40, h=30):
    folder.mkdir(parents=True)
    rng = np.random.default_rng(0)
    plate = (rng.uniform(0.3, 0.7, (h, w, 3)) * 255).astype(np.uint8)
    for i in range(n):
        img = plate.copy()
        img[10:20, 2 + 5 * i: 12 + 5 * i] = (250, 20, 20)
        Image.fromarray(img).save(folder / f"f{i:03d}.png")
    return plate


def test_capture_import_layout_timing_camera(tmp_path):
    plate = _video(tmp_path / "frames")
    cam = look_at([0, 0, 2], [0, 0, 0], [0, 1, 0], 50.0, 80, 60)  # calibrated at twice the frames' size
    write_transforms_json(tmp_path / "transforms.json", {"video": cam})
    cfg = CaptureVideoConfig(video="frames", camera="transforms.json", fps=30.0, heldout_fraction=0.34,
                             depth="silhouette")
    A = np.diag([0.5, 0.5, 0.5, 1.0])
    A[:3, 3] = [0.5, 0.2, 0.5]
    out, gt = tmp_path / "scene", tmp_path / "gt"
    out.mkdir()
    m = write_capture(out, gt, "s", "obj", cfg, 1e-3, A, root=tmp_path)
    assert (m["n_train_frames"], m["n_heldout_frames"], m["substeps"]) == (4, 2, 33)
    assert is_capture(out) and list(gt.iterdir()) == [gt / "README.md"]
    view = load_view(out, "train0")
    assert view.rgb.shape == (4, 30, 40, 3)
    assert view.camera.K[0, 0] == pytest.approx(cam.K[0, 0] / 2)  # rescaled to the frames
    # the camera centre moved with the similarity: sim = 0.5 x + t
    assert np.allclose(view.camera.center, 0.5 * cam.center + A[:3, 3], atol=1e-6)
    held, idx = load_heldout(out)
    assert idx == [5, 6] and held.rgb.shape[0] == 2
    # the median plate recovers the background where the object passes at most half the time
    assert np.abs(median_plate(read_frames(tmp_path / "frames")[1]).astype(int) - plate).max() <= 1


def test_capture_errors_are_one_line(tmp_path):
    with pytest.raises(CaptureError, match="video folder not found"):
        read_frames(tmp_path / "nope")
    _video(tmp_path / "frames")
    Image.new("RGB", (10, 10)).save(tmp_path / "frames" / "z.png")
    with pytest.raises(CaptureError, match="z.png: frame is 10x10"):
        read_frames(tmp_path / "frames")
    with pytest.raises(CaptureError, match="fps"):
        CaptureVideoConfig(video="v", camera="c", fps=0.0)
    with pytest.raises(CaptureError, match="need >= 2"):
        split_heldout(2, 0.5)
    assert capture_timing(50.0, 1e-3) == (20, 50.0)


def test_silhouette_metrics_and_depth():
    a = np.zeros((20, 20), bool)
    a[5:15, 5:15] = True
    b = np.roll(a, 3, axis=1)
    assert silhouette_chamfer_px(a, a) == 0.0 and mask_iou(a, a) == 1.0
    assert 1.0 < silhouette_chamfer_px(a, b) <= 3.0
    assert mask_iou(a, b) == pytest.approx(70 / 130)
    d = silhouette_depth(a[None])[0]
    assert d[0, 0] == 1.5 and d[10, 10] < d[5, 5] <= 1.0  # nearest in the middle


def test_capture_page_from_metrics_only_and_indexed(tmp_path):
    """build_reports writes captures/<scene>.md from a capture record and its demo JSON, copies both videos next to
    it and lists it in the README; a capture without a demo says how to make one."""
    import json

    import imageio.v3 as iio

    from gca.report import build_reports

    gif = np.zeros((2, 8, 8, 3), np.uint8)
    for scene, with_demo in (("mine", True), ("other", False)):
        run = tmp_path / "metrics/eval" / scene / "gca"
        run.mkdir(parents=True)
        iio.imwrite(run / "resim.gif", gif, extension=".gif")
        law = {"sentence": "behaves like von Mises plasticity: E = 1.2e+05 Pa, yield stress = 3e+03 Pa",
               "weights": {"e/sigma": 0.7, "e/corotated": 0.3, "p/von_mises": 0.9, "p/identity": 0.1}}
        (run.parent / "gca.json").write_text(json.dumps({
            "kind": "capture", "status": "ok", "scene": scene, "method": "gca", "n_heldout_frames": 2,
            "psnr_heldout": 21.234, "ssim_heldout": 0.81, "mask_iou_heldout": 0.77, "silhouette_cd_px_heldout": 1.9,
            "nearest_law": law, "velocity": {"v0": [0.1, -1.0, 0.0]}, "resim_gif": str(run / "resim.gif")}))
        if with_demo:
            demo = tmp_path / "metrics/demo_capture" / scene
            demo.mkdir(parents=True)
            iio.imwrite(demo / "demo.gif", gif, extension=".gif")
            (demo.parent / f"{scene}.json").write_text(json.dumps({
                "status": "ok", "method": "gca", "law_source": "runs/mine/gca/law.pt", "object": scene, "lift_m": 0.15,
                "rotation_deg": [0, 0, 30], "v0": [-0.6, 1.0, 0.0], "w0": [0, 3, 0], "frames": 12, "fps": 50.0,
                "seconds_simulated": 0.24, "finite": True, "com_drop_m": 0.2, "max_strain": 0.05,
                "gif": str(demo / "demo.gif")}))
    out = tmp_path / "reports/ci"
    build_reports(tmp_path / "metrics/eval", out, capture_demos_dir=tmp_path / "metrics/demo_capture")
    page = (out / "captures/mine.md").read_text()
    assert "| gca | ok | 2 | 21.2 | 0.81 | 0.77 | 1.9 | (0.10, -1.00, 0.00) |" in page
    assert "the learned law behaves like von Mises plasticity: E = 1.2e+05 Pa, yield stress = 3e+03 Pa" in page
    assert "p/von_mises 0.90" in page
    assert "](mine_gca_resim.gif)" in page and (out / "captures/mine_gca_resim.gif").is_file()
    assert "](mine_demo.gif)" in page and (out / "captures/mine_demo.gif").is_file()
    assert "raised 0.15 m" in page and "12 frames at 50 fps" in page
    assert "`dvc repro demo_capture@other`" in (out / "captures/other.md").read_text()
    index = (out / "README.md").read_text()
    assert "(captures/mine.md)" in index and "(captures/other.md)" in index
