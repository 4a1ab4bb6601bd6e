"""How reliable are the matches behind RDGA's global term? The ground-truth state, rendered the way
training renders (unlit), matched to the lit ground-truth frames of the training view.

    python benchmarks/match_quality.py --work /tmp/pp --scene duck \
        --config geometry=fundamental,ransac_px=1.0 --config geometry=homography,ransac_px=3.0

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

import numpy as np
import torch
import yaml
from tqdm import tqdm

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from gca.pipeline.settings import Settings  # noqa: E402
from gca.scenes.ground_truth import scene_cameras, simulate_scene  # noqa: E402
from gca.scenes.preprocess import load_prep  # noqa: E402
from gca.scenes.world import render_body  # noqa: E402
from gca.laws import material_from_preset  # noqa: E402
from gca.vision import MatchConfig  # noqa: E402
from gca.vision.matching import match_cached  # noqa: E402


def parse_config(text: str, base: MatchConfig) -> MatchConfig:
    """``"geometry=homography,ransac_px=3"`` -> a MatchConfig (fields parsed as YAML values)."""
    fields = dict(item.split("=", 1) for item in text.split(",") if item)
    return dataclasses.replace(base, **{k: yaml.safe_load(v) for k, v in fields.items()})


def distances(renders: list[np.ndarray], keypoints, cfg: MatchConfig) -> tuple[np.ndarray, list[int]]:
    """Per-match |p - q| [px] over all frames, and the match count of each frame."""
    d, counts = [], []
    for rgb, (kpts, desc) in zip(renders, keypoints):
        p, q = match_cached(rgb, kpts, desc, cfg)
        d.append(np.linalg.norm(p - q, axis=1))
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
    ap.add_argument("--json", type=Path)
    args = ap.parse_args(argv)
    settings = Settings.load(f"match_quality@{args.scene}", args.work / "params.yaml")
    scene, video, sim, base = settings.scene(args.scene), settings.video, settings.sim, settings.match
    body = settings.load_body(args.work / f"data/particles/{scene.object}.npz",
                           args.work / f"data/assets/{scene.object}/gaussians.ply", "cpu")
    preset = settings.material(scene.material)
    material = material_from_preset(preset, dt=scene.dt, n_particles=body.n_particles).to(dtype=body.x0.dtype)
    traj = simulate_scene(body, material, scene, video, sim, "cpu")
    camera = scene_cameras(scene, video.resolution)[args.view]
    frames = video.video_frames()
    _, _, keypoints = load_prep(args.work / f"data/prep/{args.scene}", len(frames))
    with torch.no_grad():
        renders = [render_body(body, traj.x[f], traj.F[f], camera, video.background)["rgb"].clamp(0, 1).numpy()
                   for f in tqdm(frames, desc="render", unit="frame")]
    rows = []
    for text in args.config or [""]:
        cfg = parse_config(text, base)
        d, counts = distances(renders, keypoints, cfg)
        rows.append({"config": text or "params.yaml", **summary(d, counts)})
    print(f"{'config':42s} {'matches/frame':>13s} {'no match':>8s} {'median':>7s} {'mean':>7s} {'p90':>7s} {'<=2px':>6s}")
    for r in rows:
        print(f"{r['config']:42s} {r['matches_per_frame']:13.1f} {r['frames_without']:8d} {r['median_px']:7.2f} "
              f"{r['mean_px']:7.2f} {r['p90_px']:7.2f} {r['within_2px']:6.2f}")
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1))
    return rows


if __name__ == "__main__":
    main(sys.argv[1:])
