"""gca.sim's MPM solver side by side with PhysGaussian's warp MPM solver on the same job (issue 20).

The job: a fixed-corotated jelly block (no plasticity), ``--steps`` steps of ``--dt``, float32, on
the unit cube with ``n_grid`` cells per axis; particles placed by ``bench_sim.block`` (uniform random
in a centred cube, about 8 per cell, just above the floor wall), same particles, volumes and masses
(rho * vol) for both solvers, E = 1e5 Pa, nu = 0.3, rho = 1000 kg/m^3, gravity (0, -9.8, 0) m/s^2.
So that the elastic law matters (a block in free fall has F = I and no stress), every particle
starts with the affine velocity ``v = (0, -v_drop, 0) + A (x - c)`` and APIC matrix ``C = A``,
``A = strain_rate * diag(1, -2, 1) + spin * [[0, -1, 0], [1, 0, 0], [0, 0, 0]]`` (a volume-preserving
squash with a spin about z; c = the block's centre).

For each ``particles:n_grid`` size it runs, in one process on one device:

- ``ours``: ``MPMSolver.step`` + ``Material(CorotatedElasticity, IdentityPlasticity)`` (fused warp law where warp runs, ``gca.laws.fused.corotated_tau``),
  launched step by step;
- ``ours_graph``: the same through ``gca.sim.graph`` frames of ``--steps-per-frame`` steps (CUDA
  graphs on a GPU; on the CPU the eager twin); ``ours_graph_generic``: its frames through the generic step (law, then
  transfers); ``ours_graph_block``: its forward P2G summed per thread block in shared memory first
  (``MPMSolver.block_p2g`` True; off by default: slower on the H100, session 32); ``ours_graph_agg``: its scatters'
  atomics aggregated per warp (``MPMSolver.agg_p2g`` True; off: slower at 30k on the H200, session 46);
  ``ours_graph_v4``: its fused frames on the interleaved (mv, m) grid, one 16-byte vector atomic a node
  (``MPMSolver.vec4_p2g`` True; on CUDA by default since session 50, so ``ours_graph`` takes it there too), and
  ``ours_graph_scalar`` the control: ``vec4_p2g`` False, the scalar atomics of the default before session 50;
- ``theirs``: ``MPM_Simulator_WARP.p2g2p`` exactly as published (it wraps every kernel in
  ``wp.ScopedTimer(synchronize=True)``, i.e. five host syncs per step);
- ``theirs_nosync``: the same ``p2g2p`` with ``wp.ScopedTimer`` temporarily replaced by a no-op while
  their steps run (their code unchanged; no host syncs);
- ``theirs_graph`` (CUDA only): one ``theirs_nosync`` step captured as a warp CUDA graph, replayed.

Timing: one warm-up run of ``--steps`` steps (kernel compile/load, graph capture) from the initial
state, then ``--repeats`` timed runs from the initial state (best kept), synchronised before and after
(torch and warp). Reported: ms/step and the speed-up of ``ours_graph`` over the fastest of theirs.

Trajectories: after ``--steps`` steps, ``|x_ours - x_theirs|`` per particle (max and mean) divided by
the block's side, and the mean displacement over the run (same units) for scale; also
ours vs ours_graph and theirs vs theirs_nosync (expected ~0).

Where the two models differ (not the same discretisation, so trajectories agree to a tolerance, not
bitwise):
- transfer: ours is MLS-MPM (force ``-dt vol 4/dx^2 tau (x_i - x_p) w_ip``, ``F <- (I + dt C') F``);
  theirs is APIC with the weight gradient (force ``-dt vol tau grad w_ip``, ``F <- (I + dt sum v_i
  grad w_ip^T) F``). Both: quadratic B-splines, APIC momentum ``m (v + C (x_i - x_p))``, C from
  ``4/dx^2 sum w v (x_i - x_p)^T``, v = mv/m on nodes with m > 1e-15 plus dt g.
- stress: the same Kirchhoff fixed-corotated ``2 mu (F - R) F^T + lam J (J - 1) I`` with
  mu, lam from (E, nu); theirs in a warp kernel (wp.svd3, then symmetrised), ours in warp kernels (the SVD kernel and one stress kernel, session 13; torch before).
- walls: theirs ``add_bounding_box`` (nodes with index < 3 or >= n_grid - 3 lose the outward normal
  velocity); ours ``boundary="slip"``, ``bound=3`` (index < 3 or > n_grid - 3): the same condition,
  except that the top wall regions start one node further out on ours. Our grid is padded by one node
  and positions are clamped to [dx/2, 1 - dx/2]; theirs has nodes 0..n_grid-1 and no clamp. The
  default job does not reach the walls.
- their ``load_initial_data_from_torch`` passes ``device`` positionally into ``clone`` (so it only
  works on cuda:0); the benchmark makes the same calls (initialize, import x/v/C from torch, volumes,
  F_trial = I, set_parameters_dict, finalize_mu_lam, add_bounding_box) with ``device=`` named.

Needs their code in ``.physgaussian/`` (ignored): ``bash benchmarks/physgaussian/prepare.sh``.

Usage::

    python benchmarks/bench_physgaussian.py --device cuda               # 30000:32 and 100000:64, 200 steps
    python benchmarks/bench_physgaussian.py --device cpu --sizes 2000:16 --steps 20 --repeats 1   # CPU check

GPU (device tool, after the warp staging; carry the ignored folder ``.physgaussian``)::

    PYTHONPATH=. python benchmarks/bench_physgaussian.py --device cuda --sizes 30000:32 100000:64 \
        --steps 200 --repeats 2 --json $OUT/physgaussian_cuda.json

Measured on the H200 (session 50, ``--order lattice --repeats 3``): ~180 s with a cold warp kernel cache (the NVRTC
compiles of both solvers' modules dominate); ``ours_graph_v4`` 2.09x their best at 30k / 32^3 and 2.69x at 100k / 64^3
(``benchmarks/results/vec4_s50/``). Any variant that fails is recorded under ``errors`` in the JSON and the others
still run.

CPU check (2 shared cores; 2000 particles on 16^3, dt 2e-4): after 20 steps ours vs theirs differ by
max 2.3e-5 / mean 4.2e-6 block sides (mean displacement 2.7e-2); after 200 steps by max 1.0e-3 /
mean 5.4e-4 (mean displacement 0.10), i.e. ~0.5% of the motion. CPU timings are not the target
(our torch law dominates there).
Prints a table and writes JSON (``--json``, default benchmarks/results/physgaussian_<device>.json).
"""

