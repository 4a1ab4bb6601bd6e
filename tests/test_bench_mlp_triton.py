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
SCRIPT = Path(__file__).resolve().parents[1] / "benchmarks" / "bench_mlp_triton.py"


def _run(code: str) -> str:
    """``code`` in a fresh Python under Triton's CPU interpreter; it must print "ok"."""
    env = {**os.environ, "TRITON_INTERPRET": "1"}
    out = subprocess.run([sys.executable, "-c", code], cwd=SCRIPT.parents[1], env=env, capture_output=True, text=True,
                         timeout=600)
    assert out.returncode == 0 and "ok" in out.stdout, out.stdout + out.stderr
    return out.stdout


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
assert torch.autograd.gradcheck(lambda z: b.mlp_triton.FusedMLP.apply(z, W1, W2, W3, 16, "ieee", 1), (xs,), eps=1e-6, atol=1e-8)
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
print("ok", d)
""")
