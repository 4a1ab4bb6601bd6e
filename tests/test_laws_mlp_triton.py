"""gca.laws.mlp_triton (``mlp_kernel: triton_tf32``): the neural laws with the fused Triton MLP against torch's MLP, in
Triton's CPU interpreter (the CPU twin of the CUDA path; the interpreter computes TF32 dots in float32, so the values
agree to float32 rounding there; the GPU measures TF32's own deviation, benchmarks/NOTES.md session 37): the law's
output (float32 2e-5, float64 1e-12 relative) and its gradients to F and to the LoRA factors (10x those), the fused
kernels counted; their weight layout checked against a transposed W2; refused on a CPU without the interpreter, for
a network they do not compute and for weights that do not fit. Each case runs in a fresh interpreter process (Triton
reads TRITON_INTERPRET when the kernels are decorated)."""

import os
import subprocess
import sys
from pathlib import Path

import pytest

pytest.importorskip("triton")
ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(Path(__file__).parent))
from interpreted import run_interpreted  # noqa: E402

SETUP = """
import torch
from gca.laws.lora import apply_lora, lora_parameters
from gca.laws.neural import NeuralElasticity, NeuralPlasticity
torch.manual_seed(0)

def laws(dtype):
    out = []
    for cls in (NeuralElasticity, NeuralPlasticity):
        net = cls()
        apply_lora(net, 16, 16.0)
        for name, p in net.named_parameters():
            if name.endswith("lora_B"):
                torch.nn.init.normal_(p, std=0.05)  # adapters that move the law
        out.append(net.to(dtype))
    return out

def F_of(n, dtype):
    g = torch.Generator().manual_seed(3)
    return (torch.eye(3, dtype=dtype) + 0.2 * torch.randn(n, 3, 3, generator=g, dtype=dtype)).requires_grad_(True)

def run(net, F, kernel):
    net.mlp_kernel = kernel
    R, X = net.fused_network(F)
    v = torch.randn(X.shape, generator=torch.Generator().manual_seed(4), dtype=X.dtype)
    grads = torch.autograd.grad(X, [F, *lora_parameters(net)], v)
    return X.detach(), grads

def rel(a, b):
    return float((a - b).abs().max() / b.abs().max())
"""


def _run(code: str, interpret: bool = True) -> str:
    """``SETUP`` + ``code`` in a fresh Python (under Triton's CPU interpreter unless ``interpret`` is False)."""
    return run_interpreted(SETUP + code, interpret)


def test_the_laws_with_the_fused_mlp_equal_torchs_values_and_lora_gradients():
    _run("""
from gca.laws import mlp_triton
calls = []
apply = mlp_triton.FusedMLP.apply
mlp_triton.FusedMLP.apply = lambda *a: calls.append(1) or apply(*a)  # the option really takes the fused kernels
for dtype, tol in ((torch.float32, 2e-5), (torch.float64, 1e-12)):
    for net in laws(dtype):
        F = F_of(150, dtype)  # 150 = two blocks of 64 and a partial one
        X, g = run(net, F, "torch")
        assert not calls
        X2, g2 = run(net, F, "triton_tf32")
        assert len(calls) == 1, calls
        calls.clear()
        assert rel(X2, X) < tol, (dtype, rel(X2, X))
        assert len(g) == 1 + 6 and all(b.abs().max() > 0 for b in g)  # F and three layers' A and B
        for a, b in zip(g2, g):
            assert rel(a, b) < 10 * tol, (dtype, rel(a, b))
# control: the kernels read torch's [out, in] layout; handed W2 transposed they compute another function
net = laws(torch.float64)[0]
z = torch.randn(150, 13, dtype=torch.float64, generator=torch.Generator().manual_seed(5))
W = [layer.effective_weight().detach() for layer in net.mlp[0::2]]
ref = net.mlp(z).detach()
assert rel(mlp_triton.mlp(z, W, "ieee").detach(), ref) < 1e-12
assert rel(mlp_triton.mlp(z, [W[0], W[1].T, W[2]], "ieee").detach(), ref) > 1e-3
print("ok")
""")


