"""A frame's weight-gradient sum of the fused Triton MLP (``MPMSolver.frame_mlp_grads``,
``gca.laws.neural.frame_mlp_sums``, ``gca.laws.mlp_triton.FrameSum``), in Triton's CPU interpreter (its CPU twin):
within one block, calls of several particle counts give the values of the plain calls bitwise and the same gradients
to F and to the LoRA factors to rounding (float64 1e-12, float32 1e-5 relative), each call's partials in a block of
the frame's, summed once and freed; negative controls: every call's partials in one block, and a sum that never
reaches the weights, change the gradients. A rollout's frames with the switch on and off give the same gradients
(checkpointed frames, the reverse sweep's recompute), and so does a kept graph differentiated three times (the term
shares' way; negative control: a pass that continues and sums the earlier pass's blocks counts them twice). Each case
runs in a fresh interpreter process (Triton reads TRITON_INTERPRET when the kernels are decorated)."""

import sys
from pathlib import Path

import pytest

pytest.importorskip("triton")
sys.path.insert(0, str(Path(__file__).parent))
from interpreted import LAW_SCENE, NET_OF, run_interpreted  # noqa: E402

SETUP = """
import torch
from gca.laws import mlp_triton
from gca.laws.base import Material
from gca.laws.lora import apply_lora, lora_parameters, merged_weights
from gca.laws.neural import NeuralElasticity, NeuralLawConfig, NeuralPlasticity, frame_mlp_sums
torch.manual_seed(0)
""" + NET_OF + """
COUNTS = (300, 77, 300)  # one frame's calls: the 77-particle call runs fewer backward programs than the others

def calls(net, dtype, on, counts=COUNTS):
    g = torch.Generator().manual_seed(3)
    Fs = [(torch.eye(3, dtype=dtype) + 0.2 * torch.randn(n, 3, 3, generator=g, dtype=dtype)).requires_grad_(True)
          for n in counts]
    vs = [torch.randn(n, 9, generator=g, dtype=dtype) for n in counts]
    with merged_weights(net), frame_mlp_sums(net, on):
        frame = net._frame_mlp
        Xs = [net.fused_network(F)[1] for F in Fs]
    loss = sum((X * v).sum() for X, v in zip(Xs, vs))
    leaves = [*Fs, *lora_parameters(net)]
    grads = torch.autograd.grad(loss, leaves, allow_unused=True)  # None (a gradient never arriving) as zeros
    return [X.detach() for X in Xs], [torch.zeros_like(t) if d is None else d for d, t in zip(grads, leaves)], frame

def rel(a, b):
    return float((a - b).abs().max() / b.abs().max())
"""


def _run(code: str) -> str:
    """``SETUP`` + ``code`` in a fresh Python under Triton's CPU interpreter."""
    return run_interpreted(SETUP + code)


def test_a_frames_sum_gives_the_plain_calls_values_and_gradients():
    _run("""
for dtype, tol in ((torch.float64, 1e-12), (torch.float32, 1e-5)):
    net = net_of(NeuralElasticity, dtype)
    X0, g0, f0 = calls(net, dtype, False)
    X1, g1, f1 = calls(net, dtype, True)
    assert f0 is None and f1 is not None and net._frame_mlp is None  # formed in the block only, and left
    assert all(torch.equal(a, b) for a, b in zip(X1, X0)), "the forward changed"
    assert len(g1) == 3 + 6 and all(float(t.abs().max()) > 0 for t in g1)
    worst = max(rel(a, b) for a, b in zip(g1, g0))
    assert worst < tol, (dtype, worst)
    # each call's partials had a block of the frame's, summed once and freed: the merged weights' gradient
    sink, weights = f1
    assert sink.calls == len(COUNTS) and sink.parts is None and sink.taken == 0
print("ok")
""")


