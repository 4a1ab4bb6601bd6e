"""The MLP stash (``MPMSolver.mlp_stash_mib``, ``gca.laws.neural.frame_mlp_stash``): a frame's forward pass keeps its
networks' fused-MLP outputs, and the frame's recompute takes them instead of launching the MLP forward again. The
recompute's inputs are the forward's bit for bit, so the gradients must be exactly the grid stash's alone, through the
reverse sweep (training's path) and the graphed frames' autograd (the term shares' path, differentiated twice), with
no MLP forward launched in a stashed frame's recompute; a budget that holds one frame stashes only the first;
negative controls: a perturbed MLP stash changes the gradients (it is read), and a frame calling a network another
number of times than its stash holds raises. In Triton's CPU interpreter (the fused MLP's CPU twin), each case in a
fresh process."""

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
from gca.laws.lora import apply_lora
from gca.laws.neural import MLPStash, NeuralElasticity, NeuralLawConfig, NeuralPlasticity, frame_mlp_stash
from gca.sim import MPMSolver, SimConfig, rollout
from gca.sim.graph import FrameGraphs
torch.manual_seed(0)
dtype = torch.float64

""" + NET_OF + """
""" + LAW_SCENE + """
params = [p for p in material.parameters() if p.requires_grad]
N_STEPS, PER_FRAME = 6, 3

def solver_of(mlp_mib):
    solver = MPMSolver(SimConfig(n_grid=8, dt=1e-3, bound=1, boundary="sticky", friction=0.0, dtype="float64",
                                 max_refine=1))
    solver.mlp_stash_mib = mlp_mib
    return solver

forwards = []  # the fused forward's launches
orig = mlp_triton._fused_mlp_fwd

class Counted:
    def __getitem__(self, grid):
        forwards.append(grid)
        return orig[grid]

mlp_triton._fused_mlp_fwd = Counted()

def swept(solver, perturb=None):
    v = v0.clone().requires_grad_(True)
    for p in params:
        p.grad = None
    del forwards[:]
    out = rollout(solver, material, x0, v, vol, vol * 1000.0, N_STEPS, PER_FRAME, sweep=True)
    made = len(forwards)
    stash = [tuple(s) for s in out.sweep.grids]
    if perturb is not None:
        out.sweep.grids[0][3].mul_(perturb)  # frame 0's plasticity outputs (F_e = F + alpha R sym(X))
    for f in range(out.x.shape[0] - 1, 0, -1):
        x, F = (t[f].detach().requires_grad_() for t in (out.x, out.F))
        loss = (torch.linspace(0.5, 1.5, n, dtype=dtype)[:, None] * x).square().sum() * f + (F ** 2).sum()
        out.sweep.add(f, *torch.autograd.grad(loss, [x, F]))
    out.sweep.finish()
    return out.x, [v.grad, *(p.grad.clone() for p in params)], stash, made, len(forwards) - made
"""


def _run(code: str) -> str:
    return run_interpreted(SETUP + code)


def test_the_fused_mlp_keeps_its_output_and_takes_a_given_one():
    _run("""
layers = mlp_triton.check(material.elasticity.mlp)
w = [l.weight.detach() for l in layers]
z = torch.randn(70, 13, dtype=dtype)
plain = mlp_triton.mlp(z, w, "ieee")
buf = torch.zeros(70, 9, dtype=dtype)
with torch.no_grad():
    kept = mlp_triton.mlp(z, w, "ieee", out=buf)
assert kept.data_ptr() == buf.data_ptr() and torch.equal(buf, plain)
zg, wg = z.clone().requires_grad_(True), [t.clone().requires_grad_(True) for t in w]
cot = torch.randn(70, 9, dtype=dtype)
ref = torch.autograd.grad((mlp_triton.mlp(zg, wg, "ieee") * cot).sum(), [zg, *wg])
del forwards[:]
taken = mlp_triton.mlp(zg, wg, "ieee", given=buf)
assert not forwards and torch.equal(taken, plain)  # no launch: the given output
got = torch.autograd.grad((taken * cot).sum(), [zg, *wg])
assert all(torch.equal(a, b) for a, b in zip(got, ref))  # the backward is the plain call's
for bad in (dict(out=buf[:, :5].contiguous()), dict(given=buf.float()), dict(out=buf, given=buf)):
    try:
        with torch.no_grad():
            mlp_triton.mlp(z, w, "ieee", **bad)
    except ValueError:
        pass
    else:
        raise AssertionError(f"took {list(bad)}")
try:
    mlp_triton.mlp(zg, wg, "ieee", out=buf)
except ValueError as exc:
    assert "no_grad" in str(exc)
else:
    raise AssertionError("out taken where a gradient is recorded")
print("ok")
""")


def test_the_swept_mlp_stash_gives_the_grid_stashs_gradients_bitwise_and_launches_no_recompute_forward():
    _run("""
