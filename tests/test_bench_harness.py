"""benchmarks/harness.py's stage subsets (how a device bundle runs a prior beside other scenes' data) and
benchmarks/paperprior_summary.py on the CPU."""

import importlib.util
import json
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _load(name: str):
    spec = importlib.util.spec_from_file_location(name, ROOT / "benchmarks" / f"{name}.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_harness_runs_only_the_stages_asked(tmp_path, monkeypatch):
    harness = _load("harness")
    called = []
    for name in harness.STAGES:  # each stage module's main records its call (the real stages have their own tests)
        module = type(sys)(name)
        module.main = (lambda n: lambda argv: called.append(n))(name)
        monkeypatch.setitem(sys.modules, name, module)
    raw = harness.make_params("ball", ["gca"], "ci", [], tmp_path / "params.yaml")
    work = tmp_path / "w"
    harness.run_stages(raw, "ball", work, tmp_path / "params.yaml", "cpu", False, stages=("assets", "particles", "prior"))
    assert called == ["assets", "particles", "prior"]
    called.clear()
    harness.run_stages(raw, "ball", work, tmp_path / "params.yaml", "cpu", False, reuse_data=True,
                       stages=("assets", "particles", "ground_truth", "preprocess"))
    assert called == ["ground_truth", "preprocess"]  # the data stages already done there are reused
    called.clear()
    harness.run_stages(raw, "ball", work, tmp_path / "params.yaml", "cpu", True, reuse_data=True)
    assert called == ["prior", "train", "evaluate"]  # control: every stage not done (no prior file was written)


def test_summary_lists_finished_and_stopped_runs(tmp_path):
    summary = _load("paperprior_summary")
    history = [{"iteration": i, "horizon": 12 + i, "loss": 1e4 * (i + 1), "grad_norm": 10.0 ** i, "wave_speed": 10.6,
                "sim_refine": 1} for i in range(7)]
    (tmp_path / "harness_paper_ball_gca_cuda.json").write_text(json.dumps({
        "scene": "ball", "method": "gca", "status": "diverged", "iterations": 7, "seconds_per_iteration": 1.2,
        "peak_memory_gib": 2.2, "chamfer_mean": None, "rejected_updates": 1, "message": "SimulationDiverged: x",
        "history": history, "rejected": [{"iteration": 6, "lr_scale": 0.5, "message": "after step 120"}]}))
    (tmp_path / "stopped_gca_t.json").write_text(json.dumps({"iterations_done": 3, "history": history[:3],
                                                             "rejected": []}))
    text = summary.summarize(tmp_path, every=5)
    assert "ball gca: diverged, 7 its" in text and "rejected at it 6 (lr x0.5)" in text
    assert "it    0" in text and "it    5" in text and "it    6" in text and "it    3" not in text  # every 5th + last
    assert "stopped_gca_t: stopped after 3 iterations" in text
    assert "no harness results" in summary.summarize(tmp_path / "empty")


def test_harness_sets_a_solver_switch_for_its_solvers_and_refuses_an_unknown_one(monkeypatch):
    import pytest

    from gca.sim.solver import MPMSolver, SimConfig

    harness = _load("harness")
    monkeypatch.setattr(MPMSolver, "block_p2g", MPMSolver.block_p2g)  # restored after the test
    harness.set_solver_switches(["block_p2g=true"])
    assert MPMSolver(SimConfig(n_grid=8)).blocks_p2g  # on even on a CPU, where its default is off
    monkeypatch.setattr(MPMSolver, "frame_mlp_grads", MPMSolver.frame_mlp_grads)
    harness.set_solver_switches(["frame_mlp_grads=true"])  # session 56's switch: the frame's MLP gradient sums
    assert MPMSolver(SimConfig(n_grid=8)).frame_mlp_grads is True
    monkeypatch.setattr(MPMSolver, "frame_mlp_grads", False)
    coarse = MPMSolver(SimConfig(n_grid=8))
    coarse.frame_mlp_grads = True  # one solver's switch reaches its refined solvers (a CFL refinement's frames)
    assert coarse.refined(2).frame_mlp_grads is True and MPMSolver(SimConfig(n_grid=8)).frame_mlp_grads is False
    with pytest.raises(SystemExit, match="--solver 'n_grid=4'"):
        harness.set_solver_switches(["n_grid=4"])
    with pytest.raises(SystemExit, match="=true|false|null"):  # Python's spelling is a string here, and a true one
        harness.set_solver_switches(["block_p2g=None"])
    monkeypatch.setattr(MPMSolver, "stash_mib", MPMSolver.stash_mib)
    harness.set_solver_switches(["stash_mib=1e9"])  # a number setting (YAML 1.1 reads 1e9 as a string)
    assert MPMSolver(SimConfig(n_grid=8)).stash_mib == 1e9
    harness.set_solver_switches(["stash_mib=0"])  # the grid stash off
    assert MPMSolver(SimConfig(n_grid=8)).stash_mib == 0
    monkeypatch.setattr(MPMSolver, "mlp_stash_mib", MPMSolver.mlp_stash_mib)
    harness.set_solver_switches(["mlp_stash_mib=1024"])  # the MLP stash's budget (session 57), to refined solvers too
    coarse = MPMSolver(SimConfig(n_grid=8))
    assert coarse.mlp_stash_mib == 1024 and coarse.refined(2).mlp_stash_mib == 1024
    for bad in ("stash_mib=-1", "stash_mib=true", "stash_mib=many", "block_p2g=3", "mlp_stash_mib=-2"):
        with pytest.raises(SystemExit, match="a number >= 0"):
            harness.set_solver_switches([bad])


def test_a_harness_row_names_its_host_cpu(tmp_path):
    """``host_cpu``: the model from a cpuinfo file and the core count (a solo training's host-bound phase moves with
    it, NOTES session 39); a file without a model line, or none, falls back to the platform's name, never empty."""
    import os
    harness = _load("harness")
    info = tmp_path / "cpuinfo"
    info.write_text("processor\t: 0\nvendor_id\t: GenuineIntel\nmodel name\t: Intel(R) Xeon(R) Platinum 8480C\n"
                    "processor\t: 1\nmodel name\t: Intel(R) Xeon(R) Platinum 8480C\n")
    cores = len(os.sched_getaffinity(0))
    assert harness.host_cpu(info) == f"Intel(R) Xeon(R) Platinum 8480C, {cores} cores"
    info.write_text("processor\t: 0\nvendor_id\t: GenuineIntel\n")
    for path in (info, tmp_path / "none"):
        got = harness.host_cpu(path)
        assert got.endswith(f", {cores} cores") and "Platinum" not in got
        assert got.split(",")[0].strip()


def test_pack_passes_the_solver_switches_to_every_copy(tmp_path, monkeypatch):
    """benchmarks/pack.py --solver reaches each copy's harness command (session 51's packed A/B of a kernel path),
    and the copies without it get none (the control arm)."""
    sys.path.insert(0, str(ROOT / "benchmarks"))
    pack = _load("pack")
    out = tmp_path / "out"
    out.mkdir()
    (out / pack.result_name("paper", "duck", "gca", "cuda")).write_text(json.dumps(
        {"train_seconds": 10.0, "seconds_per_iteration": 1.0, "peak_memory_gib": 1.0, "status": "ok", "device": "x"}))
    work = tmp_path / "w"
    (work / "prep").mkdir(parents=True)
    cmds = []

    class Fake:  # a copy that ends at once, writing nothing
        def __init__(self, cmd, **kw):
            cmds.append(cmd)

        def wait(self):
            return 0
    monkeypatch.setattr(pack.subprocess, "Popen", Fake)
    r = pack.main(["--work", str(work), "--scene", "duck", "--methods", "gca", "--copies", "2", "--out", str(out),
                   "--solver", "vec4_step=true", "--solver", "vec4_g2p_adj=true"])
    assert len(cmds) == 2 and r["solver"] == ["vec4_step=true", "vec4_g2p_adj=true"]
    for c in cmds:
        i = c.index("--solver")
        assert c[i:i + 4] == ["--solver", "vec4_step=true", "--solver", "vec4_g2p_adj=true"]
    cmds.clear()
    pack.main(["--work", str(work), "--scene", "duck", "--methods", "gca", "--copies", "1", "--out", str(out)])
    assert "--solver" not in cmds[0]


def test_profile_kernel_rows_keep_whole_names_largest_first():
    from types import SimpleNamespace as E

    profile_train = _load("profile_train")
    long = "make_kernels__locals__g2p_adjoint_" + "x" * 80  # past the printed table's 60 characters
    events = [E(key="aten::mul", self_device_time_total=10.0, count=4),
              E(key=long, self_device_time_total=300.0, count=3),
              E(key="old_torch_name", self_cuda_time_total=50.0, count=1),  # a torch without the device name
              E(key="host_only", self_device_time_total=0.0, count=7)]
    lines = profile_train.kernel_rows(events).splitlines()
    assert lines[0] == "name\tself_us\tcalls\tus_per_call"
    assert [line.split("\t")[0] for line in lines[1:]] == [long, "old_torch_name", "aten::mul"]  # no host-only row
    assert lines[1].split("\t")[1:] == ["300.0", "3", "100.00"]


def test_bench_features_rows_on_the_cpu(tmp_path):
    # the GPU bench's CPU twin: three rows timed, the one-kernel paths' outputs bitwise the two kernels', the JSON
    bench = _load("bench_features")
    rows = bench.main(["--device", "cpu", "--n", "64", "--reps", "2", "--json", str(tmp_path / "f.json")])
    assert [r["row"] for r in rows] == ["two_kernels", "one_kernel_forward", "one_kernel_kept"]
    assert all(r["equal"] and r["us"] > 0 for r in rows)
    assert json.loads((tmp_path / "f.json").read_text())["n"] == 64
