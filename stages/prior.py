"""DVC stage ``prior``: pretrain the neural prior M_0 of one material family (NCLaw-style).

    python stages/prior.py --family jelly --out models/prior/jelly.pt \
        --metrics metrics/prior/jelly.json --plots metrics/prior/jelly.png [--params params.yaml]
"""

from __future__ import annotations

import argparse
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
    print(f"prior {args.family}: held-out RMSE {metrics['heldout_rmse_cells']['untrained']:.3g} -> "
          f"{metrics['heldout_rmse_cells']['trained']:.3g} cells (x{metrics['heldout_ratio']:.1f}), response error "
          f"{metrics['response_error_pct']['trained']['mean']:.1f} % in {metrics['seconds']['total']:.0f} s")
    return metrics


if __name__ == "__main__":
    sys.exit(cli.run(main))
