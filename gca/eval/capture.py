"""Evaluation of a capture scene, which has no ground truth: the learned law's rollout re-rendered on the
held-out frames (the video's last part, never trained on), against the frames and the masks segmented from
them; a re-simulation video beside the input; and CPR's nearest classical law with its fitted parameters.

Metrics (held-out frames, the training camera):
  psnr_heldout, ssim_heldout      rendered frame vs the captured frame (background: the scene's plate)
  mask_iou_heldout                rendered alpha > 0.5 vs the preprocess stage's segmented mask [1]
  silhouette_cd_px_heldout        symmetric Chamfer distance between the two silhouettes' boundary pixels:
                                  mean of the two directed mean nearest-neighbour distances [px]
"""

from __future__ import annotations

from pathlib import Path

import imageio.v3 as iio
import numpy as np
import torch
from scipy.ndimage import binary_erosion
from scipy.spatial import cKDTree

from gca.align.cpr import CPR, CPRConfig, ELASTIC_PARAMS
from gca.eval.config import MetricsConfig
from gca.eval.evaluate import predict
from gca.eval.image import psnr, ssim
from gca.io import atomic_path
from gca.scenes.capture import all_frames
from gca.scenes.store import SceneDataError, TRAIN_VIEW, frame_substeps, load_plate, read_meta
from gca.scenes.world import Body, gaussians_at, render_gaussians
from gca.sim.cfl import CFLError
from gca.sim.rollout import SimulationDiverged

PLASTIC_NAMES = {"identity": "no plasticity (purely elastic)", "sigma": "fluid-like plasticity (volume kept)",
                 "von_mises": "von Mises plasticity", "drucker_prager": "Drucker-Prager (granular) plasticity"}


def boundary(mask: np.ndarray) -> np.ndarray:
    """Boundary pixel coordinates [K, 2] (row, col) of a bool mask [H, W]: the mask minus its erosion."""
    return np.argwhere(mask & ~binary_erosion(mask, border_value=0))


def silhouette_chamfer_px(pred: np.ndarray, true: np.ndarray) -> float:
    """Symmetric silhouette Chamfer distance [px] of two bool masks [H, W] (module docstring); nan when one
    silhouette is empty."""
    a, b = boundary(pred), boundary(true)
    if len(a) == 0 or len(b) == 0:
        return float("nan")
    return 0.5 * float(cKDTree(b).query(a)[0].mean() + cKDTree(a).query(b)[0].mean())


def mask_iou(pred: np.ndarray, true: np.ndarray) -> float:
    """Intersection over union of two bool masks [H, W] (1 when both are empty)."""
    union = np.logical_or(pred, true).sum()
    return float(np.logical_and(pred, true).sum() / union) if union else 1.0


def nearest_law(material, F_e: torch.Tensor, F_trial: torch.Tensor, cfg: CPRConfig, seed: int = 0) -> dict:
    """CPR's fit of its classical hypotheses to the learned law at one state (the most deformed frame).

    Args:
        material: the learned law (``.elasticity``: F [N,3,3] -> Kirchhoff tau [N,3,3] Pa, ``.plasticity``).
        F_e, F_trial: [N, 3, 3] elastic and trial deformation gradients of that frame.

    Returns:
        ``{"elastic": name, "plastic": name, "E_pa", "nu", "yield_stress_pa" | "friction_angle_deg",
        "weights": {e/<hyp>: w, p/<hyp>: w} (normalised per kind), "sentence": "behaves like ..."}``.
    """
    cpr = CPR(cfg, F_e.shape[0], seed)
    with torch.no_grad():
        _, _, info = cpr.residuals(material.elasticity, material.plasticity, F_e, F_trial)
    flat = CPR.log_dict(info, prefix="")
    out: dict = {"weights": {}}
    for kind, fits in (("e", info["elastic"]), ("p", info["plastic"])):
        total = sum(float(f.weight) for f in fits.values()) or 1.0
        out["weights"].update({f"{kind}/{n}": float(f.weight) / total for n, f in fits.items()})
    e, p = CPR.best(info["elastic"]), CPR.best(info["plastic"])
    out.update(elastic=e, plastic=p)
    parts = []
    if e and ELASTIC_PARAMS[e] == ("mu", "lam"):
        out["E_pa"], out["nu"] = flat[f"e/{e}/E"], flat[f"e/{e}/nu"]
        parts.append(f"E = {out['E_pa']:.3g} Pa, nu = {out['nu']:.2f}")
    elif e == "volume":
        out["lambda_pa"] = flat["e/volume/lam"]
        parts.append(f"bulk lambda = {out['lambda_pa']:.3g} Pa")
    if p == "von_mises":
        out["yield_stress_pa"] = flat.get("p/von_mises/sigma_y", float("nan"))
        parts.append(f"yield stress = {out['yield_stress_pa']:.3g} Pa")
    elif p == "drucker_prager":
        out["friction_angle_deg"] = flat["p/drucker_prager/phi"]
        parts.append(f"friction angle = {out['friction_angle_deg']:.3g} deg")
    elastic_name = {"corotated": "corotated", "stvk": "St. Venant-Kirchhoff", "volume": "volume-only (fluid-like)",
                    "sigma": "Hencky (log-strain)"}.get(e, str(e))
    out["sentence"] = (f"behaves like {elastic_name} elasticity with {PLASTIC_NAMES.get(p, str(p))}"
                       + (f": {', '.join(parts)}" if parts else "")
                       + f" (CPR weights: elastic {out['weights'].get(f'e/{e}', float('nan')):.2f}, "
                       f"plastic {out['weights'].get(f'p/{p}', float('nan')):.2f})")
    return out


