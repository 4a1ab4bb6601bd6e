"""The benchmark's nuisance statistics per scene, without training anything (issue 21; docs/benchmark.md).

Runs the observation chain of each scene (assets -> particles -> ground_truth -> preprocess -> nuisance)
at a profile in a work directory and prints one row per scene: mask IoU, depth Spearman, lighting
unexplained share, image-mean range. No method runs: the numbers describe the videos, so they may be
measured before any method is (the rule of issue 21), and on calibration scenes too.

    python benchmarks/nuisance_stats.py --work /tmp/nuis --profile ci --json benchmarks/nuisance_ci.json
    python benchmarks/nuisance_stats.py --work /tmp/nuis --profile ci --scenes ball cat --set video.timing=stress_30fps
    python benchmarks/nuisance_stats.py --work /tmp/nuis --profile ci --scenes ball --gifs reports/benchmark --gifs-only
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import yaml

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "stages"))
from gca.pipeline.grid import apply_overrides  # noqa: E402


def write_preview(work: Path, scene: str, out: Path, scale: int = 3) -> Path:
    """GIF of one scene's monocular view: lit frame | segmented mask vs the true alpha (grey: agree, red: false
    object, blue: missed) | estimated relative depth (dark = near). Evaluation-side: it reads the ground truth."""
    import imageio.v3 as iio
    import numpy as np

    from gca.scenes import load_view, truth

    view = load_view(work / "data/scenes" / scene, "train0")
    true = truth.load_alpha(work / "data/gt" / scene, "train0") > 0.5
    masks = np.load(work / "data/prep" / scene / "masks.npy")
    depth = np.load(work / "data/prep" / scene / "depth.npy")
    frames = []
    for rgb, m, a, d in zip(view.rgb, masks, true, depth):
        err = np.zeros(rgb.shape, np.uint8)
        err[m & a], err[m & ~a], err[~m & a] = (200, 200, 200), (230, 40, 40), (40, 80, 230)
        dn = (d - d.min()) / max(float(np.ptp(d)), 1e-9)
        panel = np.concatenate([(rgb * 255 + 0.5).astype(np.uint8), err,
                                (np.repeat(dn[..., None], 3, -1) * 255 + 0.5).astype(np.uint8)], 1)
        frames.append(np.kron(panel, np.ones((scale, scale, 1), np.uint8)))
    out.parent.mkdir(parents=True, exist_ok=True)
    iio.imwrite(out, np.stack(frames), duration=200, loop=0)
    return out


def depth_ablation(work: Path, scene: str, params: dict) -> dict:
    """Mean in-object Spearman of the simulated estimator on a scene with all components, none of the four
    non-monotone ones (benchmark 1.x), and each one switched off (the same seed as the ground_truth stage)."""
    import dataclasses

    import numpy as np

    from gca import config
    from gca.eval.nuisance import depth_spearman
    from gca.scenes import load_view, truth
    from gca.vision.depth import DepthConfig, SimulatedDepth

    base = config.build(DepthConfig, config.section(params, "vision.depth"), "vision.depth").simulated
    view = load_view(work / "data/scenes" / scene, "train0")
    inside = truth.load_alpha(work / "data/gt" / scene, "train0") > 0.5
    z = truth.load_true_depth(work / "data/gt" / scene, "train0")
    frames = (view.rgb * 255 + 0.5).astype(np.uint8)
    variants = {"all": {}, "none_of_4": dict(texture_copy=0.0, smooth_sigma_px=0.0, thin_flatten=0.0, flicker_tilt_std=0.0),
                "no_texture": dict(texture_copy=0.0), "no_smooth": dict(smooth_sigma_px=0.0),
                "no_thin": dict(thin_flatten=0.0), "no_flicker": dict(flicker_tilt_std=0.0)}
    seed = int(params["seed"])
    return {name: float(np.nanmean(depth_spearman(SimulatedDepth(dataclasses.replace(base, **kw), seed).estimate(
        frames, z, inside), z, inside))) for name, kw in variants.items()}


def main(argv=None) -> list[dict]:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--work", type=Path, required=True)
    ap.add_argument("--profile", default="ci")
    ap.add_argument("--scenes", nargs="*", help="default: every scene of params.yaml")
    ap.add_argument("--set", action="append", default=[], help="key=value params override (dotted key)")
    ap.add_argument("--json", type=Path, help="write the rows here")
    ap.add_argument("--gifs", type=Path, help="write a preview GIF per scene here (frame | mask errors | depth)")
    ap.add_argument("--gifs-only", action="store_true", help="only write the GIFs of an existing --work")
    ap.add_argument("--ablate-depth", action="store_true", help="with --gifs-only: print the depth components' ablation")
    args = ap.parse_args(argv)
    import assets, ground_truth, nuisance, particles, preprocess  # noqa: E401

    raw = apply_overrides(yaml.safe_load((ROOT / "params.yaml").read_text()), args.set)
    raw["profile"] = args.profile
    args.work.mkdir(parents=True, exist_ok=True)
    params = args.work / "params.yaml"
    if not args.gifs_only:
        params.write_text(yaml.safe_dump(raw, sort_keys=False))
    p = ["--params", str(params)]
    if args.gifs_only:
        from gca import config
        resolved = config.resolve(yaml.safe_load(params.read_text()), args.profile)
        out = []
        for scene in args.scenes or list(raw["scenes"]):
            if args.gifs:
                out.append(write_preview(args.work, scene, args.gifs / f"{scene}.gif"))
            if args.ablate_depth:
                print(scene, {k: round(v, 3) for k, v in depth_ablation(args.work, scene, resolved).items()})
        return out
    d = lambda *parts: str(args.work.joinpath(*parts))  # noqa: E731
    rows = []
    for scene in args.scenes or list(raw["scenes"]):
        obj = raw["scenes"][scene]["object"]
        if not (args.work / "data/particles" / f"{obj}.npz").is_file():
            assets.main(["--object", obj, "--out", d("data/assets", obj), "--metrics", d("m/assets", f"{obj}.json")] + p)
            particles.main(["--object", obj, "--assets", d("data/assets", obj), "--out", d("data/particles", f"{obj}.npz"),
                            "--metrics", d("m/particles", f"{obj}.json")] + p)
        gt = ground_truth.main(["--scene", scene, "--assets", d("data/assets", obj), "--particles",
                                d("data/particles", f"{obj}.npz"), "--out", d("data/scenes", scene), "--gt",
                                d("data/gt", scene), "--metrics", d("m/gt", f"{scene}.json")] + p)
        preprocess.main(["--scene", scene, "--scene-dir", d("data/scenes", scene), "--out", d("data/prep", scene),
                         "--metrics", d("m/prep", f"{scene}.json")] + p)
        stats = nuisance.main(["--scene", scene, "--scene-dir", d("data/scenes", scene), "--gt", d("data/gt", scene),
                               "--prep", d("data/prep", scene), "--out", d("metrics/nuisance", f"{scene}.json")] + p)
        meta = json.loads((args.work / "data/scenes" / scene / "meta.json").read_text())
        if args.gifs:
            write_preview(args.work, scene, args.gifs / f"{scene}.gif")
        rows.append({"scene": scene, "calibration": bool(raw["scenes"][scene].get("calibration", False)),
                     "profile": args.profile, "fps": meta["fps"], "frames": len(meta["video_frames"]),
                     "mask_iou_mean": stats["mask_iou_mean"], "mask_iou_min": stats["mask_iou_min"],
                     "depth_spearman_mean": stats["depth_spearman_mean"], "depth_spearman_min": stats["depth_spearman_min"],
                     "lighting_unexplained_share": stats["lighting_unexplained_share"],
                     "image_mean_range": gt["image_mean_range"], "overrides": args.set})
    print("| scene | fps | frames | mask IoU mean/min | depth Spearman mean/min | lighting unexplained | image-mean range |")
    print("| --- | --- | --- | --- | --- | --- | --- |")
    for r in rows:
        print(f"| {r['scene']}{' (calibration)' if r['calibration'] else ''} | {r['fps']:.1f} | {r['frames']} | "
              f"{r['mask_iou_mean']:.3f} / {r['mask_iou_min']:.3f} | {r['depth_spearman_mean']:.3f} / "
              f"{r['depth_spearman_min']:.3f} | {r['lighting_unexplained_share']:.3f} | {r['image_mean_range']:.3f} |")
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1) + "\n")
    return rows


if __name__ == "__main__":
    main(sys.argv[1:])
