"""End-to-end benchmark harness: one scene through every stage, timed, on the GPU (or CPU).

Runs the stage mains (assets -> particles -> prior -> ground_truth -> preprocess -> train ->
evaluate) for one scene at a profile, in a work directory, and writes one JSON per (scene, method)
under ``--out`` with the fields the performance issue asks for: device, versions, profile, scene,
method, n_particles, n_gaussians, train_seconds, rollout_seconds, peak_memory_gib, the wall time per
training phase (simulate, render_losses, backward, optimizer), per-iteration means, and the CD.
Ends with a short table.

    python benchmarks/harness.py --scene duck --methods gca neuma nclaw --profile paper \
        --set train.iterations=5 --set velocity.iterations=20 --out benchmarks/results

``--set key=value`` overrides a params entry (dotted key, YAML value) for this run only: the
numbers it produces state them, so a reduced-iteration timing is never mistaken for a full run.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from pathlib import Path

import torch
import yaml

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "stages"))
from gca.pipeline.grid import grid_params  # noqa: E402  (the same params restriction as the grid runner)


def make_params(scene: str, methods: list[str], profile: str, overrides: list[str], out: Path) -> dict:
    """params.yaml for one scene (its object and prior family only) at ``profile``, written to ``out``."""
    raw = grid_params(profile, [scene], methods, overrides)
    out.write_text(yaml.safe_dump(raw, sort_keys=False))
    return raw


def result_name(profile: str, scene: str, method: str, device: str, tag: str = "") -> str:
    """File name of one (scene, run) JSON under ``--out`` (``method``: the run's name, ``gca@seed1`` for a
    seed other than 0)."""
    return f"harness_{profile}_{scene}_{method}_{device}{tag}.json"


def versions() -> dict:
    import numpy
    import warp
    return {"python": platform.python_version(), "torch": torch.__version__, "warp": warp.__version__,
            "numpy": numpy.__version__, "cuda": torch.version.cuda}


def host_cpu(cpuinfo: Path = Path("/proc/cpuinfo")) -> str:
    """The host's CPU model and the cores this process may use ("<model>, <n> cores", as ``nproc``): a solo
    training's render + losses phase is host-bound (NOTES session 39: the same code 24 % slower on the ball on another
    lease of the same GPU kind), so a row names its host. ``platform.processor()`` where ``cpuinfo`` is unreadable or names no model."""
    try:
        model = next((line.split(":", 1)[1].strip() for line in cpuinfo.read_text().splitlines()
                      if line.lower().startswith("model name") and ":" in line), "")
    except OSError:
        model = ""
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()  # nproc's count
    return f"{model or platform.processor() or platform.machine()}, {cores} cores"


STAGES = ("assets", "particles", "prior", "ground_truth", "preprocess", "train", "evaluate")


def run_stages(raw: dict, scene: str, work: Path, params: Path, device: str, skip_prior: bool,
               reuse_data: bool = False, stages: tuple[str, ...] = STAGES) -> dict:
    """Run the ``stages`` of one scene in order in ``work``; returns each stage's wall time [s].

    A subset lets several processes share one lease: e.g. the prior in one work directory while others make
    their scenes' data (``assets particles ground_truth preprocess``), then ``train evaluate`` on both."""
    import assets, evaluate, ground_truth, particles, preprocess, prior, train  # noqa: E401
    spec = raw["scenes"][scene]
    obj, family = spec["object"], spec["prior"]
    d = lambda *p: str(work.joinpath(*p))  # noqa: E731
    p = ["--params", str(params)]
    seconds = {}

    def timed(name, fn, argv):
        if name not in stages:
            return
        if reuse_data and name in ("assets", "particles", "ground_truth", "preprocess") and (work / "m" / f"{name}.done").is_file():
            print(f"[harness] {name}: reused", flush=True)
            return
        t0 = time.perf_counter()
        fn(argv)
        seconds[name] = time.perf_counter() - t0
        (work / "m").mkdir(parents=True, exist_ok=True)
        (work / "m" / f"{name}.done").touch()
        print(f"[harness] {name}: {seconds[name]:.1f} s", flush=True)

    timed("assets", assets.main, ["--object", obj, "--out", d("assets", obj), "--metrics", d("m/assets.json")] + p)
    timed("particles", particles.main, ["--object", obj, "--assets", d("assets", obj), "--out", d("particles.npz"),
                                        "--metrics", d("m/particles.json")] + p)
    if "prior" in stages and not (skip_prior and (work / "prior" / f"{family}.pt").is_file()):
        argv = ["--family", family, "--out", d("prior", f"{family}.pt"), "--metrics", d("m/prior.json"),
                "--plots", d("m/prior.png")] + p
        try:
            timed("prior", prior.main, argv + ["--device", device])
        except RuntimeError as exc:  # keep the timing run going; the failure is printed, not hidden
            print(f"[harness] prior on {device} failed ({type(exc).__name__}: {exc}); retrying on cpu", flush=True)
            timed("prior", prior.main, argv + ["--device", "cpu"])
    timed("ground_truth", ground_truth.main, ["--scene", scene, "--assets", d("assets", obj), "--particles",
                                              d("particles.npz"), "--out", d("scene"), "--gt", d("gt"), "--metrics", d("m/gt.json"),
                                              "--device", device] + p)
    timed("preprocess", preprocess.main, ["--scene", scene, "--scene-dir", d("scene"), "--out", d("prep"),
                                          "--metrics", d("m/prep.json")] + p)
    common = ["--scene", scene, "--scene-dir", d("scene"), "--particles", d("particles.npz"), "--gaussians",
              d("assets", obj, "gaussians.ply"), "--prior-dir", d("prior"), "--device", device] + p
    timed("train", train.main, common + ["--prep", d("prep"), "--out", d("runs")])
    timed("evaluate", evaluate.main, common + ["--gt", d("gt"), "--runs", d("runs"), "--out", d("eval")])
    return seconds


