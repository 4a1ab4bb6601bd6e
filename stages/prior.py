"""DVC stage ``prior``: pretrain the neural prior M_0 of one material family (NCLaw-style).

    python stages/prior.py --family jelly --out models/prior/jelly.pt \
        --metrics metrics/prior/jelly.json --plots metrics/prior/jelly.png [--params params.yaml]
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

import torch
from tqdm import tqdm

from gca import stamp
from gca.pipeline import cli
from gca.io import write_json
from gca.laws.checkpoint import save_prior
from gca.pipeline.prior import prior_configs
from gca.pipeline.settings import Settings
from gca.pipeline.track import stage_run
from gca.train.prior import plot_prior, pretrain_prior


def parse_args(argv):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--family", required=True, help="a key of `prior.families:` in params.yaml (e.g. jelly)")
    for name, what in (("out", "prior checkpoint .pt"), ("metrics", "metrics .json"), ("plots", "loss and response plot .png")):
        ap.add_argument(f"--{name}", type=Path, required=True, help=what)
    cli.add_common(ap, device="cuda" if torch.cuda.is_available() else "cpu")
    return ap.parse_args(argv)


def summary_line(family: str, metrics: dict) -> str:
    """One line: held-out RMSE from the start to the end [cells], the response error [%] and the time. The start is
    the untrained net's RMSE where finite, else the warm start's (an untrained net can leave the grid: inf)."""
    rmse = metrics["heldout_rmse_cells"]
    start, label = rmse.get("untrained"), "untrained"
    if not (isinstance(start, (int, float)) and math.isfinite(start)) and rmse.get("warm") is not None:
        start, label = rmse["warm"], "warm start"
    ratio = start / rmse["trained"] if math.isfinite(start) and rmse["trained"] > 0 else float("nan")
    return (f"prior {family}: held-out RMSE {start:.3g} ({label}) -> {rmse['trained']:.3g} cells (x{ratio:.1f}), "
            f"response error {metrics['response_error_pct']['trained']['mean']:.1f} % in {metrics['seconds']['total']:.0f} s")


def main(argv=None) -> dict:
    args = parse_args(argv)
    settings = Settings.load(f"prior@{args.family}", args.params)
    preset, law_cfg, cfg = prior_configs(settings, args.family)
    device = args.device
    with stage_run("prior", settings.params, tags={"family": args.family}) as run, \
            tqdm(desc=f"prior {args.family}", unit="step", leave=False) as bar:
        def progress(phase, i, n, **values):
            bar.set_description(f"prior {args.family}: {phase}")
            bar.total, bar.n = n, i
            bar.set_postfix(values, refresh=True)
            if phase == "train" and (i % cfg.log_every == 0 or i == n):
                run.log_metrics({"train_loss_cells2": values["loss"]}, step=i)

        # an interrupted run (SIGTERM: a deadline, a 10-minute device command) goes on from its checkpoint
        checkpoint = args.out.with_name(args.out.name + ".checkpoint")
        keys = ("profile", "seed", "laws.neural", f"prior.families.{args.family}", "prior.train", "sim")  # dvc.yaml's
        stamp.guard_checkpoint(checkpoint, stamp.fingerprint(settings.params, keys, extra=[args.family, str(device)]))
        # SIGTERM in teacher forcing: checkpoint at the end of the step, then stop (before it: stop at once)
        result = pretrain_prior(preset, law_cfg, cfg, settings.seed, device, progress, checkpoint=checkpoint)
        save_prior(args.out, result.elasticity, result.plasticity, args.family,
                   metadata={"preset": preset, "seed": settings.seed, "profile": settings.profile,
                             "heldout_ratio": result.metrics["heldout_ratio"]})
        metrics = {"family": args.family, "device": device, **result.metrics}
        write_json(args.metrics, metrics)
        plot_prior(result, args.plots, args.family)
        run.log_metrics({k: v for k, v in metrics.items() if k not in ("data", "family", "device")})
        run.log_artifact(args.plots)
        stamp.clear_checkpoint(checkpoint)
    print(summary_line(args.family, metrics))
    return metrics


if __name__ == "__main__":
    sys.exit(cli.run(main))
