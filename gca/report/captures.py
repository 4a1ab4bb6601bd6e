"""One report page per capture scene (``reports/<profile>/captures/<scene>.md``), from its evaluate metrics and its
new-scene demo only: held-out PSNR/SSIM, mask IoU and silhouette Chamfer distance, CPR's nearest classical law
in words, the launch velocity, the re-simulation video beside the input and the new-scene demo (both copied next
to the page).

The ``report`` stage writes them with every table (``dvc repro report``: the whole grid). For one capture without
the synthetic grid, after ``dvc repro evaluate@<scene> demo_capture@<scene>``::

    python -m gca.report.captures --metrics metrics/eval --demos metrics/demo_capture --out reports/ci

writes only ``reports/ci/captures/`` (the next ``report`` run rewrites the folder as a whole).
"""

from __future__ import annotations

import argparse
import shutil
import sys
from pathlib import Path

from gca.io import read_json


def _fmt(value, digits: int = 3) -> str:
    return f"{value:.{digits}g}" if isinstance(value, (int, float)) else "n/a"


def _vec(values) -> str:
    return "(" + ", ".join(f"{v:.2f}" for v in values or []) + ")"


def capture_records(metrics_dir: str | Path) -> dict[str, list[dict]]:
    """``{scene: [record, ...]}`` of every capture record (``kind: capture``) under ``metrics_dir/<scene>/``."""
    out: dict[str, list[dict]] = {}
    for path in sorted(Path(metrics_dir).glob("*/*.json")):
        record = read_json(path)
        if isinstance(record, dict) and record.get("kind") == "capture":
            out.setdefault(path.parent.name, []).append({**record, "_path": str(path)})
    return out


def _copy(src, folder: Path, name: str, written: list[Path]) -> Path | None:
    src = Path(src or "")
    if not src.is_file():
        return None
    dst = folder / name
    shutil.copyfile(src, dst)
    written.append(dst)
    return dst


def _demo_lines(scene: str, demos_dir: Path | None, folder: Path, written: list[Path]) -> list[str]:
    """The page's new-scene demo section, from ``demos_dir/<scene>.json`` (stage ``demo_capture@<scene>``)."""
    lines = ["", "## New-scene demo", ""]
    path = Path(demos_dir) / f"{scene}.json" if demos_dir is not None else None
    if path is None or not path.is_file():
        return lines + [f"Not run: `dvc repro demo_capture@{scene}` makes it (params `demo.captures.{scene}`)."]
    d = read_json(path)
    lines.append(f"The law learned on this capture ({d.get('method')}, `{d.get('law_source')}`) drives "
                 f"`{d.get('object')}` raised {_fmt(d.get('lift_m'))} m, turned {_vec(d.get('rotation_deg'))} deg "
                 f"(about x, y, z) and launched with v0 = {_vec(d.get('v0'))} m/s, w0 = {_vec(d.get('w0'))} rad/s: a "
                 "throw the video never showed, filmed by the capture's camera over its empty scene.")
    lines.append("")
    if d.get("status") != "ok":
        return lines + [f"Status: {d.get('status')} ({d.get('message', '')})"]
    lines.append(f"{d.get('frames')} frames at {_fmt(d.get('fps'))} fps ({_fmt(d.get('seconds_simulated'))} s), state "
                 f"finite: {d.get('finite')}, centre-of-mass drop {_fmt(d.get('com_drop_m'))} m, largest principal "
                 f"strain {_fmt(d.get('max_strain'))}.")
    lines.append("")
    for key, suffix, what in (("gif", "demo.gif", "animation"), ("strip_png", "demo_strip.png", "frame strip")):
        dst = _copy(d.get(key), folder, f"{scene}_{suffix}", written)
        if dst is not None:
            lines += [f"[{what}]({dst.name})", "", f"![new-scene demo {what}]({dst.name})", ""]
    return lines


def write_capture_pages(metrics_dir: str | Path, out_dir: str | Path, demos_dir: str | Path | None = None) -> list[Path]:
    """Write ``out_dir/captures/<scene>.md`` (and its media) for each capture scene; returns the files written,
    each page after its media.

    Args:
        metrics_dir: ``metrics/eval`` (the evaluate stage's records).
        out_dir: ``reports/<profile>``.
        demos_dir: ``metrics/demo_capture`` (the demo_capture stages' folders and JSON), or None.
    """
    written: list[Path] = []
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
            lines.append(f"| {run} | {r.get('status')} | {r.get('n_heldout_frames')} | {_fmt(r.get('psnr_heldout'))} | "
                         f"{_fmt(r.get('ssim_heldout'))} | {_fmt(r.get('mask_iou_heldout'))} | "
                         f"{_fmt(r.get('silhouette_cd_px_heldout'))} | {_vec(r.get('velocity', {}).get('v0'))} |")
        lines += ["", "## Nearest classical law (CPR)", ""]
        for r in records:
            law = r.get("nearest_law")
            run = Path(r["_path"]).stem
            if not law:
                lines.append(f"- {run}: no fit ({r.get('message', 'the rollout did not finish')})")
                continue
            lines.append(f"- {run}: the learned law {law['sentence']}")
            weights = ", ".join(f"{k} {v:.2f}" for k, v in sorted(law["weights"].items()))
            lines.append(f"  - hypothesis weights (normalised per kind): {weights}")
        lines += ["", "## Re-simulation", "", "Left: the input video; right: the learned law re-simulated and rendered "
                  "(training frames, then the held-out ones).", ""]
        for r in records:
            run = Path(r["_path"]).stem
            for key, suffix, what in (("resim_gif", "resim.gif", "input | re-simulation video"),
                                      ("strip_png", "strip.png", "frame strip")):
                dst = _copy(r.get(key), folder, f"{scene}_{run}_{suffix}", written)
                if dst is not None:
                    lines += [f"[{run}: {what}]({dst.name})", "", f"![{run} {what}]({dst.name})", ""]
        lines += _demo_lines(scene, None if demos_dir is None else Path(demos_dir), folder, written)
        page = folder / f"{scene}.md"
        page.write_text("\n".join(lines) + "\n")
        written.append(page)
    return written


def main(argv=None) -> list[Path]:
    ap = argparse.ArgumentParser(description="write reports/<profile>/captures/<scene>.md from the capture stages' metrics")
    ap.add_argument("--metrics", type=Path, default=Path("metrics/eval"), help="the evaluate stages' folder")
    ap.add_argument("--demos", type=Path, default=Path("metrics/demo_capture"), help="the demo_capture stages' folder")
    ap.add_argument("--out", type=Path, required=True, help="reports/<profile>")
    args = ap.parse_args(argv)
    written = write_capture_pages(args.metrics, args.out, args.demos)
    pages = [p for p in written if p.suffix == ".md"]
    if not pages:
        raise SystemExit(f"{args.metrics}: no capture records (kind: capture); run `dvc repro evaluate@<scene>` first")
    print("\n".join(f"wrote {p}" for p in pages))
    return written


if __name__ == "__main__":
    main(sys.argv[1:])
