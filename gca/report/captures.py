"""One report page per capture scene (``reports/<profile>/captures/<scene>.md``), from its evaluate metrics only:
held-out PSNR/SSIM, mask IoU and silhouette Chamfer distance, CPR's nearest classical law, the launch
velocity, and the re-simulation video beside the input (copied next to the page)."""

from __future__ import annotations

import shutil
from pathlib import Path

from gca.io import read_json


def _fmt(value, digits: int = 3) -> str:
    return f"{value:.{digits}g}" if isinstance(value, (int, float)) else "n/a"


def capture_records(metrics_dir: str | Path) -> dict[str, list[dict]]:
    """``{scene: [record, ...]}`` of every capture record (``kind: capture``) under ``metrics_dir/<scene>/``."""
    out: dict[str, list[dict]] = {}
    for path in sorted(Path(metrics_dir).glob("*/*.json")):
        record = read_json(path)
        if isinstance(record, dict) and record.get("kind") == "capture":
            out.setdefault(path.parent.name, []).append({**record, "_path": str(path)})
    return out


def write_capture_pages(metrics_dir: str | Path, out_dir: str | Path) -> list[Path]:
    """Write ``out_dir/captures/<scene>.md`` (and its media) for each capture scene; returns the files written."""
    written = []
    for scene, records in capture_records(metrics_dir).items():
        folder = Path(out_dir) / "captures"
        folder.mkdir(parents=True, exist_ok=True)
        lines = [f"# Capture `{scene}`", "",
                 "Evaluated without ground truth: the learned law's rollout re-rendered on the held-out frames (the "
                 "video's last part, never trained on) from the training camera. Silhouette CD: mean of the two "
                 "directed mean nearest-neighbour distances between the silhouettes' boundary pixels [px].", "",
                 "| run | status | held-out frames | PSNR [dB] | SSIM | mask IoU | silhouette CD [px] | v0 [m/s] |",
                 "| --- | --- | --- | --- | --- | --- | --- | --- |"]
        for r in records:
            run = Path(r["_path"]).stem
            v0 = ", ".join(f"{v:.2f}" for v in r.get("velocity", {}).get("v0", []))
            lines.append(f"| {run} | {r.get('status')} | {r.get('n_heldout_frames')} | {_fmt(r.get('psnr_heldout'))} | "
                         f"{_fmt(r.get('ssim_heldout'))} | {_fmt(r.get('mask_iou_heldout'))} | "
                         f"{_fmt(r.get('silhouette_cd_px_heldout'))} | ({v0}) |")
        lines += ["", "## Nearest classical law (CPR)", ""]
        for r in records:
            law = r.get("nearest_law")
            run = Path(r["_path"]).stem
            if not law:
                lines.append(f"- {run}: no fit ({r.get('message', 'the rollout did not finish')})")
                continue
            lines.append(f"- {run}: {law['sentence']}")
            weights = ", ".join(f"{k} {v:.2f}" for k, v in sorted(law["weights"].items()))
            lines.append(f"  - hypothesis weights (normalised per kind): {weights}")
        lines += ["", "## Re-simulation", "", "Left: the input video; right: the learned law re-simulated and rendered.", ""]
        for r in records:
            run = Path(r["_path"]).stem
            for key, suffix in (("resim_gif", "resim.gif"), ("strip_png", "strip.png")):
                src = Path(r.get(key, ""))
                if src.is_file():
                    dst = folder / f"{scene}_{run}_{suffix}"
                    shutil.copyfile(src, dst)
                    written.append(dst)
                    lines.append(f"![{run} {suffix}]({dst.name})")
        page = folder / f"{scene}.md"
        page.write_text("\n".join(lines) + "\n")
        written.append(page)
    return written