def test_the_fused_mlp_is_refused_where_it_cannot_compute():
    _run("""
import pytest
from gca.laws import mlp_triton
net = laws(torch.float32)[0]
net.mlp[1] = torch.nn.Tanh()  # a network the other kernels fuse, but these compute the exact GELU: refused
with pytest.raises(ValueError, match="exact GELU"):
    run(net, F_of(20, torch.float32), "triton_tf32")
net = laws(torch.float32)[0]
net.mlp[3] = torch.nn.GELU(approximate="tanh")
with pytest.raises(ValueError, match="exact GELU"):
    run(net, F_of(20, torch.float32), "triton_tf32")
z = torch.randn(20, 13)
W = [torch.randn(64, 13), torch.randn(64, 64), torch.randn(9, 64)]
with pytest.raises(ValueError, match="weights"):  # a weight that does not fit z: refused, never read out of bounds
    mlp_triton.mlp(z, [W[0][:, :12], W[1], W[2]])
with pytest.raises(ValueError, match="power of two"):
    mlp_triton.mlp(z, W, block=48)
for warps in (0, 3, 32):  # the backward's warps per program: a power of two from 1 to 16
    with pytest.raises(ValueError, match="warps per program"):
        mlp_triton.mlp(z, W, warps=warps)
with pytest.raises(ValueError, match="float32"):
    mlp_triton.mlp(z.double(), [w.double() for w in W], "tf32")
print("ok")
""")
    _run("""
import pytest
net = laws(torch.float32)[0]
with pytest.raises(ValueError, match="interpreter"):  # a CPU without Triton's interpreter: one clear line
    run(net, F_of(20, torch.float32), "triton_tf32")
print("ok")
""", interpret=False)


def test_one_compiled_backward_serves_every_particle_count():
    """The compiled backward's launch carries no count as a constexpr (CPR's 1-10 frame chunks and each scene's particle
    count compiled a kernel each, 2.3-2.5 s apiece: session 44), and its counts are not specialised by Triton. The
    kernel compiles for sm_90 on this CPU (Triton's own compiler, no GPU): the CUDA path's source is checked here, not
    only the interpreter's, and its tile loop is still software-pipelined (async copies). Control: the interpreted
    launch does pass the count as a constexpr, and the equality check sees it."""
    _run("""
import triton
from triton.backends.compiler import GPUTarget
from triton.compiler import ASTSource
from gca.laws import mlp_triton as m
ns = [29985, 29985 * 7, 30000 * 10, 28418 * 3]
launches = [m._bwd_launch(n, 13, 64, 9, m.BLOCK, "tf32", 264, interpreted=False) for n in ns]
assert all(c == launches[0][2] for _, _, c in launches), [c for _, _, c in launches]
assert len({counts for _, counts, _ in launches}) == len(ns)  # the counts do vary
assert set(m._fused_mlp_bwd.do_not_specialize) == {"n", "n_programs", "per_program"}
assert set(m._fused_mlp_fwd.do_not_specialize) == {"n"}
interp = [m._bwd_launch(n, 13, 64, 9, m.BLOCK, "tf32", 264, interpreted=True)[2] for n in ns]
assert len({c["INTERPRETED_PER"] for c in interp}) > 1  # control: a per-count constexpr would fail the check above
for p, counts, _ in launches:  # fewer than per_program iterations of all p programs fall past the last tile
    n, p2, per = counts
    tiles = triton.cdiv(n, m.BLOCK)
    assert p2 == p <= 264 and p * per >= tiles and p * per - tiles < per, counts
fn, consts = m._fused_mlp_bwd, launches[0][2]
sig = {a: "*fp32" if a.endswith("_ptr") else "i32" for a in fn.arg_names}
sig.update({k: "constexpr" for k in consts})
attrs = {(i,): [["tt.divisibility", 16]] for i, a in enumerate(fn.arg_names) if a.endswith("_ptr")}
src = ASTSource(fn, sig, constexprs={(fn.arg_names.index(k),): v for k, v in consts.items()}, attrs=attrs)
kernel = triton.compile(src, target=GPUTarget("cuda", 90, 32), options=dict(num_warps=m.BWD_WARPS))
assert "scf.for" in kernel.asm["ttgir"] and "async_copy" in kernel.asm["ttgir"], kernel.asm["ttgir"][:2000]
print("ok")
""", interpret=False)


def test_the_option_bench_rolls_out_both_kinds(tmp_path):
    """benchmarks/bench_mlp_option.py (the GPU measurement of the option) on a small block in the interpreter: a row
    per kind, the torch row the reference (0 deviation), the fused one within float32 rounding of it here."""
    out = tmp_path / "o.json"
    env = {**os.environ, "TRITON_INTERPRET": "1"}
    run = subprocess.run([sys.executable, "benchmarks/bench_mlp_option.py", "--device", "cpu", "--kinds", "torch",
                          "triton_tf32", "--particles", "500", "--n-grid", "16", "--steps", "4", "--per-frame", "2",
                          "--repeats", "1", "--json", str(out)], cwd=ROOT, env=env, capture_output=True, text=True,
                         timeout=600)
    assert run.returncode == 0, run.stdout + run.stderr
    import json
    rows = json.loads(out.read_text())["rows"]
    assert [r["kind"] for r in rows] == ["torch", "triton_tf32"]
    assert rows[0]["x_dev_cells"] == 0.0 and rows[0]["grad_rel_dev"] == 0.0
    assert rows[1]["x_dev_cells"] < 1e-3 and rows[1]["grad_rel_dev"] < 1e-4 and rows[1]["ms"] > 0
