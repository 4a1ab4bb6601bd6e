"""benchmarks/bench_sim.py, bench_p2g.py, bench_law_precision.py, bench_mlp.py and the packed drivers
(bench_runs_packed.py, bench_mlp_packed.py) on the CPU: the particle orders of the benchmark block, every P2G kernel
layout timed on each order, the law's FP32 / TF32 bench, P processes started at one signal (smoke runs of what the
H100 bundles run)."""

import importlib.util
import json
import time
from pathlib import Path

import pytest
import torch

from gca.sim import SimConfig

ROOT = Path(__file__).resolve().parents[1]


def _load(name: str):
    spec = importlib.util.spec_from_file_location(name, ROOT / "benchmarks" / f"{name}.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_block_orders_fill_the_same_cube():
    bench = _load("bench_sim")
    cfg = SimConfig(n_grid=16, dt=1e-4)
    x_r, vol_r, _ = bench.block(1000, cfg, torch.device("cpu"), order="random")
    x_l, vol_l, _ = bench.block(1000, cfg, torch.device("cpu"), order="lattice")
    assert x_r.shape == (1000, 3) and x_l.shape == (1000, 3)  # 10^3: the lattice keeps round(n^(1/3))^3
    spacing = float(x_r.max() - x_r.min()) / 10  # the lattice has 10 points per side
    assert torch.allclose(x_r.min(0).values, x_l.min(0).values, atol=spacing)
    assert torch.allclose(x_r.max(0).values, x_l.max(0).values, atol=spacing)
    assert torch.isclose(vol_r.sum(), vol_l.sum())  # the same block volume
    assert torch.all(x_l[1:, 2] != x_l[:-1, 2])  # meshgrid order: z runs fastest
    assert len(torch.unique(x_l, dim=0)) == 1000


def test_bench_p2g_times_every_order_and_kernel_on_the_cpu():
    rows = _load("bench_p2g").main(["--device", "cpu", "--sizes", "500:16", "--iters", "1", "--repeats", "1"])
    assert [r["order"] for r in rows] == ["random", "lattice", "cell", "morton", "ball64", "ball64_sub", "ball64_shuffle",
                                          "ball12", "ball12_sub", "duck"]
    assert rows[1]["particles"] == 512  # 8^3
    assert abs(rows[9]["particles"] - 500) < 60
    assert rows[7]["particles"] == rows[8]["particles"] and abs(rows[7]["particles"] - 500) < 60
    assert abs(rows[4]["particles"] - 500) < 60  # a lattice ball of ~500 at ~64 per cell
    assert rows[4]["particles"] == rows[5]["particles"] == rows[6]["particles"]  # the same ball reordered
    assert all(r[k] > 0 for r in rows for k in ("p2g_us", "p2g_agg_us", "p2g_indirect_us", "p2g_interleaved_us",
                                                "p2g_nodes_us", "p2g_block_us", "g2p_us", "g2p_adj_us",
                                                "g2p_agg_adj_us", "p2g_v4_us", "g2p4_adj_us"))
    assert all(r["p2g_v4_dev"] == 0.0 for r in rows)  # on a CPU the interleaved grid is p2g's bitwise


def test_the_duck_order_has_the_duck_s_density_and_warp_spread():
    # the duck as sampled at the paper profile (session 45): a warp's 32 particles on ~8 stencil bases, ~4 lanes a
    # node; the paper ball's density on ~13. The bench's lattice balls must show the same contrast
    bench = _load("bench_p2g")

    def bases_per_warp(x):
        base = torch.floor(x.double() * 32 - 0.5).long()
        key = (base[:, 0] * 64 + base[:, 1]) * 64 + base[:, 2]
        n = len(key) // 32 * 32
        return sum(len(set(w.tolist())) for w in key[:n].reshape(-1, 32)) / (n // 32)

    duck, ball = (bench.particles(30000, 32, o, torch.device("cpu")) for o in ("duck", "ball12"))
    assert abs(len(duck) - 30000) < 1500
    assert 6.5 < bases_per_warp(duck) < 10 < 11.5 < bases_per_warp(ball) < 15


def test_ball64_orders_are_one_ball_and_the_sub_lattice_order_spreads_a_warp_over_cells():
    bench = _load("bench_p2g")
    n, n_grid = 30000, 32
    mesh, sub, shuffled = (bench.particles(n, n_grid, o, torch.device("cpu")) for o in ("ball64", "ball64_sub",
                                                                                       "ball64_shuffle"))

    def rows(x):
        return {tuple(p) for p in x.tolist()}
    assert rows(mesh) == rows(sub) == rows(shuffled) and len(rows(mesh)) == len(mesh)  # one set of particles
    assert not torch.equal(mesh, sub) and not torch.equal(mesh, shuffled)

    def cells_per_warp(x):  # distinct grid cells among each 32 consecutive particles, mean
        c = bench._cells(x.double(), n_grid)
        key = (c[:, 0] * n_grid + c[:, 1]) * n_grid + c[:, 2]
        return sum(len(torch.unique(key[i:i + 32])) for i in range(0, len(key) - 31, 32)) / (len(key) // 32)
    assert cells_per_warp(mesh) < 10  # meshgrid order: 4 consecutive particles per cell along z
    assert cells_per_warp(sub) > 25  # one particle per cell within a sub-lattice
    spacing = 0.25 / n_grid  # within a sub-lattice, consecutive particles are one cell apart along z (mostly)
    step = (sub[1:] - sub[:-1]).norm(dim=1)
    assert (torch.isclose(step, torch.tensor(4 * spacing), rtol=1e-3)).float().mean() > 0.8
    sampled, ordered = (bench.particles(n, n_grid, o, torch.device("cpu")) for o in ("ball12", "ball12_sub"))
    assert rows(sampled) == rows(ordered) and not torch.equal(sampled, ordered)  # the paper density's ball, reordered
    assert cells_per_warp(sampled) < 16 < 28 < cells_per_warp(ordered)


def test_the_interleaved_order_is_a_permutation_spreading_warps_and_its_p2g_equals_the_kernel():
    import warp as wp
    from gca.sim.kernels import KERNELS, grid_size
    bench = _load("bench_p2g")
    n_grid = 16
    x = bench.particles(3000, n_grid, "ball64", torch.device("cpu"))
    order = bench.interleaved(x, n_grid)
    assert torch.equal(torch.sort(order).values, torch.arange(len(x)))

    def cells_per_warp(y):
        c = bench._cells(y.double(), n_grid)
        key = (c[:, 0] * n_grid + c[:, 1]) * n_grid + c[:, 2]
        return sum(len(torch.unique(key[i:i + 32])) for i in range(0, len(key) - 31, 32)) / (len(key) // 32)
    assert cells_per_warp(x) < 10 and cells_per_warp(x[order]) > 25
    # the indirect kernel scatters the same grid as the per-particle kernel, in either order (float32 sums)
    k, wd, n = KERNELS["float32"], wp.get_device("cpu"), len(x)
    g = torch.Generator().manual_seed(0)
    v, C = torch.randn(n, 3, generator=g), torch.randn(n, 3, 3, generator=g)
    tau, vol = 1e3 * torch.randn(n, 3, 3, generator=g), torch.full((n,), 1e-6)
    G = grid_size(n_grid)

    mass = vol * 1e3

    def scatter(kernel, order_t=None):  # the grid (mv, m) scattered by `kernel`, through `order_t` if given
        mv, m = wp.zeros((G, G, G), dtype=k.vec3, device=wd), wp.zeros((G, G, G), dtype=k.T, device=wd)
        args = [wp.from_torch(x, dtype=k.vec3), wp.from_torch(v, dtype=k.vec3), wp.from_torch(C, dtype=k.mat33),
                wp.from_torch(tau, dtype=k.mat33), wp.from_torch(vol), wp.from_torch(mass),
                wp.zeros(n, dtype=wp.int32, device=wd), 1e-4, float(n_grid), n_grid, mv, m]
        if order_t is None:
            wp.launch(kernel, dim=n, inputs=args, device=wd)
        else:
            o = order_t.to(torch.int32).contiguous()
            wp.launch(kernel, dim=len(o), inputs=[wp.from_torch(o), *args], device=wd)
        return wp.to_torch(mv).clone(), wp.to_torch(m).clone()
    ref = scatter(k.p2g)
    for o in (torch.arange(n), order):
        for a, b in zip(scatter(bench._indirect_kernel(), o), ref):
            torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-5 * float(b.abs().max()))
    half = scatter(bench._indirect_kernel(), order[: n // 2])
    assert not torch.allclose(half[1], ref[1])  # control: half the particles give another grid


def test_bench_runs_times_sequential_and_batched_rollouts_on_the_cpu():
    rows = _load("bench_runs").main(["--device", "cpu", "--runs", "2", "--particles", "200", "--n-grid", "12",
                                     "--steps", "4", "--steps-per-frame", "2", "--repeats", "1",
                                     "--laws", "composite", "batched"])
    assert [r["laws"] for r in rows] == ["composite", "batched"]
    for row in rows:
        assert row["runs"] == 2 and row["particles_per_run"] == 216  # 6^3 lattice
        assert row["sequential_s"] > 0 and row["batched_s"] > 0 and row["speedup"] > 0


def test_bench_sim_times_the_fused_and_the_generic_analytic_step_side_by_side(tmp_path):
    res = _load("bench_sim").main(["--device", "cpu", "--sizes", "500:16", "--steps", "10", "--repeats", "1",
                                   "--law", "neo_hookean", "--graph", "on", "--fuse", "on", "off", "--order",
                                   "lattice", "--skip-rollout", "--json", str(tmp_path / "sim.json")])
    rows = res["throughput"]
    assert [r["fuse"] for r in rows] == [True, False]
    assert all(r["fwd_ms_per_step"] > 0 and r["fwd_bwd_ms_per_step"] > 0 for r in rows)


def test_bench_fused_frame_times_the_three_forward_paths_on_the_cpu():
    rows = _load("bench_fused_frame").main(["--device", "cpu", "--law", "corotated", "--particles", "500",
                                            "--n-grid", "16", "--steps", "3", "--repeats", "1"])
    assert [r["law"] for r in rows] == ["corotated"]
    assert all(rows[0][k] > 0 for k in ("frame_fused", "step_fused", "generic"))


def test_bench_law_precision_runs_on_the_cpu_and_measures_float32_against_float64():
    before = torch.get_float32_matmul_precision()
    out = _load("bench_law_precision").main(["--device", "cpu", "--particles", "600", "--n-grid", "16", "--steps",
                                             "20", "--steps-per-frame", "10", "--iters", "1", "--repeats", "1"])
    assert torch.get_float32_matmul_precision() == before  # the precision is restored
    assert set(out["law"]) == set(out["rollout"]) == {"fp32", "tf32"}
    assert all(v > 0 for r in out["law"].values() for v in r.values())
    fp32, tf32 = out["rollout"]["fp32"], out["rollout"]["tf32"]
    assert 0 < fp32["max_dx_cells"] < 1e-3  # float32 really ran (a float64 run would deviate by 0), and stayed close
    assert 0 < fp32["max_dF"] < 1e-4
    assert 0.999 < fp32["grad_cos"] <= 1 + 1e-12 and 0 < fp32["grad_rel_err"] < 1e-2
    # TF32 is a CUDA mode; on a CPU torch may use reduced-precision kernels of its own under it, or none
    assert tf32["max_dx_cells"] < 1e-3 and tf32["grad_cos"] > 0.999


def test_bench_mlp_times_torch_and_the_tile_kernel_and_checks_both_against_float64():
    before = torch.get_float32_matmul_precision()
    out = _load("bench_mlp").main(["--device", "cpu", "--sizes", "70", "--variants", "torch", "simt", "t16",
                                   "torch_tf32", "--iters", "1", "--repeats", "1"])
    assert torch.get_float32_matmul_precision() == before  # torch_tf32's precision is restored
    assert [r["variant"] for r in out["mlp"]] == ["torch", "simt", "t16", "torch_tf32"]
    assert [r["variant"] for r in out["law"]] == ["torch", "simt", "warp"]
    for r in out["mlp"]:
        assert r["mlp_fwd_us"] > 0 and r["mlp_fwd_bwd_us"] > 0
        assert 0 < r["X_rel_dev"] < 1e-5 and 0 < r["grad_rel_dev"] < 1e-5  # float32 ran, and stayed close
    assert out["mlp"][1]["f64_rel_dev"] < 1e-12 and out["mlp"][2]["f64_rel_dev"] < 1e-12  # float64 builds = torch's
    assert all(r["law_fwd_bwd_us"] > 0 for r in out["law"])


def test_bench_runs_packed_runs_processes_of_batched_runs_at_once_on_the_cpu(tmp_path):
    mod = _load("bench_runs_packed")
    rows = mod.main(["--device", "cpu", "--configs", "1x1", "2x1", "1x2", "--particles", "200", "--n-grid", "12",
                     "--steps", "4", "--steps-per-frame", "2", "--run-rollouts", "4",
                     "--json", str(tmp_path / "p.json")])
    assert [(r["processes"], r["runs_per_process"], r["rollouts_per_process"]) for r in rows] == [(1, 1, 4), (2, 1, 2),
                                                                                                   (1, 2, 2)]
    assert rows[0]["x_solo"] == 1.0 and all(r["span_s"] > 0 and r["run_rollouts_per_s"] > 0 for r in rows)
    for r in rows[1:]:  # the ratio is the rates' ratio, against the one-run row
        assert r["x_solo"] == pytest.approx(r["run_rollouts_per_s"] / rows[0]["run_rollouts_per_s"])
    assert json.loads((tmp_path / "p.json").read_text())["rows"] == rows
    assert all(r["low_priority"] == 0 and r["mean_s_low"] is None and r["priorities"] == [None] * r["processes"]
               for r in rows)


def test_bench_runs_packed_gives_the_last_k_processes_below_normal_mps_priority(tmp_path):
    """``PxB:K``: the last K workers start with CUDA's MPS client priority at below normal, the others without it
    (the worker's own record of its environment), each group's mean time from the go beside the span."""
    mod = _load("bench_runs_packed")
    rows = mod.main(["--device", "cpu", "--configs", "3x1:2", "2x1", "--particles", "200", "--n-grid", "12",
                     "--steps", "4", "--steps-per-frame", "2", "--rollouts-each", "3"])
    low, plain = rows
    assert low["priorities"] == [None, "1", "1"] and plain["priorities"] == [None, None]
    assert (low["low_priority"], low["rollouts_per_process"], plain["rollouts_per_process"]) == (2, 3, 3)
    for r in rows:
        groups = [v for v in (r["mean_s_normal"], r["mean_s_low"]) if v is not None]
        assert groups and all(0 < v <= r["span_s"] + 1e-9 for v in groups)
    assert plain["mean_s_low"] is None and low["mean_s_low"] is not None
    assert mod.parse_config("12x1:12") == (12, 1, 12) and mod.parse_config("4x2") == (4, 2, 0)
    short = mod.main(["--device", "cpu", "--configs", "3x1:1", "1x1", "--particles", "200", "--n-grid", "12",
                      "--steps", "4", "--steps-per-frame", "2", "--rollouts-each", "3", "--short", "2", "1"])
    assert (short[0]["short_processes"], short[0]["short_rollouts"]) == (2, 1)  # the last two do one rollout each
    assert (short[1]["short_processes"], short[1]["short_rollouts"]) == (0, None)  # a config of <= S: all long
    assert short[0]["run_rollouts_per_s"] == pytest.approx(5 / short[0]["span_s"])  # 3 + 1 + 1 run-rollouts


def test_bench_runs_packed_refuses_a_bad_config_and_reports_a_failed_worker():
    mod = _load("bench_runs_packed")
    for bad in ("8", "0x2", "2xb", "2x1:3", "2x1:-1", "2x1:a"):
        with pytest.raises(SystemExit):  # argparse: one line naming the config
            mod.main(["--device", "cpu", "--configs", bad])
    with pytest.raises(SystemExit, match="a worker failed"):  # control: a worker that cannot start is not waited on
        mod.main(["--device", "no_such_device", "--configs", "1x1", "--particles", "200", "--n-grid", "12",
                  "--steps", "2", "--steps-per-frame", "2", "--ready-timeout", "120"])


def test_bench_mlp_packed_replays_each_variant_in_several_processes_on_the_cpu(tmp_path):
    mod = _load("bench_mlp_packed")
    rows = mod.main(["--device", "cpu", "--procs", "2", "--variants", "torch", "simt", "law_torch",
                     "--particles", "200", "--calls", "8", "--json", str(tmp_path / "m.json")])
    assert [(r["variant"], r["pass"], r["processes"], r["calls_per_process"]) for r in rows] == [
        (v, p, 2, 4) for v in ("torch", "simt") for p in ("fwd", "fwdbwd")] + [("law_torch", "fwdbwd", 2, 4)]
    assert all(r["us_per_call"] > 0 for r in rows)
    for r in rows:  # each against its own kind at the same P: the MLP against torch's, a law step against law_torch's
        ref = next(x for x in rows if x["variant"] == ("law_torch" if r["variant"].startswith("law_") else "torch")
                   and x["pass"] == r["pass"] and x["processes"] == r["processes"])
        assert r["x_torch"] == pytest.approx(ref["us_per_call"] / r["us_per_call"])
    assert json.loads((tmp_path / "m.json").read_text())["rows"] == rows
    with pytest.raises(SystemExit):  # argparse: an unknown variant named
        mod.main(["--device", "cpu", "--variants", "torch", "cublas"])


def test_bench_mlp_packed_calls_are_the_variants_own():
    """The replayed calls compute what they are named: simt's and the law's equal torch's (float32 sums in another
    order: to 1e-4 of the largest value)."""
    mod = _load("bench_mlp_packed")
    dev = torch.device("cpu")

    def close(a, b):
        for x, y in zip([a] if torch.is_tensor(a) else a, [b] if torch.is_tensor(b) else b):
            assert x.shape == y.shape and float((x - y).abs().max()) <= 1e-4 * float(y.abs().max())

    close(mod.call_of("simt", "fwd", 64, dev)(), mod.call_of("torch", "fwd", 64, dev)())
    close(mod.call_of("simt", "fwdbwd", 64, dev)(), mod.call_of("torch", "fwdbwd", 64, dev)())
    close(mod.call_of("law_simt", "fwdbwd", 64, dev)(), mod.call_of("law_torch", "fwdbwd", 64, dev)())
    with pytest.raises(AssertionError):  # control: the forward of other particles is another output
        close(mod.call_of("torch", "fwd", 64, dev)(), mod.call_of("torch", "fwd", 64, dev)().flip(0))
    assert mod.passes_of("ieee_64") == ("fwd", "fwdbwd") and mod.passes_of("law_torch") == ("fwdbwd",)


_DUMMY = """
import argparse, sys, time
sys.path.insert(0, {root!r})
from benchmarks.packed import add_arguments, ready_then_go, write_result
ap = argparse.ArgumentParser()
add_arguments(ap)
ap.add_argument("--setup", type=float, default=0.0)
ap.add_argument("--work", type=float, default=0.0)
ap.add_argument("--fail", action="store_true")
a = ap.parse_args()
time.sleep(a.setup)
t0 = ready_then_go(a.ready, a.go, a.ready_timeout)
if a.fail:
    sys.exit(3)
time.sleep(a.work)
write_result(a.result, t0)
"""


def _dummy(tmp_path) -> str:
    path = tmp_path / "dummy.py"
    path.write_text(_DUMMY.format(root=str(ROOT)))
    return str(path)


def test_packed_workers_start_together_each_run_in_a_fresh_folder(tmp_path):
    """The span counts the timed work only, not the workers' unequal set-up, also when the same runs go again in the
    same parent folder (an earlier run's ready and go files do not count: a config listed twice)."""
    packed = _load("packed")
    cmds = [[_dummy(tmp_path), "--setup", str(0.6 * i), "--work", "0.2"] for i in range(3)]
    for _ in range(2):
        span, results = packed.run_workers(cmds, tmp_path / "runs", 60.0, "dummy")
        assert 0.2 <= span < 0.55 and len(results) == 3  # the control, no start signal: a span of ~1.4 s
    assert len(list((tmp_path / "runs").iterdir())) == 2


def test_a_worker_failing_after_the_go_stops_the_others_and_a_worker_without_a_go_gives_up(tmp_path):
    packed = _load("packed")
    t0 = time.monotonic()
    with pytest.raises(SystemExit, match="exited with status 3"):
        packed.run_workers([[_dummy(tmp_path), "--work", "60"], [_dummy(tmp_path), "--fail"]], tmp_path / "runs",
                           60.0, "dummy")
    assert time.monotonic() - t0 < 20  # the 60-s worker was stopped, not waited for
    with pytest.raises(SystemExit, match="exited with status 3"):  # its order does not matter
        packed.run_workers([[_dummy(tmp_path), "--fail"], [_dummy(tmp_path), "--work", "60"]], tmp_path / "runs",
                           60.0, "dummy")
    assert time.monotonic() - t0 < 40
    with pytest.raises(SystemExit, match="no go within"):  # a driver that died gives no go: the worker gives up
        packed.ready_then_go(str(tmp_path / "ready"), str(tmp_path / "never"), timeout=0.2)
    rows = [{"cost": 2.0, "b": True}, {"cost": 1.0, "b": False}]
    packed.ratios(rows, "x", lambda r: rows[0] if not r["b"] else None, "cost")
    assert rows[0]["x"] is None and rows[1]["x"] == 2.0  # the baseline's cost over the row's: lower is better
