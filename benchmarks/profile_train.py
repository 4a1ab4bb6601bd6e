"""Where one training iteration spends its time: cProfile (Python, host syncs included) and the
CUDA kernel totals of torch.profiler, on a work directory the harness has filled (a script).

Usage (after ``benchmarks/harness.py --work /tmp/h ...`` has run the scene's stages)::

    python benchmarks/profile_train.py --work /tmp/h --scene duck --method gca --iterations 2

Runs ``--warmup`` untimed iterations (graph capture, JIT), then ``--iterations`` under cProfile and
prints the ``--top`` functions by cumulative time, then one more under torch.profiler and prints
the top kernels by CUDA time. Details go to ``--out`` when given.
"""

from __future__ import annotations

import argparse
import contextlib
import cProfile
import io
import pstats
import sys
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]


def build(work: Path, scene: str, method_name: str, device: str):
    """(solver, law, data, objective, cfg, opt) of ``method`` (seed 0) as the train stage builds them
    (:func:`gca.pipeline.train.train_job`)."""
    from gca import config
    from gca.pipeline.settings import Settings
    from gca.train import state
    from gca.train.methods import get_method
    from gca.pipeline.train import SceneInputs, read_velocity, train_job
    params = Settings(config.load(path=work / "params.yaml", via_dvc=False))
    spec = params.params["scenes"][scene]
    inputs = SceneInputs(scene_dir=work / "scene", prep_dir=work / "prep", particles=work / "particles.npz",
                         gaussians=work / "assets" / spec["object"] / "gaussians.ply",
                         prior=work / "prior" / f"{spec['prior']}.pt")
    job = train_job(params, scene, get_method(method_name), inputs, read_velocity(work / "runs" / "velocity.json"),
                    device)
    opt, _ = state.make_optimizer(job.law, job.cfg)
    return job.solver, job.law, job.data, job.objective, job.cfg, opt


def kernel_rows(events) -> str:
    """Every profiled event's own device time as TSV (``name, self_us, calls, us_per_call``; the whole names, which
    the printed table cuts at 60 characters), the largest first: the kernels' table a bundle reads whole (session 51
    lost the top of it to a reply's length)."""
    def own(e) -> float:
        return float(getattr(e, "self_device_time_total", None) or getattr(e, "self_cuda_time_total", 0.0) or 0.0)
    rows = sorted((e for e in events if own(e) > 0), key=own, reverse=True)
    lines = ["name\tself_us\tcalls\tus_per_call"]
    lines += [f"{e.key}\t{own(e):.1f}\t{e.count}\t{own(e) / max(e.count, 1):.2f}" for e in rows]
    return "\n".join(lines) + "\n"


@contextlib.contextmanager
def labelled(objective, loop):
    """Name the iteration's parts in the torch.profiler trace (``phase/...`` ranges): the rollout, the frames'
    render, CPR, the frames' losses (with the sweep: its adjoints are queued inside) and the backward (the sweep's
    tail), by wrapping those functions while the block runs."""
    from torch.profiler import record_function

    def wrap(owner, name, label):
        original = getattr(owner, name)

        def wrapped(*a, **k):
            with record_function(f"phase/{label}"):
                return original(*a, **k)
        setattr(owner, name, wrapped)
        return lambda: setattr(owner, name, original)
    from gca.sim.rollout import ReverseSweep
    undo = [wrap(loop, "simulate", "simulate"), wrap(objective, "_render_frames", "render"),
            wrap(objective, "prior_gradient", "cpr"), wrap(objective, "_frame_losses", "frame_losses"),
            wrap(torch.Tensor, "backward", "backward"), wrap(ReverseSweep, "finish", "backward")]
    try:
        yield
    finally:
        for u in reversed(undo):
            u()


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--work", type=Path, default=Path("/tmp/gca-harness"))
    ap.add_argument("--scene", default="duck")
    ap.add_argument("--method", default="gca")
    ap.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    ap.add_argument("--warmup", type=int, default=1)
    ap.add_argument("--iterations", type=int, default=2)
    ap.add_argument("--horizon", type=int, default=0, help="video frames supervised (0: all)")
    ap.add_argument("--top", type=int, default=35)
    ap.add_argument("--torch-profile", action="store_true", help="also torch.profiler off CUDA (on CUDA always)")
    ap.add_argument("--out", type=Path, default=None)
    ap.add_argument("--solver", action="append", default=[], metavar="SWITCH=yaml_value",
                    help="an MPMSolver switch, as harness.py --solver (session 51: the profile of a kernel path)")
    args = ap.parse_args(argv)
    if args.solver:
        sys.path.insert(0, str(ROOT / "benchmarks"))
        from harness import set_solver_switches
        set_solver_switches(args.solver)
    from gca.train import loop
    solver, law, data, objective, cfg, opt = build(args.work, args.scene, args.method, args.device)
    n_video = args.horizon or len(data.video_frames)

    def step():
        with loop.run_settings(cfg, law):  # as train() runs it (matmul precision, MLP kernel)
            record = loop._gradient(solver, law, data, objective, cfg, n_video)
        opt.step()
        return record

    for _ in range(args.warmup):
        step()
    prof = cProfile.Profile()
    records = []
    prof.enable()
    for _ in range(args.iterations):
        records.append(step())
    prof.disable()
    text = io.StringIO()
    pstats.Stats(prof, stream=text).sort_stats("cumulative").print_stats(args.top)
    phases = {k: sum(r[k] for r in records) / len(records) for k in records[0] if k.startswith("time/")}
    print("per iteration [s]:", {k[5:]: round(v, 3) for k, v in phases.items()})
    print(text.getvalue()[-9000:])
    if args.device == "cuda" or args.torch_profile:
        from torch.profiler import ProfilerActivity, profile
        activities = [ProfilerActivity.CPU] + ([ProfilerActivity.CUDA] if args.device == "cuda" else [])
        with profile(activities=activities) as tp, labelled(objective, loop):
            step()
        events = tp.key_averages()
        table = events.table(sort_by="self_cuda_time_total" if args.device == "cuda" else "self_cpu_time_total", row_limit=args.top, max_name_column_width=60)
        ranges = events.table(sort_by="cuda_time_total" if args.device == "cuda" else "cpu_time_total", row_limit=args.top, max_name_column_width=60)
        print(table[-8000:])
        print(ranges[-4000:])
        if args.out:
            args.out.mkdir(parents=True, exist_ok=True)
            (args.out / f"profile_train_{args.method}_cuda.txt").write_text(table + "\n\n" + ranges)
            (args.out / f"profile_train_{args.method}_kernels.tsv").write_text(kernel_rows(events))
    if args.out:
        args.out.mkdir(parents=True, exist_ok=True)
        (args.out / f"profile_train_{args.method}_cprofile.txt").write_text(text.getvalue())


if __name__ == "__main__":
    sys.path.insert(0, str(ROOT))
    main(sys.argv[1:])