def collect(raw: dict, scene: str, work: Path, device: str, stage_seconds: dict, overrides: list[str]) -> list[dict]:
    rows = []
    gt = json.loads((work / "m/gt.json").read_text())
    from gca.config import resolve
    from gca.pipeline.settings import Settings
    from gca.pipeline.train import seed_runs
    from gca.train.methods import get_method

    methods = [get_method(m) for m in raw["scenes"][scene]["methods"]]
    for _, seed, name in seed_runs(Settings(resolve(raw, raw["profile"])), methods):
        train = json.loads((work / "runs" / name / "train.json").read_text())
        metrics = json.loads((work / "eval" / f"{name}.json").read_text())
        history = json.loads((work / "runs" / name / "history.json").read_text())["history"]
        phases = {}
        for rec in history:
            for k, v in rec.items():
                if k.startswith("time/"):
                    phases[k[5:]] = phases.get(k[5:], 0.0) + v
        rows.append({
            "device": torch.cuda.get_device_name(0) if device == "cuda" else platform.processor() or "cpu",
            "host": host_cpu(), "versions": versions(), "profile": raw["profile"], "overrides": overrides, "scene": scene,
            "method": name, "seed": seed, "n_particles": gt["n_particles"], "n_gaussians": gt["n_gaussians"],
            "iterations": train["iterations"], "status": metrics["status"], "message": train.get("message", ""),
            "train_seconds": train["train_seconds"], "rollout_seconds": metrics.get("rollout_seconds"),
            "rollout_render_seconds": metrics.get("rollout_render_seconds"), "rejected_updates": len(train.get("rejected_updates", [])),
            "peak_memory_gib": train["peak_memory_gib"], "phase_seconds": phases,
            "render_backend": train.get("render_backend"),
            "seconds_per_iteration": train["train_seconds"] / max(train["iterations"], 1),
            "chamfer_mean": metrics.get("chamfer_mean"), "stage_seconds": stage_seconds,
            # per iteration: losses, gradient norm, horizon, sim_refine, phase times; and every rejected update
            "history": history, "rejected": train.get("rejected_updates", [])})
    return rows


def keep_stopped(work: Path, out: Path, tag: str) -> list[Path]:
    """A run stopped by SIGTERM: each training checkpoint's iterations so far (history with the per-iteration phase
    times, ``sim_refine``, rejected updates) as ``stopped_<run>[_tag].json`` in ``out``, so a run cut by a time limit
    still says where its time went."""
    written = []
    for ckpt in sorted((work / "runs").glob("*/checkpoint.pt")):
        state = torch.load(ckpt, map_location="cpu", weights_only=False)
        path = out / f"stopped_{ckpt.parent.name}{'_' + tag if tag else ''}.json"
        path.write_text(json.dumps({"run": ckpt.parent.name, "iterations_done": len(state.get("history", [])),
                                    "history": state.get("history", []), "rejected": state.get("rejected", []),
                                    "seconds": state.get("seconds")}, indent=1, default=float) + "\n")
        print(f"[harness] stopped: {path} ({len(state.get('history', []))} iterations)", flush=True)
        written.append(path)
    return written


SOLVER_SWITCHES = ("block_p2g", "agg_p2g", "agg_g2p", "vec4_p2g", "vec4_step", "vec4_g2p_adj", "hand_p2g_adj",
                   "hand_g2p_adj", "frame_mlp_grads", "fuse_frames", "fuse_analytic", "split_p2g", "keep_grid")
SOLVER_NUMBERS = ("stash_mib", "mlp_stash_mib")  # MPMSolver's numeric path settings (>= 0; 0: that stash off)


