"""benchmarks/bench_mlp_triton.py's fused MLP (issue 20's probe) in Triton's CPU interpreter: the forward equals
torch's on a partial last block, other activations are refused; the backward (persistent programs, per-program
partials) equals torch's autograd in float64 to 1e-12 and passes a gradcheck, a transposed weight caught; the packed
bench replays these calls. The kernels live in gca.laws.mlp_triton (its law-level twin: tests/test_laws_mlp_triton.py);
triton is installed by setup on CPU machines (the `interp` extra), so these run in CI."""

import os
import subprocess
import sys
from pathlib import Path

import pytest

pytest.importorskip("triton")
sys.path.insert(0, str(Path(__file__).parent))
from interpreted import run_interpreted  # noqa: E402
SCRIPT = Path(__file__).resolve().parents[1] / "benchmarks" / "bench_mlp_triton.py"


def _run(code: str) -> str:
    """``code`` in a fresh Python under Triton's CPU interpreter, in the repository root."""
    return run_interpreted(code, cwd=SCRIPT.parents[1])


def test_the_fused_forward_equals_torch_and_refuses_other_activations():
    _run("""
import sys, torch
sys.argv = ["x", "--device", "cpu"]
sys.path.insert(0, "benchmarks")
import bench_mlp_triton as b
from gca.laws.neural import NeuralLawConfig, make_mlp
torch.manual_seed(1)
net = make_mlp(NeuralLawConfig())
x = torch.randn(70, 13)  # 70 = 2 blocks of 32 and a partial one
ref = net(x).detach()
y = b.fused_forward(net, x, 32)
dev = float((y - ref).abs().max() / ref.abs().max())
assert dev < 1e-5, dev
net[1] = torch.nn.GELU(approximate="tanh")  # the kernel computes the exact GELU: refused, not computed wrongly
try:
    b.fused_forward(net, x, 32)
    raise SystemExit("a tanh GELU was not refused")
except ValueError as e:
    assert "exact GELUs" in str(e)
print("ok", dev)
""")


def test_the_fused_backward_equals_autograd_in_float64():
    _run("""
import sys, torch
import torch.nn.functional as tf
sys.argv = ["x", "--device", "cpu"]
sys.path.insert(0, "benchmarks")
import bench_mlp_triton as b
from gca.laws.neural import NeuralLawConfig, make_mlp
torch.manual_seed(1)
net = make_mlp(NeuralLawConfig()).double()
x = (0.5 * torch.randn(40, 13, dtype=torch.float64)).requires_grad_(True)  # 3 tiles of 16 on 2 programs: one loops
Ws = [m.weight for m in net if isinstance(m, torch.nn.Linear)]
v = torch.randn(40, 9, dtype=torch.float64)
ref = torch.autograd.grad((net(x) * v).sum(), [x, *Ws])
got = torch.autograd.grad((b.fused_mlp(net, x, 16, programs=2) * v).sum(), [x, *Ws])
dev = max(float((a - r).abs().max() / r.abs().max()) for a, r in zip(got, ref))
assert dev < 1e-12, dev
W1, W2, W3 = (w.detach() for w in Ws)
wrong = torch.autograd.grad(((W3 @ tf.gelu(W2.t() @ tf.gelu(W1 @ x.t()))).t() * v).sum(), [x])[0]  # W2 transposed
assert float((got[0] - wrong).abs().max() / wrong.abs().max()) > 1e-2  # control: the test sees a transposed weight
xs = x.detach()[:5].clone().requires_grad_(True)
assert torch.autograd.gradcheck(lambda z: b.mlp_triton.FusedMLP.apply(z, W1, W2, W3, 16, "ieee", 1, 8), (xs,), eps=1e-6, atol=1e-8)
print("ok", dev)
""")


