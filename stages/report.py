"""DVC stage ``report``: regenerate the paper's tables and figures from the metrics JSON only.

    python stages/report.py --metrics metrics --out reports --summary metrics/report.json --params params.yaml
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from gca import config
from gca.pipeline import cli
from gca.pipeline import schema
from gca.io import write_json
from gca.report import ReportConfig, build_reports, summary
from gca.report.runs import load_runs
from gca.pipeline.track import stage_run


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--metrics", type=Path, default=Path("metrics"), help="metrics folder of `evaluate`")
    parser.add_argument("--out", type=Path, default=Path("reports"), help="reports folder (replaced)")
    parser.add_argument("--summary", type=Path, default=Path("metrics/report.json"), help="summary metrics JSON")
    parser.add_argument("--media", type=Path, nargs="*", default=[], help="GIF/PNG folders to include (demos)")
    parser.add_argument("--nuisance", type=Path, help="the nuisance stage's folder (metrics/nuisance)")
    cli.add_common(parser)
    return parser.parse_args(argv)


def main(argv: list[str] | None = None) -> list[Path]:
    args = parse_args(argv)
    params = schema.load("report", args.params)
    cfg = config.build(ReportConfig, config.section(params, "report"), "report")
    with stage_run("report", params, table="all") as run:
        written = build_reports(args.metrics, args.out, cfg, media_dirs=[m for m in args.media if m.is_dir()],
                                benchmark_version=str(params.get("benchmark", {}).get("version", "")),
                                nuisance_dir=args.nuisance)
        headline = summary(load_runs(args.metrics), cfg)
        write_json(args.summary, headline)
        run.log_metrics({"n_records": headline["n_records"],
                         "table1_average_cd": {m: a["mean_cd"] for m, a in headline["table1_average_cd"].items()}})
        run.log_artifact(args.out)
    print(f"report: wrote {len(written)} files to {args.out}")
    return written


if __name__ == "__main__":
    sys.exit(cli.run(main))
