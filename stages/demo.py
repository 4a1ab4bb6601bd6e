"""DVC stages ``demo`` and ``demo_capture``: generalization demos (a learned law on a new shape; two learned laws
colliding; a capture's learned law on its object placed and thrown anew).

    python stages/demo.py --runs runs --data data --prior-dir models/prior --out metrics/demo \
        --metrics metrics/demo.json --params params.yaml
    python stages/demo.py --capture example_capture --runs runs --data data --prior-dir models/prior \
        --out metrics/demo_capture/example_capture --metrics metrics/demo_capture/example_capture.json

With ``--capture <scene>`` (``demo_capture@<scene>``) only that capture's new-scene demo runs
(``demo.captures.<scene>``): ``<out>/{demo.gif, strip.png}`` and the metrics JSON.

Writes ``<out>/new_shape/{demo.gif, strip.png}``, ``<out>/interaction/{demo.gif, strip.png}`` and the
metrics JSON. A missing trained law falls back to its scene's prior with a warning
(``demo.missing_law: prior``) or stops the stage (``error``).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from gca.config import section
from gca.pipeline import cli
from gca.io import atomic_path, write_json
from gca.pipeline.demo import DemoInputs, capture_demo, demo_config, interaction_demo, new_shape_demo
from gca.pipeline.settings import Settings
from gca.pipeline.track import stage_run
from gca.pipeline.train import default_device


def parse_args(argv):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    for name, what in (("runs", "the train stage's runs/ root (runs/<scene>/<method>/law.pt)"),
                       ("data", "the data/ root (data/particles, data/assets)"), ("prior-dir", "models/prior"),
                       ("out", "metrics/demo (GIFs and strips)"), ("metrics", "metrics .json")):
        ap.add_argument(f"--{name}", type=Path, required=True, help=what)
    ap.add_argument("--capture", help="a capture scene (key of demo.captures): run only its new-scene demo")
    cli.add_common(ap, device=default_device())
    return ap.parse_args(argv)


def main(argv=None) -> dict:
    args = parse_args(argv)
    settings = Settings.load(f"demo_capture@{args.capture}" if args.capture else "demo", args.params)
    cfg = demo_config(settings)
    inputs = DemoInputs(args.runs, args.data, args.prior_dir, args.device)
    # the one key of `video` the demos read (DVC's view holds only what dvc.yaml declares: video.background)
    background = tuple(float(c) for c in section(settings.params, "video.background"))
    if args.capture:
        return _capture(settings, cfg, inputs, args, background)
    with stage_run("demo", settings.params) as run:
        with atomic_path(args.out, is_dir=True) as tmp:
            out = {}
            with cli.phase("demo", f"new shape ({cfg.n_frames} frames)"):
                out["new_shape"] = new_shape_demo(settings, cfg, inputs, tmp / "new_shape", background)
            with cli.phase("demo", f"interaction ({cfg.n_frames} frames)"):
                out["interaction"] = interaction_demo(settings, cfg, inputs, tmp / "interaction", background)
        for demo in out.values():
            _relocate(demo, tmp, args.out)
        _record(run, out, settings, args)
    for name in ("new_shape", "interaction"):
        print(f"demo {name}: {out[name]['status']} -> {args.out / name}")
    return out


def _capture(settings, cfg, inputs, args, background) -> dict:
    """``demo_capture@<scene>``: one capture's new-scene demo."""
    with stage_run("demo_capture", settings.params, scene=args.capture) as run:
        with atomic_path(args.out, is_dir=True) as tmp:
            with cli.phase("demo", f"capture {args.capture} thrown anew ({cfg.n_frames} frames)"):
                out = capture_demo(settings, args.capture, cfg, inputs, tmp, background)
        _relocate(out, tmp, args.out)
        _record(run, out, settings, args)
    print(f"demo capture {args.capture}: {out['status']} -> {args.out}")
    return out


def _relocate(demo: dict, tmp: Path, final: Path) -> None:
    """Point a demo's media paths at the final folder ``final``, not the temporary one ``tmp`` they were written in."""
    for key in ("gif", "strip_png"):
        if key in demo:
            demo[key] = str(final / Path(demo[key]).relative_to(tmp))


def _record(run, out: dict, settings, args) -> None:
    """The demo's metrics JSON and its MLflow metrics and artifacts."""
    out.update(profile=settings.profile, seed=settings.seed)
    write_json(args.metrics, out)
    run.log_metrics(out)
    run.log_artifact(args.out)


if __name__ == "__main__":
    sys.exit(cli.run(main))
