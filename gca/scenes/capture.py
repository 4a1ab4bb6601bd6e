"""A capture scene's observations in the layout of :mod:`gca.scenes.store` (the ground_truth stage's capture
branch), and what evaluation reads back: the held-out frames.

    data/scenes/<scene>/
      meta.json            kind "capture"; dt, substeps (round(1 / (fps dt))), video_frames (1-based
                           simulated frames of the training part), heldout_frames (the rest), times [s], fps
      cameras.json         {"train0": the video's camera in the sim frame, "heldout0": the same camera}
      views/train0/rgb/    the training frames (the first 1 - heldout_fraction of the video)
      views/train0/plate.png   the user's empty-scene image, else the median of all frames
      views/heldout0/rgb/  the held-out frames (the video's last part; training never reads them)
      preview.gif

Image k of the video (0-based) is simulated frame k + 1: the launch state is one frame interval before
the first image. No ground truth exists for a capture: the ground_truth stage's ``--gt`` folder gets
only ``README.md`` saying so, and no stage reads it.
"""

from __future__ import annotations

from pathlib import Path

import imageio.v3 as iio
import numpy as np

from gca.capture.cameras import CaptureError, rescale, transform_camera
from gca.capture.video import CaptureVideoConfig, median_plate, read_camera, read_frames, read_image, split_heldout
from gca.io import write_json
from gca.render.camera import Camera
from gca.scenes.store import TRAIN_VIEW, ViewData, frame_name, load_view, read_cameras, read_meta, view_dir

HELDOUT_VIEW = "heldout0"
NO_GROUND_TRUTH = ("# No ground truth\n\nThis scene is a capture (`kind: capture`): a real video has no ground-truth "
                   "trajectory, depth or law. Evaluation uses the held-out frames (`data/scenes/<scene>/views/heldout0`).\n")


def is_capture(scene_dir: str | Path) -> bool:
    """Whether a scene directory holds a capture (its meta.json says ``kind: capture``)."""
    return read_meta(scene_dir).get("kind") == "capture"


def capture_timing(fps: float, dt: float) -> tuple[int, float]:
    """(MPM substeps per video frame, realised frame rate [1/s]) for a video at ``fps`` simulated at ``dt`` [s]."""
    steps = max(1, int(round(1.0 / (fps * dt))))
    return steps, 1.0 / (steps * dt)


def write_capture(out_dir: Path, gt_dir: Path, scene_name: str, object_name: str, cfg: CaptureVideoConfig, dt: float,
                  sim_from_scan: np.ndarray, max_side: int = 0, root: str | Path = ".") -> dict:
    """Import a capture's video into ``out_dir`` (empty; module layout) and mark ``gt_dir`` as having none.

    Args:
        cfg: ``scenes.<name>.capture``; dt: the scene's MPM time step [s].
        sim_from_scan: [4, 4] similarity ``sim_from_world @ object_from_scan`` taking the camera from the scan's
            frame to the simulation frame.
        max_side: frames are downscaled so the longer side is at most this [px] (0: native); the camera follows.

    Returns:
        Summary metrics (frame counts, resolution, substeps, realised fps, plate source).
    """
    names, frames, native = read_frames(Path(root) / cfg.video, max_side)
    camera = read_camera(cfg.camera, cfg.frame, root)
    if (camera.width, camera.height) != native:
        if abs(camera.width / camera.height - native[0] / native[1]) > 0.01:
            raise CaptureError(f"{Path(root) / cfg.video}: frames are {native[0]}x{native[1]} but the camera "
                               f"({cfg.camera}) is {camera.width}x{camera.height} (another aspect ratio)")
    h, w = frames.shape[1:3]
    camera = transform_camera(rescale(camera, w, h), sim_from_scan)
    n_train = split_heldout(len(frames), cfg.heldout_fraction)
    substeps, fps = capture_timing(cfg.fps, dt)
    if cfg.plate:
        plate = read_image(Path(root) / cfg.plate, (w, h))
    else:
        plate = median_plate(frames)
    for view, chunk in ((TRAIN_VIEW, frames[:n_train]), (HELDOUT_VIEW, frames[n_train:])):
        folder = view_dir(out_dir, view) / "rgb"
        folder.mkdir(parents=True, exist_ok=True)
        for i, img in enumerate(chunk):
            iio.imwrite(folder / frame_name(i), img)
    iio.imwrite(view_dir(out_dir, TRAIN_VIEW) / "plate.png", plate)
    write_json(out_dir / "cameras.json", {TRAIN_VIEW: camera.to_dict(), HELDOUT_VIEW: camera.to_dict()})
    video_frames = list(range(1, n_train + 1))
    heldout = list(range(n_train + 1, len(frames) + 1))
    meta = {"scene": scene_name, "object": object_name, "kind": "capture", "dt": dt, "substeps": substeps,
            "frame_every": 1, "n_frames": len(frames), "video_frames": video_frames, "heldout_frames": heldout,
            "times": [f * substeps * dt for f in video_frames], "fps": fps, "fps_requested": cfg.fps,
            "duration_s": len(frames) * substeps * dt, "resolution": [w, h], "native_resolution": list(native),
            "source_frames": names, "plate": cfg.plate or "median of the frames",
            "views": {"train": [TRAIN_VIEW], "eval": []}}
    write_json(out_dir / "meta.json", meta)
    iio.imwrite(out_dir / "preview.gif", frames, duration=1000.0 / cfg.fps, loop=0)
    gt_dir.mkdir(parents=True, exist_ok=True)
    (gt_dir / "README.md").write_text(NO_GROUND_TRUTH)
    return {"n_frames": len(frames), "n_train_frames": n_train, "n_heldout_frames": len(heldout), "width": w,
            "height": h, "substeps": substeps, "fps": fps, "fps_error": abs(fps - cfg.fps) / cfg.fps,
            "plate_given": bool(cfg.plate)}


def load_heldout(scene_dir: str | Path) -> tuple[ViewData, list[int]]:
    """The held-out frames (a :class:`ViewData` of ``heldout0``) and their simulated-frame indices."""
    meta = read_meta(scene_dir)
    frames = list(meta.get("heldout_frames", []))
    if not frames:
        return ViewData(HELDOUT_VIEW, read_cameras(scene_dir)[TRAIN_VIEW], np.zeros((0, 1, 1, 3), np.float32)), []
    return load_view(scene_dir, HELDOUT_VIEW, {**meta, "video_frames": frames}), frames


def all_frames(scene_dir: str | Path) -> tuple[np.ndarray, list[int], Camera]:
    """The whole video [T, H, W, 3] float in [0, 1] (training then held-out), its simulated-frame indices and
    the camera (sim frame)."""
    train = load_view(scene_dir, TRAIN_VIEW)
    held, held_idx = load_heldout(scene_dir)
    rgb = np.concatenate([train.rgb, held.rgb]) if held_idx else train.rgb
    return rgb, list(read_meta(scene_dir)["video_frames"]) + held_idx, train.camera