def test_rows_a_call_does_not_store_are_zeros_in_the_sum_whatever_the_blocks_held():
    """The blocks are made uninitialised (torch.empty; here full of 7.0), and the rows past a call's programs are
    zeroed once a pass (past the first call's programs) and in the blocks of calls with fewer: the 77-particle call
    first, last, in the middle of a frame's backward gives the plain calls' gradients with blocks made full of garbage.
    Negative control: without the zeroing, the garbage enters the sum."""
    _run("""
dtype = torch.float64
net = net_of(NeuralElasticity, dtype)
new_parts, zero = mlp_triton.FrameSum._new_parts, mlp_triton.FrameSum.__dict__["_zero"]  # the staticmethod
def garbage(self):  # what uninitialised blocks may hold
    return torch.full_like(new_parts(self), 7.0)

for counts in ((300, 77, 300), (77, 300, 300), (300, 300, 77)):
    _, g0, _ = calls(net, dtype, False, counts)
    mlp_triton.FrameSum._new_parts = garbage
    try:
        _, g1, _ = calls(net, dtype, True, counts)
        mlp_triton.FrameSum._zero = staticmethod(lambda rows: None)
        _, g2, _ = calls(net, dtype, True, counts)
    finally:
        mlp_triton.FrameSum._new_parts, mlp_triton.FrameSum._zero = new_parts, zero
    assert max(rel(a, b) for a, b in zip(g1, g0)) < 1e-12, counts
    assert max(rel(a, b) for a, b in zip(g2[3:], g0[3:])) > 1e-3, counts  # the garbage rows were summed
print("ok")
""")


def test_negative_controls_an_overwriting_backward_and_a_sum_that_never_arrives_change_the_gradients():
    _run("""
dtype = torch.float64
net = net_of(NeuralElasticity, dtype)
_, g0, _ = calls(net, dtype, False)
block_for = mlp_triton.FrameSum.block_for

def one_block(self, task, rows):  # every call's partials into the first block: the frame keeps the last call's only
    block = block_for(self, task, rows)
    self.taken = 1
    return self.parts[0]

mlp_triton.FrameSum.block_for = one_block
try:
    _, g1, _ = calls(net, dtype, True)
finally:
    mlp_triton.FrameSum.block_for = block_for
bad = max(rel(a, b) for a, b in zip(g1[3:], g0[3:]))
assert bad > 1e-3, bad  # the LoRA gradients lose the earlier calls
assert max(rel(a, b) for a, b in zip(g1[:3], g0[:3])) < 1e-12  # dz does not go through the rows

backward = mlp_triton._FrameWeights.backward
mlp_triton._FrameWeights.backward = staticmethod(lambda ctx, *g: (None, *g))  # the rows never summed
try:
    _, g2, _ = calls(net, dtype, True)
finally:
    mlp_triton._FrameWeights.backward = backward
assert all(float(t.abs().max()) == 0 for t in g2[3:]), "the LoRA gradients came another way"
_, g3, _ = calls(net, dtype, True)
assert max(rel(a, b) for a, b in zip(g3, g0)) < 1e-12  # and restored
print("ok")
""")


def test_the_block_is_a_noop_without_autograd_for_another_kernel_and_when_off():
    _run("""
dtype = torch.float64
net = net_of(NeuralElasticity, dtype)
with torch.no_grad(), merged_weights(net), frame_mlp_sums(net):
    assert net._frame_mlp is None
with frame_mlp_sums(net, enabled=False):
    assert net._frame_mlp is None
net.mlp_kernel = "torch"
with frame_mlp_sums(net):
    assert net._frame_mlp is None
net.mlp_kernel = "triton_tf32"
with frame_mlp_sums(net):
    outer = net._frame_mlp
    with frame_mlp_sums(net):
        assert net._frame_mlp is outer  # a nested block reuses the outer frame's
    assert net._frame_mlp is outer
assert net._frame_mlp is None
sink, weights = mlp_triton.frame_weights([l.weight for l in mlp_triton.check(net.mlp)])
z = torch.zeros(10, 13, dtype=dtype)
try:
    mlp_triton.mlp(z, weights, "ieee", programs=4, sink=sink)
except ValueError as exc:
    assert "frame sum of 8 programs" in str(exc), exc
else:
    raise AssertionError("a call of other programs than the frame's was taken")
print("ok")
""")