def set_solver_switches(items: list[str]) -> None:
    """Set ``MPMSolver`` class switches (``name=yaml_value``; the kernel paths are implementation choices, not
    params: same results to float rounding) for every solver this process makes."""
    from gca.sim.solver import MPMSolver

    for item in items:
        name, _, value = item.partition("=")
        parsed = yaml.safe_load(value) if value else "missing"
        if name in SOLVER_NUMBERS and isinstance(parsed, str):  # YAML 1.1 reads 1e9 as a string
            try:
                parsed = float(parsed)
            except ValueError:
                pass
        number = name in SOLVER_NUMBERS and isinstance(parsed, (int, float)) and not isinstance(parsed, bool) \
            and parsed >= 0
        if not number and (name not in SOLVER_SWITCHES or not (parsed is None or isinstance(parsed, bool))):
            raise SystemExit(f"harness.py: --solver {item!r}: expected one of {', '.join(SOLVER_SWITCHES)}"
                             f"=true|false|null, or {', '.join(SOLVER_NUMBERS)}=a number >= 0")
        setattr(MPMSolver, name, parsed)
        print(f"[harness] MPMSolver.{name} = {getattr(MPMSolver, name)!r}", flush=True)


def main(argv=None) -> list[dict]:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", default="duck")
    ap.add_argument("--methods", nargs="+", default=["gca", "neuma", "nclaw"])
    ap.add_argument("--profile", default="paper")
    ap.add_argument("--set", dest="overrides", action="append", default=[], help="dotted.key=yaml_value")
    ap.add_argument("--work", type=Path, default=Path("/tmp/gca-harness"))
    ap.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "results")
    ap.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    ap.add_argument("--reuse-prior", action="store_true", help="keep a prior already in the work directory")
    ap.add_argument("--reuse-data", action="store_true", help="keep assets/particles/scene/prep already made there")
    ap.add_argument("--tag", default="", help="suffix of the JSON names (side-by-side runs in one --out)")
    ap.add_argument("--stages", nargs="+", choices=STAGES, default=list(STAGES),
                    help="run only these stages (in pipeline order); the table needs train and evaluate")
    ap.add_argument("--solver", action="append", default=[], metavar="SWITCH=yaml_value",
                    help="an MPMSolver implementation switch for this run's solvers (A/B of a kernel path: "
                         f"{', '.join(SOLVER_SWITCHES)}; e.g. block_p2g=false)")
    args = ap.parse_args(argv)
    set_solver_switches(args.solver)
    args.work.mkdir(parents=True, exist_ok=True)
    args.out.mkdir(parents=True, exist_ok=True)
    os.environ.setdefault("MLFLOW_TRACKING_URI", f"sqlite:///{args.work / 'mlflow.db'}")
    params = args.work / "params.yaml"
    raw = make_params(args.scene, args.methods, args.profile, args.overrides, params)
    from gca import stop

    stop.install()  # SIGTERM (`timeout`, the device tool's limit), GCA_STOP_AT or GCA_STOP_FILE: training
    # checkpoints, then what ran is kept (packed under MPS, bundles stop it with GCA_STOP_AT: no signal, NOTES s42)
    try:
        stage_seconds = run_stages(raw, args.scene, args.work, params, args.device, args.reuse_prior, args.reuse_data,
                                   tuple(args.stages))
    except stop.Terminated:
        stop.quiesce()
        keep_stopped(args.work, args.out, args.tag)
        raise
    if "evaluate" not in args.stages:
        print(f"[harness] stages {args.stages} done in {args.work} (no table without evaluate)", flush=True)
        return []
    rows = collect(raw, args.scene, args.work, args.device, stage_seconds, args.overrides)
    for row in rows:
        (args.out / result_name(row["profile"], row["scene"], row["method"], args.device, args.tag)).write_text(json.dumps(row, indent=2, sort_keys=True) + "\n")
    print(f"\n{'method':<12}{'P':>8}{'G':>8}{'it':>4}{'s/it':>8}{'sim':>8}{'render':>8}{'bwd':>8}"
          f"{'rollout s':>10}{'peak GiB':>9}{'CD':>9}")
    for r in rows:
        ph, it = r["phase_seconds"], max(r["iterations"], 1)
        print(f"{r['method']:<12}{r['n_particles']:>8}{r['n_gaussians']:>8}{r['iterations']:>4}"
              f"{r['seconds_per_iteration']:>8.2f}{ph.get('simulate', 0) / it:>8.2f}{ph.get('render_losses', 0) / it:>8.2f}"
              f"{ph.get('backward', 0) / it:>8.2f}{r['rollout_seconds'] or float('nan'):>10.2f}"
              f"{r['peak_memory_gib']:>9.2f}{r['chamfer_mean'] or float('nan'):>9.4f}")
    return rows


if __name__ == "__main__":
    main(sys.argv[1:])