def test_the_packed_bench_replays_the_fused_mlp():
    """``bench_mlp_packed.py``'s ``ieee_32`` calls are the fused MLP of torch's call's network: equal to torch's."""
    _run("""
import sys, torch
sys.argv = ["x", "--device", "cpu"]
sys.path.insert(0, ".")
from benchmarks import bench_mlp_packed as m
dev = torch.device("cpu")
y, ref = m.call_of("ieee_32", "fwd", 70, dev)(), m.call_of("torch", "fwd", 70, dev)()
d = float((y - ref).abs().max() / ref.abs().max())
assert y.shape == ref.shape == (70, 9) and d < 1e-5, d
assert float((y - ref.flip(0)).abs().max() / ref.abs().max()) > 1e-3  # control: another row order is caught
gs, gr = m.call_of("ieee_32", "fwdbwd", 70, dev)(), m.call_of("torch", "fwdbwd", 70, dev)()
assert max(float((a - r).abs().max() / r.abs().max()) for a, r in zip(gs, gr)) < 1e-5
assert m.VARIANT.match("tf32_32_w4_p1") and not m.VARIANT.match("tf32_32_p1_w4")  # a sweep's launch, in its order
gs = m.call_of("tf32_32_w4_p1", "fwdbwd", 70, dev)()  # the interpreter computes TF32 dots in float32
assert max(float((a - r).abs().max() / r.abs().max()) for a, r in zip(gs, gr)) < 1e-5
print("ok", d)
""")


def test_a_launch_sweep_names_the_backward_and_computes_the_same_function():
    """Session 38's sweep of the TF32 backward's launch: ``tf32_<B>_w<W>_p<P>`` sets the backward's warps and programs
    per SM (the defaults are the library's), any launch gives the same values and gradients (the interpreter computes
    TF32 dots in float32: 1e-5 of torch's), and a name outside the grammar is refused."""
    _run("""
import sys, torch
sys.argv = ["x", "--device", "cpu"]
sys.path.insert(0, "benchmarks")
import bench_mlp_triton as b
b.SMS = 1  # one "SM": programs per SM are then the programs themselves (the interpreter's count, patched)
W, P = b.mlp_triton.BWD_WARPS, b.mlp_triton.BWD_PROGRAMS_PER_SM  # the library's launch (session 39: 4 warps, 2 per SM)
assert b.fused_launch("tf32_64") == ("tf32", 64, W, P)
assert b.fused_launch("tf32_128_w8_p1") == ("tf32", 128, 8, 1)
assert b.fused_launch("ieee_32_p1") == ("ieee", 32, b.mlp_triton.BWD_WARPS, 1)
assert b.fused_launch("torch") is None and b.fused_launch("tf32_64_p2_w4") is None  # the order is fixed
for bad in ("tf32", "tf32_64_w", "bf16_64", "tf32_64_p2_w4"):
    try:
        b.variant_call(bad, None)
        raise AssertionError(f"{bad} was not refused")
    except SystemExit as e:
        assert "unknown variant" in str(e)
from gca.laws.neural import NeuralLawConfig, make_mlp
torch.manual_seed(2)
net = make_mlp(NeuralLawConfig())
x = torch.randn(70, 13).requires_grad_(True)
v = torch.randn(70, 9)
Ws = [m.weight for m in net if isinstance(m, torch.nn.Linear)]
ref = torch.autograd.grad((net(x) * v).sum(), [x, *Ws])
per = -(-5 // P)  # the library's P programs over 5 tiles of 16: per tiles each, so ceil(5 / per) programs
for name, launch in (("tf32_16_w8_p1", (1, 8)), ("tf32_32_w1_p4", (3, 1)), ("tf32_16", (-(-5 // per), W)),
                     ("tf32_64_w2", (min(2, P), 2))):
    # 70 rows: 5 tiles of 16 (p1: one program loops over all 5; p4: 2 tiles each, so 3 programs; p2: 3 tiles each, 2
    # programs), 3 tiles of 32 (p4: 3 programs, one tile each), 2 of 64 (p >= 2: 2 programs, one tile each); the
    # named warps and programs differ from the library's (4, 2), so a parser that dropped them would fail
    call = b.variant_call(name, net)
    with b.backward_launches() as seen:  # the backward's launch as the kernel receives it: (programs, warps)
        got = torch.autograd.grad((call(x) * v).sum(), [x, *Ws])
    assert [(grid[0], kw["num_warps"]) for grid, kw, _ in seen] == [launch], (name, seen)
    dev = max(float((g - r).abs().max() / r.abs().max()) for g, r in zip(got, ref))
    assert dev < 1e-5, (name, dev)
    bad = torch.autograd.grad((call(x) * v.flip(0)).sum(), [x, *Ws])  # control: another cotangent is seen
    assert max(float((g - r).abs().max() / r.abs().max()) for g, r in zip(bad, ref)) > 1e-2
print("ok")
""")