def test_a_rollouts_gradients_with_the_frame_sums_equal_the_plain_frames():
    _run("""
from gca.sim import MPMSolver, SimConfig, rollout
dtype = torch.float64
""" + LAW_SCENE + """

def grads(on):
    solver = MPMSolver(SimConfig(n_grid=8, dt=1e-3, bound=1, boundary="sticky", friction=0.0, dtype="float64",
                                 max_refine=1))
    solver.frame_mlp_grads = on
    v = v0.clone().requires_grad_(True)
    out = rollout(solver, material, x0, v, vol, vol * 1000.0, 6, 3, checkpoint=True)
    loss = (out.x[-1] * torch.linspace(0.5, 1.5, n, dtype=dtype)[:, None]).sum() + (out.F[-1] ** 2).sum()
    params = [p for p in material.parameters() if p.requires_grad]
    return out.x.detach(), torch.autograd.grad(loss, [v, *params])

made = []
init = mlp_triton.FrameSum.__init__
mlp_triton.FrameSum.__init__ = lambda self, *a: (made.append(1), init(self, *a))[1]
x0_, g0 = grads(False)
assert not made
x1_, g1 = grads(True)
assert len(made) >= 2 * 2, made  # two networks, each frame's recompute (two frames) at least
assert torch.equal(x0_, x1_)
assert len(g1) == 1 + 12 and all(float(t.abs().max()) > 0 for t in g1)
worst = max(rel(a, b) for a, b in zip(g1, g0))
assert worst < 1e-10, worst

def terms(on, checkpoint, reset=True):
    # the term shares' way (gca.train.objective): one kept graph differentiated per term, then again
    solver = MPMSolver(SimConfig(n_grid=8, dt=1e-3, bound=1, boundary="sticky", friction=0.0, dtype="float64",
                                 max_refine=1))
    solver.frame_mlp_grads = on
    out = rollout(solver, material, x0, v0, vol, vol * 1000.0, 6, 3, checkpoint=checkpoint)
    t1 = (out.x[-1] * torch.linspace(0.5, 1.5, n, dtype=dtype)[:, None]).sum()
    t2 = (out.F[-1] ** 2).sum()
    params = [p for p in material.parameters() if p.requires_grad]
    own = mlp_triton.FrameSum.block_for, mlp_triton.FrameSum.sum_of
    if not reset:  # the control: a new pass continues the earlier pass's blocks and sums them with its own
        def stale_block(self, task, rows):
            self.task = task
            if self.parts is None:
                self.parts = torch.zeros(4 * self.calls, self.programs, sum(self.sizes), dtype=self.dtype)
            self.taken += 1
            return self.parts[self.taken - 1]

        def stale_sum(self, task):
            return list(self.parts[:self.taken].reshape(-1, self.parts.shape[2]).sum(0).split(self.sizes))

        mlp_triton.FrameSum.block_for, mlp_triton.FrameSum.sum_of = stale_block, stale_sum
    try:
        return [torch.autograd.grad(t, params, retain_graph=True) for t in (t1, t2, t1)]
    finally:
        mlp_triton.FrameSum.block_for, mlp_triton.FrameSum.sum_of = own

for checkpoint in (True, False):
    plain = terms(False, checkpoint)
    summed = terms(True, checkpoint)
    worst = max(rel(a, b) for A, B in zip(summed, plain) for a, b in zip(A, B))
    assert worst < 1e-10, (checkpoint, worst)
    stale = terms(True, checkpoint, reset=False)
    off = max(rel(a, b) for a, b in zip(stale[1], plain[1]))
    assert off > 1e-4, (checkpoint, off)  # the second pass counted the first's partials
print("ok")
""")
