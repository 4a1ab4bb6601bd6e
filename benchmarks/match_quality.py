"""How reliable are the matches behind RDGA's global term? The ground-truth state, rendered the way
training renders (unlit), matched to the lit ground-truth frames of the training view (inside the rendered
mask and the frame's preprocessed mask, as training does).

    python benchmarks/match_quality.py --work /tmp/pp --scene calib_torus \
        --config backend=sift --config backend=sift,geometry=fundamental --config backend=flow,flow_image=gray

``--warp dx,dy,deg,scale`` moves every render (and its mask) by that similarity about the object's centre
before matching, a stand-in for a wrong simulated state: a correct match then has ``q = W^-1 p`` and the
distances are measured from there.

``--work`` is a pipeline (or ``gca/pipeline/grid.py``) work directory holding the scene's
``data/assets``, ``data/particles`` and ``data/prep``. The render shows the *exact* ground-truth
state, so a correct match has ``|p - q| ~ 0``: the distances measure the matcher alone (lighting
interference, repeated texture, the RANSAC model), i.e. the noise floor of the global term.
Prints one row per matching config; ``--json`` writes them.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
from pathlib import Path

import cv2
import numpy as np
import torch
import yaml
from tqdm import tqdm

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from gca.pipeline.settings import Settings  # noqa: E402
from gca.scenes.config import scene_video  # noqa: E402
from gca.scenes.ground_truth import scene_cameras, simulate_scene  # noqa: E402
from gca.scenes.preprocess import load_prep  # noqa: E402
from gca.scenes.world import render_body  # noqa: E402
from gca.laws import material_from_preset  # noqa: E402
from gca.vision import MatchConfig  # noqa: E402
from gca.scenes.store import load_view  # noqa: E402
from gca.vision.matching import match_frame  # noqa: E402


def parse_config(text: str, base: MatchConfig) -> MatchConfig:
    """``"geometry=homography,ransac_px=3"`` -> a MatchConfig (fields parsed as YAML values)."""
    fields = dict(item.split("=", 1) for item in text.split(",") if item)
    return dataclasses.replace(base, **{k: yaml.safe_load(v) for k, v in fields.items()})


def similarity(renders: list[tuple[np.ndarray, np.ndarray]], warp: tuple[float, float, float, float]) -> np.ndarray:
    """The 2x3 similarity (rotation ``deg`` and ``scale`` about the first render's mask centroid, then the shift
    ``dx, dy`` [px]) that ``--warp dx,dy,deg,scale`` applies to the renders."""
    ys, xs = np.nonzero(renders[0][1])
    m = cv2.getRotationMatrix2D((float(xs.mean()), float(ys.mean())), warp[2], warp[3])
    m[:, 2] += warp[:2]
    return m


def warped(renders: list[tuple[np.ndarray, np.ndarray]], m: np.ndarray, background) -> list:
    """Each (RGB, mask) moved by the 2x3 map ``m`` (the background fills what it uncovers)."""
    size = renders[0][1].shape[::-1]
    return [(cv2.warpAffine(rgb, m, size, borderValue=tuple(float(b) for b in background)),
             cv2.warpAffine(inside.astype(np.uint8), m, size, flags=cv2.INTER_NEAREST) > 0) for rgb, inside in renders]


def distances(renders: list[tuple[np.ndarray, np.ndarray]], frames: np.ndarray, masks: np.ndarray, keypoints,
              cfg: MatchConfig, m: np.ndarray | None = None) -> tuple[np.ndarray, list[int]]:
    """Per-match |p - q| [px] over all frames, and the match count of each frame.

    renders: per frame (RGB [H, W, 3] in [0, 1], rendered mask [H, W] bool); frames: the video [T, H, W, 3] in
    [0, 1]; masks: the video's masks [T, H, W]; keypoints: the video's cached SIFT keypoints per frame; m: the
    2x3 map the renders were moved by (a correct match then has q = m^-1 p), or None."""
    inverse = None if m is None else cv2.invertAffineTransform(m)
    d, counts = [], []
    for (rgb, inside), frame, mask, (kpts, desc) in zip(renders, frames, masks, keypoints):
        p, q = match_frame(rgb, frame, kpts, desc, cfg, inside, mask)  # float frames: rounded to uint8 there
        truth = p if inverse is None else p @ inverse[:, :2].T + inverse[:, 2]
        d.append(np.linalg.norm(truth - q, axis=1))
        counts.append(len(p))
    return np.concatenate(d) if d else np.zeros(0), counts


def summary(d: np.ndarray, counts: list[int]) -> dict:
    """Match counts and the distance distribution [px]."""
    stat = (lambda f: float(f(d)) if len(d) else float("nan"))
    return {"matches_per_frame": float(np.mean(counts)), "frames_without": int(sum(c == 0 for c in counts)),
            "median_px": stat(np.median), "mean_px": stat(np.mean), "p90_px": stat(lambda x: np.percentile(x, 90)),
            "within_2px": stat(lambda x: np.mean(x <= 2.0))}


def main(argv=None) -> list[dict]:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--work", type=Path, required=True)
    ap.add_argument("--scene", required=True)
    ap.add_argument("--view", default="train0")
    ap.add_argument("--config", action="append", default=[], help="comma-separated MatchConfig fields")
    ap.add_argument("--warp", default="", help="dx,dy,deg,scale: move the renders by this similarity first")
    ap.add_argument("--json", type=Path)
    args = ap.parse_args(argv)
    settings = Settings.load(f"match_quality@{args.scene}", args.work / "params.yaml")
    scene, sim, base = settings.scene(args.scene), settings.sim, settings.match
    video = scene_video(settings.video, scene)  # the scene's own frames (fps > 0: from its dt and duration)
    body = settings.load_body(args.work / f"data/particles/{scene.object}.npz",
                           args.work / f"data/assets/{scene.object}/gaussians.ply", "cpu")
    preset = settings.material(scene.material)
    material = material_from_preset(preset, dt=scene.dt, n_particles=body.n_particles).to(dtype=body.x0.dtype)
    traj = simulate_scene(body, material, scene, video, sim, "cpu")
    camera = scene_cameras(scene, video.resolution)[args.view]
    frames = video.video_frames()
    _, masks, keypoints = load_prep(args.work / f"data/prep/{args.scene}", len(frames))
    video_rgb = load_view(args.work / f"data/scenes/{args.scene}", args.view).rgb
    threshold = settings.rdga.alpha_threshold
    renders = []
    with torch.no_grad():
        for f in tqdm(frames, desc="render", unit="frame"):
            out = render_body(body, traj.x[f], traj.F[f], camera, video.background)
            renders.append((out["rgb"].clamp(0, 1).numpy(), out["alpha"].numpy() >= threshold))
    m = None
    if args.warp:
        m = similarity(renders, tuple(float(v) for v in args.warp.split(",")))
        renders = warped(renders, m, video.background)
    rows = []
    for text in args.config or [""]:
        cfg = parse_config(text, base)
        d, counts = distances(renders, video_rgb, masks, keypoints, cfg, m)
        rows.append({"config": text or "params.yaml", "warp": args.warp, **summary(d, counts)})
    print(f"{'config':42s} {'matches/frame':>13s} {'no match':>8s} {'median':>7s} {'mean':>7s} {'p90':>7s} {'<=2px':>6s}")
    for r in rows:
        print(f"{r['config']:42s} {r['matches_per_frame']:13.1f} {r['frames_without']:8d} {r['median_px']:7.2f} "
              f"{r['mean_px']:7.2f} {r['p90_px']:7.2f} {r['within_2px']:6.2f}")
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1))
    return rows


if __name__ == "__main__":
    main(sys.argv[1:])