from __future__ import annotations

import argparse
import contextlib
import importlib
import json
import platform
import sys
import time
from pathlib import Path

import torch
import warp as wp

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_sim import RHO, block  # noqa: E402

from gca.laws.base import Material  # noqa: E402
from gca.laws.elastic import CorotatedElasticity  # noqa: E402
from gca.laws.plastic import IdentityPlasticity  # noqa: E402
from gca.sim import MPMSolver, SimConfig  # noqa: E402
from gca.sim.graph import graphed_frame  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
THEIRS = ROOT / ".physgaussian"
E, NU = 1e5, 0.3  # Young's modulus [Pa], Poisson ratio [-]
GRAVITY = (0.0, -9.8, 0.0)  # [m/s^2]
BOUND = 3  # wall thickness [cells]: PhysGaussian's add_bounding_box uses padding = 3


def load_theirs():
    """PhysGaussian's ``mpm_solver_warp`` module from ``.physgaussian/`` (prepared by prepare.sh)."""
    if not (THEIRS / "mpm_solver_warp.py").exists():
        raise SystemExit(f"{THEIRS} is missing: run benchmarks/physgaussian/prepare.sh (copies and patches "
                         "PhysGaussian's warp MPM solver from a mirror of github.com/XPandora/PhysGaussian)")
    if str(THEIRS) not in sys.path:
        sys.path.insert(0, str(THEIRS))
    return importlib.import_module("mpm_solver_warp")


def their_commit() -> str:
    path = THEIRS / "COMMIT"
    return path.read_text().strip() if path.exists() else "unknown"


class _NoTimer:
    def __init__(self, *args, **kwargs):
        pass

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        return False


@contextlib.contextmanager
def _their_timers_off(mod):
    """``wp.ScopedTimer`` is a no-op inside (their p2g2p's only host syncs); restored on exit. (Swapping
    their module's ``wp`` for a proxy instead crashed their bounding-box kernel on the CPU.)"""
    saved = wp.ScopedTimer
    wp.ScopedTimer = _NoTimer
    try:
        yield
    finally:
        wp.ScopedTimer = saved


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)
    wp.synchronize_device(wp.device_from_torch(device))


