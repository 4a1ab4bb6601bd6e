"""benchmarks/bench_sim.py and bench_p2g.py on the CPU: the particle orders of the benchmark block, and every P2G
kernel layout timed on each order (a smoke run of what the H100 bundles run)."""

import importlib.util
from pathlib import Path

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
    assert [r["order"] for r in rows] == ["random", "lattice", "cell", "morton", "ball64"]
    assert rows[1]["particles"] == 512  # 8^3
    assert abs(rows[4]["particles"] - 500) < 60  # a lattice ball of ~500 at ~64 per cell
    assert all(r[k] > 0 for r in rows for k in ("p2g_us", "p2g_nodes_us", "p2g_block_us", "g2p_us", "g2p_adj_us"))


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