def test_the_sweeps_pick_is_the_fastest_fused_launch(tmp_path):
    """``--fastest``: the fused variants of a result file by forward + backward time at the given size, fastest
    first, torch and the library's own launch (timed anyway) left out; rows of another size do not count."""
    from gca.laws.mlp_triton import BWD_PROGRAMS_PER_SM, BWD_WARPS
    library = f"tf32_64_w{BWD_WARPS}_p{BWD_PROGRAMS_PER_SM}"  # the library's launch by its full name
    other = "tf32_64_w8_p4" if library != "tf32_64_w8_p4" else "tf32_64_w4_p2"  # session 38's launch, 39's
    rows = [{"particles": 30000, "variant": "torch", "fwd_bwd_us": 50.0},
            {"particles": 30000, "variant": "tf32_64", "fwd_bwd_us": 60.0},
            {"particles": 30000, "variant": other, "fwd_bwd_us": 80.0},
            {"particles": 30000, "variant": "tf32_128_w8_p1", "fwd_bwd_us": 70.0},
            {"particles": 30000, "variant": "tf32_32_w4_p8", "fwd_bwd_us": 90.0},
            {"particles": 30000, "variant": library, "fwd_bwd_us": 55.0},  # the library's launch, named out
            {"particles": 100000, "variant": "tf32_32_w4_p8", "fwd_bwd_us": 1.0}]
    f = tmp_path / "sweep.json"
    f.write_text(__import__("json").dumps({"device": "x", "rows": rows}))
    out = subprocess.run([sys.executable, str(SCRIPT), "--fastest", str(f), "--particles", "30000", "--top", "2"],
                         cwd=SCRIPT.parents[1], env={**os.environ, "TRITON_INTERPRET": "1"}, capture_output=True,
                         text=True, timeout=300)
    assert out.returncode == 0, out.stderr
    assert out.stdout.split() == ["tf32_128_w8_p1", other]
    missing = subprocess.run([sys.executable, str(SCRIPT), "--fastest", str(tmp_path / "none.json")],
                             cwd=SCRIPT.parents[1], capture_output=True, text=True, timeout=300)
    assert missing.returncode == 0 and missing.stdout.strip() == "" and "no sweep to pick from" in missing.stderr


def test_the_backwards_compiled_resources_are_read_off_its_launch():
    """``backward_kernel``: the registers, spills and shared memory of the kernel the backward's launch returns (a
    stand-in for CUDA's compiled kernel here: the interpreter returns none, so its rows carry no such fields)."""
    _run("""
import sys, types, torch
sys.argv = ["x", "--device", "cpu"]
sys.path.insert(0, "benchmarks")
import bench_mlp_triton as b
from gca.laws.neural import NeuralLawConfig, make_mlp
torch.manual_seed(3)
net = make_mlp(NeuralLawConfig())
x = torch.randn(40, 13).requires_grad_(True)
call = b.variant_call("tf32_16", net)
both = lambda: torch.autograd.grad(call(x), [x], torch.ones(40, 9))
assert b.backward_kernel(both) == {}  # the interpreter: no compiled kernel comes back
real = b.mlp_triton._fused_mlp_bwd
class Fake:  # a launch that returns what CUDA's does: a kernel with its resources
    def __getitem__(self, grid):
        def run(*args, **kwargs):
            real[grid](*args, **kwargs)
            return types.SimpleNamespace(n_regs=168, n_spills=24, metadata=types.SimpleNamespace(shared=33792))
        return run
b.mlp_triton._fused_mlp_bwd = Fake()
assert b.backward_kernel(both) == {"bwd_regs": 168, "bwd_spills": 24, "bwd_shared_bytes": 33792}
assert isinstance(b.mlp_triton._fused_mlp_bwd, Fake)  # put back as found
assert b.backward_kernel(lambda: torch.autograd.grad(net(x), [x], torch.ones(40, 9))) == {}  # torch: no launch
print("ok")
""")