x_ref, g_ref, stash_ref, fwd_ref, bwd_ref = swept(solver_of(0.0))
x, g, stash, fwd, bwd = swept(solver_of(64.0))
calls = (N_STEPS // PER_FRAME) * PER_FRAME * 2  # two networks, one call a step each
assert fwd_ref == fwd == calls + 1 and bwd_ref == calls, (fwd_ref, fwd, bwd_ref)  # + the CFL's wave speed
assert bwd == 0, bwd  # every frame's recompute took its outputs
assert all(len(s) == 2 for s in stash_ref) and all(len(s) == 4 for s in stash)
assert all(s[k].shape == (PER_FRAME, n, 9) for s in stash for k in (2, 3))
assert torch.equal(x, x_ref)
assert len(g) == 1 + len(params) and all(float(t.abs().max()) > 0 for t in g_ref)
assert all(torch.equal(a, b) for a, b in zip(g, g_ref))
# a budget of one frame's MLP stash: the first frame keeps it, the second recomputes its MLP forwards
per = sum(t.numel() * t.element_size() for t in stash[0][2:])
x1, g1, stash1, _, bwd1 = swept(solver_of(1.5 * per / 2 ** 20))
assert [len(s) for s in stash1] == [4, 2] and bwd1 == PER_FRAME * 2, ([len(s) for s in stash1], bwd1)
assert all(torch.equal(a, b) for a, b in zip(g1, g_ref))
# negative control: the recompute reads the stash (frame 0's plastic outputs 1 % off move the laws' gradients ~1e-5)
_, g_bad, _, _, _ = swept(solver_of(64.0), perturb=1.01)
moved = min(float((a - b).abs().max() / b.abs().max()) for a, b in zip(g_bad[1:], g_ref[1:]))
assert moved > 1e-6, moved
print("ok")
""")


def test_the_graphed_frames_mlp_stash_gives_the_same_gradients_twice():
    _run("""
def grads(solver):
    v = v0.clone().requires_grad_(True)
    out = rollout(solver, material, x0, v, vol, vol * 1000.0, N_STEPS, PER_FRAME, graph=True)
    loss = (out.x[-1] ** 2).sum() + (out.F[1] ** 2).sum() + 0.1 * out.F_trial[2].sum()
    leaves = [v, *params]
    del forwards[:]
    first = torch.autograd.grad(loss, leaves, retain_graph=True)
    return first, torch.autograd.grad(2 * loss, leaves), len(forwards)

(g_ref, _, n_ref), (g, g2, n_mlp) = grads(solver_of(0.0)), grads(solver_of(64.0))
assert n_ref == 2 * N_STEPS * 2 and n_mlp == 0, (n_ref, n_mlp)  # two backward passes, each recomputing every frame
for a, b, c in zip(g, g_ref, g2):
    assert torch.equal(a, b) and torch.equal(c, 2 * b)
print("ok")
""")


def test_a_frame_that_calls_a_network_another_number_of_times_raises():
    _run("""
runner = FrameGraphs(solver_of(64.0), material, PER_FRAME, n, capture=False)
assert len(runner.mlp_nets) == 2 and runner.mlp_stash_bytes == 2 * PER_FRAME * n * 9 * 8
assert FrameGraphs(solver_of(0.0), material, PER_FRAME, n, capture=False).mlp_nets == []
st = MLPStash(torch.zeros(2, n, 9, dtype=dtype), replay=True, name="elasticity")
st.take(), st.take()
try:
    st.take()
except RuntimeError as exc:
    assert "holds 2 calls" in str(exc)
else:
    raise AssertionError("a third call taken")
bufs = [torch.zeros(PER_FRAME, n, 9, dtype=dtype) for _ in range(2)]
F = torch.eye(3, dtype=dtype).expand(n, 3, 3).contiguous()
try:
    with torch.no_grad(), frame_mlp_stash(material, bufs, replay=False):
        material.stress(F)  # one call of PER_FRAME
except RuntimeError as exc:
    assert "called it 1 times" in str(exc), exc
else:
    raise AssertionError("a frame of too few calls passed")
assert material.elasticity._mlp_stash is None and material.plasticity._mlp_stash is None
print("ok")
""")


def test_a_composite_material_or_a_budget_under_one_frame_keeps_no_mlp_stash():
    # session 57's review: a composite's networks each run on their slice of the particles (not the stash's [N] rows):
    # it keeps none, and its rollout runs as with the budget off; a budget under one frame's outputs keeps none either
    _run("""
from gca.laws.base import CompositeMaterial
other = Material(net_of(NeuralElasticity, dtype, cfg), net_of(NeuralPlasticity, dtype, cfg), 1000.0).to(dtype)
composite = CompositeMaterial([material, other], [25, 15])
assert FrameGraphs(solver_of(64.0), composite, PER_FRAME, n, capture=False).mlp_nets == []
per_mib = 2 * PER_FRAME * n * 9 * 8 / 2 ** 20
assert FrameGraphs(solver_of(0.9 * per_mib), material, PER_FRAME, n, capture=False).mlp_nets == []
assert len(FrameGraphs(solver_of(per_mib), material, PER_FRAME, n, capture=False).mlp_nets) == 2
results = []
for mib in (0.0, 64.0):
    v = v0.clone().requires_grad_(True)
    with torch.no_grad():
        plain = rollout(solver_of(mib), composite, x0, v0, vol, vol * 1000.0, N_STEPS, PER_FRAME, graph=True)
    out = rollout(solver_of(mib), composite, x0, v, vol, vol * 1000.0, N_STEPS, PER_FRAME, sweep=True)
    assert all(len(s) == 2 for s in out.sweep.grids)  # grids only
    out.sweep.add(out.x.shape[0] - 1, torch.ones_like(out.x[-1]), None)
    out.sweep.finish()
    results.append((plain.x, v.grad))
assert torch.equal(results[0][0], results[1][0]) and torch.equal(results[0][1], results[1][1])
print("ok")
""")