def initial_state(n: int, n_grid: int, dt: float, device: torch.device, v_drop: float, strain_rate: float,
                  spin: float, order: str = "random"):
    """Shared initial state: (cfg, x, v, C, F, vol, mass, side) in float32 on ``device``."""
    cfg = SimConfig(n_grid=n_grid, dt=dt, gravity=GRAVITY, bound=BOUND, boundary="slip", dtype="float32",
                    max_refine=1)
    x, vol, mass = block(n, cfg, device, order=order)
    n = x.shape[0]
    A = strain_rate * torch.diag(torch.tensor([1.0, -2.0, 1.0])) + spin * torch.tensor(
        [[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 0.0]])
    A = A.to(x)
    c = x.mean(0)
    v = (x - c) @ A.T + torch.tensor([0.0, -v_drop, 0.0]).to(x)
    C = A.expand(n, 3, 3).contiguous()
    F = torch.eye(3).to(x).expand(n, 3, 3).contiguous()
    side = float((x.max(0).values - x.min(0).values).mean())
    return cfg, x, v, C, F, vol, mass, side


# -- ours ----------------------------------------------------------------------------------------


def run_ours(state, steps: int, device, graph: bool, steps_per_frame: int, solver_cache: dict, fuse: bool = True,
             block: bool | None = None, agg: bool | None = None, vec4: bool | None = None):
    """Final positions after ``steps`` steps, and a closure that re-runs them (for timing). ``fuse``: graphed frames
    take the fused analytic step (``MPMSolver.step_fused``, the default); False: the generic step (law, then
    transfers; the default before session 30). ``block``: ``MPMSolver.block_p2g``, ``agg``: ``MPMSolver.agg_p2g``
    ``vec4``: ``MPMSolver.vec4_p2g`` (None: their defaults: block and agg off, vec4 on CUDA)."""
    cfg, x0, v0, C0, F0, vol, mass, _ = state
    key = f"solver_{fuse}_{block}_{agg}_{vec4}"
    if key not in solver_cache:
        solver_cache[key] = MPMSolver(cfg, device)
        solver_cache[key].fuse_analytic = fuse
        if block is not None:  # None: the solver's own default (None there would mean "on CUDA")
            solver_cache[key].block_p2g = block
        if agg is not None:
            solver_cache[key].agg_p2g = agg
        if vec4 is not None:
            solver_cache[key].vec4_p2g = vec4
        solver_cache[key + "_material"] = Material(CorotatedElasticity(E, NU), IdentityPlasticity(), RHO).to(
            device=device, dtype=cfg.torch_dtype)
    solver, material = solver_cache[key], solver_cache[key + "_material"]
    runner = None
    if graph:
        if steps % steps_per_frame:
            raise SystemExit(f"--steps {steps} must be a multiple of --steps-per-frame {steps_per_frame}")
        runner = solver.frame_graphs(material, steps_per_frame, x0.shape[0])
        runner.bind(vol, mass)

    def go():
        with torch.no_grad():
            x, v, C, F = x0.clone(), v0.clone(), C0.clone(), F0.clone()
            if runner is not None:
                for _ in range(steps // steps_per_frame):
                    x, v, C, F, _ = graphed_frame(runner, x, v, C, F)
            else:
                for _ in range(steps):
                    x, v, C, Ftr = solver.step(x, v, C, F, material.stress(F), vol, mass)
                    F = material.project(Ftr)
            return x

    info = {"captured": bool(runner is not None and runner.capture)}
    return go, info


# -- theirs --------------------------------------------------------------------------------------


def build_theirs(mod, state, device: torch.device):
    """An ``MPM_Simulator_WARP`` holding the shared initial state (their API, ``device=`` named)."""
    cfg, x0, v0, C0, _, vol, _, _ = state
    dev = str(wp.device_from_torch(device))
    n = x0.shape[0]
    sim = mod.MPM_Simulator_WARP(n, n_grid=cfg.n_grid, grid_lim=1.0, device=dev)
    sim.import_particle_x_from_torch(x0.contiguous(), device=dev)  # clones (their default)
    sim.import_particle_v_from_torch(v0.contiguous(), device=dev)
    sim.import_particle_C_from_torch(C0.contiguous(), device=dev)
    sim.mpm_state.particle_vol = wp.from_numpy(vol.detach().cpu().numpy(), dtype=float, device=dev)
    wp.launch(mod.set_mat33_to_identity, dim=n, inputs=[sim.mpm_state.particle_F_trial], device=dev)
    sim.set_parameters_dict({"material": "jelly", "E": E, "nu": NU, "density": RHO, "g": list(GRAVITY),
                             "grid_lim": 1.0, "n_grid": cfg.n_grid}, device=dev)
    sim.finalize_mu_lam(device=dev)
    sim.add_bounding_box()
    return sim, dev


def run_theirs(mod, state, steps: int, device, variant: str):
    dt = state[0].dt

    def go():
        sim, dev = build_theirs(mod, state, device)  # fresh state (the timed part is the steps only)
        _sync(device)
        t0 = time.perf_counter()
        if variant == "theirs":
            for i in range(steps):
                sim.p2g2p(i, dt, device=dev)
        elif variant == "theirs_nosync":
            with _their_timers_off(mod):
                for i in range(steps):
                    sim.p2g2p(i, dt, device=dev)
        else:  # theirs_graph: capture one step (no syncs inside), replay it
            with _their_timers_off(mod):
                sim.p2g2p(0, dt, device=dev)  # module loads before capture
                sim2, _ = build_theirs(mod, state, device)  # fresh state; kernels are loaded now
                with wp.ScopedCapture(device=dev) as capture:
                    sim2.p2g2p(0, dt, device=dev)
                sim = sim2  # the capture did not execute the step; the state is still the initial one
                _sync(device)
                t0 = time.perf_counter()
                for _ in range(steps):
                    wp.capture_launch(capture.graph)
        _sync(device)
        seconds = time.perf_counter() - t0
        x = wp.to_torch(sim.mpm_state.particle_x).to(device).clone()
        return x, seconds

    return go


# -- driver --------------------------------------------------------------------------------------


def measure(mod, n, n_grid, args, device) -> dict:
    state = initial_state(n, n_grid, args.dt, device, args.v_drop, args.strain_rate, args.spin, args.order)
    x0, side = state[1], state[7]
    row = {"particles": int(x0.shape[0]), "n_grid": n_grid, "steps": args.steps, "dt": args.dt, "block_side": side,
           "ms_per_step": {}, "final_x": {}}
    cache: dict = {}
    variants = ["ours", "ours_graph_generic", "ours_graph_block", "ours_graph_agg", "ours_graph_scalar",
                "ours_graph_v4", "ours_graph", "theirs", "theirs_nosync"] + \
        (["theirs_graph"] if device.type == "cuda" else [])
    finals = {}
    for name in variants:
        try:
            if name.startswith("ours"):
                go, info = run_ours(state, args.steps, device, name != "ours", args.steps_per_frame, cache,
                                    fuse=name != "ours_graph_generic",
                                    block=True if name == "ours_graph_block" else None,
                                    agg=True if name == "ours_graph_agg" else None,
                                    vec4={"ours_graph_v4": True, "ours_graph_scalar": False}.get(name))
                finals[name] = go()  # warm-up + trajectory
                best = float("inf")
                for _ in range(args.repeats):
                    _sync(device)
                    t0 = time.perf_counter()
                    go()
                    _sync(device)
                    best = min(best, time.perf_counter() - t0)
                if name != "ours":
                    row[f"{name}_captured"] = info["captured"]
            else:
                go = run_theirs(mod, state, args.steps, device, name)
                finals[name], _ = go()  # warm-up + trajectory
                best = min(go()[1] for _ in range(args.repeats))
            row["ms_per_step"][name] = 1e3 * best / args.steps
        except Exception as err:  # one variant failing must not lose the others
            row.setdefault("errors", {})[name] = f"{type(err).__name__}: {err}"
        print(f"  {n}:{n_grid} {name}: {row['ms_per_step'].get(name, float('nan')):.3f} ms/step", flush=True)

    def diff(a, b):
        if a not in finals or b not in finals:
            return None
        d = (finals[a] - finals[b]).norm(dim=1) / side
        return {"max": float(d.max()), "mean": float(d.mean())}

    row["trajectory"] = {"ours_vs_theirs": diff("ours", "theirs"), "ours_vs_ours_graph": diff("ours", "ours_graph"),
                         "ours_graph_vs_ours_graph_generic": diff("ours_graph", "ours_graph_generic"),
                         "ours_graph_vs_ours_graph_block": diff("ours_graph", "ours_graph_block"),
                         "ours_graph_vs_ours_graph_agg": diff("ours_graph", "ours_graph_agg"),
                         "ours_graph_vs_ours_graph_v4": diff("ours_graph", "ours_graph_v4"),
                         "ours_graph_vs_ours_graph_scalar": diff("ours_graph", "ours_graph_scalar"),
                         "theirs_vs_theirs_nosync": diff("theirs", "theirs_nosync"),
                         "theirs_vs_theirs_graph": diff("theirs", "theirs_graph")}
    if "ours" in finals:
        row["trajectory"]["mean_displacement"] = float((finals["ours"] - x0).norm(dim=1).mean() / side)
        row["trajectory"]["finite"] = bool(all(torch.isfinite(t).all() for t in finals.values()))
    ms = row["ms_per_step"]
    theirs_best = min((ms[k] for k in ms if k.startswith("theirs")), default=None)
    if theirs_best and "ours_graph" in ms:
        row["speedup_ours_graph_vs_best_theirs"] = theirs_best / ms["ours_graph"]
    ours_best = min((k for k in ms if k.startswith("ours_graph")), key=ms.get, default=None)  # any option of ours
    if theirs_best and ours_best:
        row["best_ours"] = ours_best
        row["speedup_best_ours_vs_best_theirs"] = theirs_best / ms[ours_best]
    if "theirs" in ms and "ours_graph" in ms:
        row["speedup_ours_graph_vs_theirs_published"] = ms["theirs"] / ms["ours_graph"]
    del row["final_x"]
    return row


def _table(results: dict) -> str:
    names = ["ours", "ours_graph_generic", "ours_graph_block", "ours_graph_agg", "ours_graph_scalar", "ours_graph_v4",
             "ours_graph", "theirs", "theirs_nosync", "theirs_graph"]
    lines = ["| particles | grid | " + " | ".join(f"{k} ms/step" for k in names)
             + " | speed-up (ours_graph / best theirs) | max / mean |dx| ours vs theirs (block sides) | mean displacement |",
             "|" + " --- |" * (len(names) + 5)]
    for r in results["runs"]:
        ms = r["ms_per_step"]
        t = r["trajectory"]
        ovt = t["ours_vs_theirs"]
        lines.append(f"| {r['particles']} | {r['n_grid']}^3 | "
                     + " | ".join(f"{ms[k]:.3f}" if k in ms else "-" for k in names)
                     + f" | {r.get('speedup_ours_graph_vs_best_theirs', float('nan')):.2f}x"
                     + (f" | {ovt['max']:.2e} / {ovt['mean']:.2e}" if ovt else " | -")
                     + f" | {t.get('mean_displacement', float('nan')):.2e} |")
    return "\n".join(lines)


def _parse(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    p.add_argument("--sizes", nargs="+", default=["30000:32", "100000:64"], help="particles:n_grid pairs")
    p.add_argument("--order", default="random", choices=["random", "lattice"],
                   help="particles at random in the block, or on a lattice in meshgrid order (as objects are sampled)")
    p.add_argument("--steps", type=int, default=200)
    p.add_argument("--repeats", type=int, default=2, help="timed runs per variant after one warm-up (best kept)")
    p.add_argument("--dt", type=float, default=2e-4, help="time step [s]")
    p.add_argument("--steps-per-frame", type=int, default=10, help="steps per CUDA-graph frame (ours_graph)")
    p.add_argument("--v-drop", type=float, default=0.5, help="initial downward speed [m/s]")
    p.add_argument("--strain-rate", type=float, default=10.0, help="initial squash rate [1/s]")
    p.add_argument("--spin", type=float, default=5.0, help="initial spin about z [rad/s]")
    p.add_argument("--json", default=None, help="output (default benchmarks/results/physgaussian_<device>.json)")
    return p.parse_args(argv)


def main(argv=None) -> dict:
    args = _parse(argv)
    mod = load_theirs()
    wp.config.quiet = True
    wp.init()
    device = torch.device(args.device)
    if device.type == "cuda" and device.index is None:
        device = torch.device("cuda", torch.cuda.current_device())
    results = {"device": torch.cuda.get_device_name(device) if device.type == "cuda" else platform.processor() or "cpu",
               "warp": wp.__version__, "torch": torch.__version__, "physgaussian_commit": their_commit(),
               "job": {"law": "fixed corotated", "E": E, "nu": NU, "rho": RHO, "gravity": GRAVITY, "bound": BOUND,
                       "dt": args.dt, "steps": args.steps, "v_drop": args.v_drop, "strain_rate": args.strain_rate,
                       "spin": args.spin, "dtype": "float32", "order": args.order},
               "runs": []}
    t_all = time.perf_counter()
    for spec in args.sizes:
        n, n_grid = (int(s) for s in spec.split(":"))
        results["runs"].append(measure(mod, n, n_grid, args, device))
    results["wall_seconds"] = time.perf_counter() - t_all
    print(_table(results))
    print(f"total {results['wall_seconds']:.1f} s")
    out = Path(args.json or ROOT / f"benchmarks/results/physgaussian_{device.type}.json")
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(results, indent=2))
    print(f"wrote {out}")
    return results


if __name__ == "__main__":
    main()