def evaluate_capture(solver, material, body: Body, velocity: tuple[list, list], scene_dir: Path, prep_dir: Path,
                     background, out_dir: Path, cfg: MetricsConfig, cpr_cfg: CPRConfig, seed: int = 0) -> dict:
    """The metrics of one trained law on a capture (module docstring); writes ``resim.gif`` (input | re-simulation,
    every frame) and ``strip.png`` to ``out_dir``."""
    meta = read_meta(scene_dir)
    rgb, frames, camera = all_frames(scene_dir)
    n_train = len(meta["video_frames"])
    held_path = Path(prep_dir) / "heldout_masks.npy"
    if not held_path.is_file():
        raise SceneDataError(f"{held_path}: missing (the preprocess stage writes it for a capture scene)")
    held_masks = np.load(held_path)
    if len(held_masks) != len(frames) - n_train:
        raise SceneDataError(f"{held_path}: {len(held_masks)} masks for {len(frames) - n_train} held-out frames")
    metrics: dict = {"kind": "capture", "n_train_frames": n_train, "n_heldout_frames": len(frames) - n_train}
    try:
        traj, seconds = predict(solver, material, body, velocity, frames, frame_substeps(meta, solver.cfg.dt, scene_dir))
    except (SimulationDiverged, CFLError) as exc:
        return {**metrics, "status": "diverged", "message": str(exc)}
    plate = load_plate(scene_dir, TRAIN_VIEW)
    bg = torch.zeros(3, dtype=body.x0.dtype, device=body.x0.device)
    renders, alphas = [], []
    with torch.no_grad():
        for f in frames:
            means, covs = gaussians_at(body, traj.x[f], traj.F[f])
            out = render_gaussians(body, means, covs, body.colors, camera, bg)
            a = out["alpha"].cpu().numpy()
            back = plate if plate is not None else np.broadcast_to(np.asarray(background, np.float32), rgb.shape[1:])
            renders.append(np.clip(out["rgb"].cpu().numpy() + (1 - a[..., None]) * back, 0, 1))
            alphas.append(a)
    pred, alpha = np.stack(renders).astype(np.float32), np.stack(alphas)
    metrics.update(status="ok", rollout_seconds=seconds)
    if len(held_masks):
        p = torch.as_tensor(pred[n_train:]).permute(0, 3, 1, 2)
        r = torch.as_tensor(rgb[n_train:]).permute(0, 3, 1, 2)
        pm = alpha[n_train:] > 0.5
        metrics.update(
            psnr_heldout=float(psnr(p, r, max_val=cfg.image_max_val).mean()),
            ssim_heldout=float(ssim(p, r, max_val=cfg.image_max_val, window=cfg.ssim_window).mean()),
            mask_iou_heldout=float(np.mean([mask_iou(a, b) for a, b in zip(pm, held_masks)])),
            silhouette_cd_px_heldout=float(np.nanmean([silhouette_chamfer_px(a, b) for a, b in zip(pm, held_masks)])))
    k = int(torch.stack([(traj.F[f] - torch.eye(3, dtype=traj.F.dtype, device=traj.F.device)).norm(dim=(1, 2)).mean()
                         for f in frames]).argmax())
    if traj.F_trial is not None:
        metrics["nearest_law"] = nearest_law(material, traj.F[frames[k]], traj.F_trial[frames[k]], cpr_cfg, seed)
    out_dir.mkdir(parents=True, exist_ok=True)
    side = np.concatenate([rgb, pred], axis=2)  # input | re-simulation
    with atomic_path(out_dir / "resim.gif") as tmp:  # a stage stopped while it writes leaves no half-written file
        iio.imwrite(tmp, (side * 255 + 0.5).astype(np.uint8), extension=".gif", duration=1000.0 / float(meta["fps"]),
                    loop=0)
    idx = np.linspace(0, len(frames) - 1, min(4, len(frames))).round().astype(int)
    with atomic_path(out_dir / "strip.png") as tmp:
        iio.imwrite(tmp, (np.concatenate([np.concatenate(list(rgb[idx]), 1),
                                          np.concatenate(list(pred[idx]), 1)], 0) * 255 + 0.5).astype(np.uint8),
                    extension=".png")
    metrics.update(resim_gif=str(out_dir / "resim.gif"), strip_png=str(out_dir / "strip.png"))
    return metrics
