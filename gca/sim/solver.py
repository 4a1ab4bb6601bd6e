"""MLS-MPM solver: configuration and the torch <-> warp autograd bridge of one step.

The constitutive law lives in torch (``tau = law(F)``); warp does the transfers. One call of
:meth:`MPMSolver.step` is one ``torch.autograd.Function``:

- forward: P2G, grid update and G2P with no tape, into freshly allocated output tensors (nothing
  that needs gradients is overwritten). Without autograd the grid buffers are reused scratch space;
  with it (``keep_grid``, the default) the step's grid (node momenta, masses and velocities, ~7 floats
  per node: 1.2 MB at 32^3, 8.4 MB at 64^3) is kept for its backward;
- backward: the adjoint kernels of G2P, the grid update and P2G run in reverse order on the kept grid,
  giving the gradients with respect to ``x, v, C, F, tau``. The reference (``keep_grid = False``)
  recomputes the step under a local ``wp.Tape`` from the saved inputs instead, which costs a second
  P2G (the step's most expensive kernel), grid update and G2P per step; both give the same gradients
  (tested). Gradients are returned as computed: never zeroed or NaN-filtered.

In training each frame's steps already run twice (the forward pass, then the recompute of a
checkpointed or CUDA-graphed frame in backward), so keeping the grid within the recompute saves a
third pass of the transfers at the price of one frame's grids in memory.

The grid stash (``step(..., grid=(mv, m))``, driven by :class:`gca.sim.graph.FrameGraphs` and the rollout,
``stash_mib``): the forward pass, run without autograd, scatters each step's P2G into the given buffers (mv, m),
which the caller keeps; the recompute then takes each step's grid from them instead of running P2G again (grid
update and G2P only), and its backward runs on that grid as with ``keep_grid``. The same gradients: bitwise on
the CPU, where P2G's sums run in one order (tested); on a GPU the stash is the forward's own grid, which a
recompute would reproduce only to the atomics' rounding. It costs 4 floats per node and step (0.69 MB at 32^3).

``vol`` and ``mass`` are constants of the simulation (no gradient).
"""

from __future__ import annotations

import copy
import dataclasses
from typing import Sequence

import torch
import warp as wp
from torch.autograd.function import once_differentiable

from gca.sim.fused_step import make_fused_step_kernels
from gca.sim.graph import FrameGraphs, GraphCache
from gca.sim.kernels import BOUNDARY_KINDS, KERNELS, PAD, grid_size, launch_blocks
from gca.warp_stream import on_torch_stream as _stream

_WHERE = "gca/sim/solver.py"
_TORCH_DTYPES = {"float32": torch.float32, "float64": torch.float64}


@dataclasses.dataclass(frozen=True)
class SimConfig:
    """Knobs of the MPM simulator (params.yaml section ``sim``).

    Defaults are params.yaml's values (paper profile where it differs; tests/test_pipeline_schema.py checks).
    """

    n_grid: int = 32  # grid cells per axis on the unit cube; dx = 1 / n_grid [m]
    dt: float = 5e-4  # time step [s]
    gravity: Sequence[float] = (0.0, -9.8, 0.0)  # body acceleration [m/s^2]
    bound: int = 2  # wall thickness: nodes within this many cells of a face obey the wall [cells]
    boundary: str = "friction"  # wall condition: sticky | slip | friction
    friction: float = 0.4  # Coulomb coefficient mu_b of the "friction" walls [-]
    clip: float = 0.5  # positions are clamped to [clip*dx, 1 - clip*dx] [cells]
    eps_mass: float = 0.0  # added to node mass in v = mv / (m + eps) [kg]
    min_node_mass: float = 1e-15  # lighter nodes count as empty: float32 adjoint of mv/m overflows below ~1e-18 [kg]
    cfl: float = 0.5  # refuse dt > cfl * dx / (c + |v|max) [-]
    max_clamped_fraction: float = 0.1  # rollout raises if more particles sit on the clamp [-]
    dtype: str = "float32"  # float32 | float64 (float64 for gradient checks)
    cuda_graphs: bool = True  # replay each frame from CUDA graphs on a GPU (gca.sim.graph) [-]
    max_refine: int = 4  # a law breaking the CFL bound at dt runs k <= max_refine times smaller steps (same frames); 1 = refuse [-]

    def __post_init__(self):
        object.__setattr__(self, "gravity", tuple(float(g) for g in self.gravity))
        problems = []
        if int(self.n_grid) != self.n_grid or self.n_grid < 4:
            problems.append(f"n_grid={self.n_grid} must be an integer >= 4")
        if not self.dt > 0:
            problems.append(f"dt={self.dt} must be > 0")
        if len(self.gravity) != 3:
            problems.append(f"gravity={self.gravity} must have 3 components")
        if int(self.bound) != self.bound or not 0 <= self.bound < self.n_grid // 2:
            problems.append(f"bound={self.bound} must be an integer in [0, n_grid/2)")
        if self.boundary not in BOUNDARY_KINDS:
            problems.append(f"boundary={self.boundary!r} must be one of {sorted(BOUNDARY_KINDS)}")
        if self.friction < 0:
            problems.append(f"friction={self.friction} must be >= 0")
        if not 0 <= self.clip < self.n_grid / 2:
            problems.append(f"clip={self.clip} must be in [0, n_grid/2) cells")
        if self.min_node_mass < 0:
            problems.append(f"min_node_mass={self.min_node_mass} must be >= 0")
        if self.eps_mass < 0 or not 0 < self.cfl <= 1 or not 0 < self.max_clamped_fraction <= 1:
            problems.append("need eps_mass >= 0, 0 < cfl <= 1, 0 < max_clamped_fraction <= 1")
        if int(self.max_refine) != self.max_refine or self.max_refine < 1:
            problems.append(f"max_refine={self.max_refine} must be an integer >= 1")
        if self.dtype not in _TORCH_DTYPES:
            problems.append(f"dtype={self.dtype!r} must be one of {sorted(_TORCH_DTYPES)}")
        if problems:
            raise ValueError(f"{_WHERE}: bad SimConfig: " + "; ".join(problems))

    @property
    def dx(self) -> float:
        """Cell size [m]."""
        return 1.0 / self.n_grid

    @property
    def clamp_range(self) -> tuple[float, float]:
        """Positions are clamped to this range on every axis [m]."""
        return self.clip * self.dx, 1.0 - self.clip * self.dx

    @property
    def torch_dtype(self) -> torch.dtype:
        return _TORCH_DTYPES[self.dtype]


class MPMSolver:
    """One MLS-MPM step on the unit cube, differentiable through torch autograd.

    Args:
        cfg: simulator configuration.
        device: torch device of the state tensors ("cpu" or "cuda[:k]").
    """

    keep_grid: bool = True  # backward from the forward's kept grid; False: recompute the step under a tape
    # the grid stash's budget per rollout [MiB]: a rollout whose frames' stashed grids (mv, m of every step) fit keeps
    # them from its forward pass, so that its frames' recomputes skip P2G (the step's costliest kernel); 0 = off. At the
    # paper profile (32^3, 800 steps) a rollout stashes ~550 MB. Needs keep_grid (the reference path recomputes all).
    # The budget is per rollout, not per device: processes packed on one GPU each keep their own (NOTES session 46)
    stash_mib: float = 1536.0
    # forward P2G with a thread per (particle, node) (kernels.p2g_nodes) instead of per particle. Off: measured on the
    # H100 (benchmarks/bench_p2g.py, NOTES session 13) it is faster only for particles in random order (30k: 60 vs
    # 82 us) and 2x slower for the lattice-ordered particles the pipeline samples (70 vs 35 us); ~7x slower on a CPU
    split_p2g: bool = False
    # steps of an analytic law (gca.laws.fused.AnalyticStress) where no gradient is asked for go through
    # :meth:`step_fused` (gca.sim.fused_step: the stress inside P2G, three kernels), a purely elastic material's whole
    # frame through :meth:`frame_fused` (2 n + 1 kernels for n steps); False: the generic step
    fuse_analytic: bool = True
    # a purely elastic frame through frame_fused (True), step by step through step_fused (False), or None: on CUDA only
    # (measured, NOTES session 30: 0.055 vs 0.062 ms per step on the H100 at 30k; 12.3 vs 10.5 ms on a 2-core CPU, where
    # the one-pass kernel compiles worse than the two it replaces)
    fuse_frames: bool | None = None
    # forward P2G summed per thread block in shared memory before the grid's atomics (kernels.scatter_block; the
    # generic step's P2G and the fused step's), True / False, or None: on CUDA only. Off: measured on the H100 (NOTES
    # session 32, bench_p2g) it is slower than the per-particle kernel on the pipeline's lattice-ordered particles
    # (ball at ~64 per cell: 99 vs 59 us; 8 per cell: 51 vs 35 us) although every block's sums went through its window
    block_p2g: bool | None = False
    # forward P2G with warp-aggregated atomics (kernels.p2g_agg, and the fused analytic step's kernels through
    # kernels.scatter_agg: a warp's particles of one stencil base sum their shares by shuffles, one atomic per node
    # and base), True / False, or None: on CUDA only (off CUDA it is p2g). block_p2g, where on, takes precedence.
    # Off: measured on the H200 (NOTES session 46, bench_p2g) at the paper profile's 30k particles on 32^3 it is 8 %
    # faster on the duck's order (~4 lanes per base) and 20 % slower at the ball's density (~2.3); it halves P2G only
    # at 100k / 64^3 on dense orders, where the atomics' contention binds
    agg_p2g: bool | None = False
    # G2P whose adjoint sums a warp's grid cotangents per stencil base before its atomic adds (kernels.g2p_agg; its
    # forward is g2p's plus one __match_any_sync), True / False, or None: on CUDA only. Off: measured slower on every
    # order and size (NOTES session 46: +12 to +167 %)
    agg_g2p: bool | None = False
    # the fused analytic step (frame_fused, step_fused) on a grid whose momentum and mass are interleaved as one vec4 a
    # node, each node's share one 16-byte vector atomic on sm_90+ in float32 (kernels.scatter4, red.global.add.v4.f32;
    # component-wise elsewhere: the same sums), True / False, or None: where the vector reduction runs (float32 on sm_90
    # or later, _resolve_vector). block_p2g and agg_p2g, where on, take precedence. On there by default: measured on
    # the H200 (NOTES session 50, bench_p2g) the scatter 2.5-3.9x faster on every order but the 30k lattice (-4 %),
    # PhysGaussian's job 0.046 -> 0.029 ms/step at 30k / 32^3 and 0.105 -> 0.047 at 100k / 64^3, the same trajectories
    # to 7e-7 (float32 rounding: the atomics' order)
    vec4_p2g: bool | None = None
    # the generic step's forward P2G (a training frame's forward pass, a recompute without the stash; not under a
    # tape) through kernels.p2g4 onto an interleaved vec4 scratch, unpacked into (mv, m) by the grid update
    # (kernels.grid_update_unpack4): the vector atomics of vec4_p2g for the neural laws. True / False, or None: as
    # vec4_p2g's. block_p2g, split_p2g and agg_p2g, where on, take precedence. On there by default with vec4_g2p_adj,
    # by the rule written before their measurement (NOTES session 51, H200, the duck's GCA training with both against
    # neither: 200 iterations solo 113.6 -> 93.7 s, twelve 20-iteration copies packed under MPS 69.4 -> 60.5 s each,
    # the same CD to 2e-6; each switch's own share not measured)
    vec4_step: bool | None = None
    # the step's backward (on a kept or stashed grid) with G2P's adjoint through kernels.g2p4: each node's velocity
    # cotangent added to an interleaved vec4 accumulator by one vector atomic (sm_90+, float32) instead of three scalar
    # atomics, then moved into the velocity grid's gradient by kernels.grid_unpack_adj4. True / False, or None: as
    # vec4_p2g's; agg_g2p, where on, takes precedence. On there by default with vec4_step (NOTES session 51; alone in
    # bench_p2g at 30k particles it was no faster than warp's adjoint, 51-82 -> 69-81 us, and faster at 100k)
    vec4_g2p_adj: bool | None = None
    # the step's backward (on a kept or stashed grid) with P2G's adjoint written out (kernels.p2g_adj: a gather of the
    # grid's cotangents, one thread a particle) instead of warp's generated adjoint of kernels.p2g, which replays the
    # 27 unrolled node updates and differentiates every temporary (34 us a launch of the duck's 30k particles, the
    # fifth kernel of its iteration: NOTES session 52). The same gradients to rounding (another summation order).
    # True / False, or None: on CUDA only. On there by default by the rule written before its measurement (NOTES
    # session 52, H200: 34.4 -> 15.4 us a launch on the duck, 33.8 -> 16.4 on the ball; with hand_g2p_adj a
    # full-horizon iteration's kernels 387 -> 357 ms on the duck, 356 -> 331 on the ball, twelve packed duck trainings
    # -9.5 %, the solo duck 95.2 -> 92.7 s, the same CD to 1e-6)
    hand_p2g_adj: bool | None = None
    # the step's backward with G2P's adjoint written out (kernels.g2p4_adj) where it scatters into the interleaved
    # accumulator (vec4_g2p_adj on, agg_g2p off; elsewhere no effect): warp's generated adjoint of g2p4 was 47.5 us a
    # launch on the duck, the second kernel of its iteration (NOTES session 52). The same gradients to rounding.
    # True / False, or None: on CUDA only. On there by default with hand_p2g_adj (NOTES session 52, H200: 48.2 -> 37.6
    # us a launch on the duck, 37.1 -> 25.2 on the ball)
    hand_g2p_adj: bool | None = None
    # a frame's neural networks on the fused Triton MLP (train.mlp_kernel: triton_tf32) sum their weight gradients once
    # a frame (gca.laws.neural.frame_mlp_sums, gca.laws.mlp_triton.FrameSum: each step's backward stores its programs'
    # partials in a block of the frame's) instead of one reduction and three adds a step (session 52's duck profile:
    # 1604 reductions of 7.0 us and ~4800 adds of 1.6 us a full-horizon iteration). The same gradients to float
    # rounding. On (True) since session 58, with the MLP stash below, by the pair's rule (NOTES session 58, H200: the
    # block form with the stash -15.0 ms a duck full-horizon iteration, -28.2 on the ball, twelve packed duck trainings
    # -3.4 %; alone each ~-4.5 ms, under its own rule; session 57's in-place form -4.2). True / False (not
    # device-resolved: the kernels say where they run; no effect on the torch MLP)
    frame_mlp_grads: bool = True
    # the MLP stash's budget per rollout [MiB]: where a frame keeps its grid stash (stash_mib) and its neural networks
    # run the fused Triton MLP (train.mlp_kernel: triton_tf32), the first frames whose networks' outputs X [n_steps, N,
    # 9] fit also keep them from the forward pass (gca.laws.neural.frame_mlp_stash), and their recomputes launch no MLP
    # forward (1600 of a full-horizon iteration's 3205 at the paper profile: ~8.4 us each packed, NOTES session 57).
    # Bitwise the same gradients (the recompute's inputs are the forward's). ~2.2 MB a step at 30k particles (two
    # networks), ~1.7 GB for the duck's 800 steps: the budget takes the frames that fit. 0 = off. 1024 since session
    # 58 with frame_mlp_grads (the pair's rule above; the duck's peak 2.52 -> 3.57 GiB, H200)
    mlp_stash_mib: float = 1024.0

    def __init__(self, cfg: SimConfig, device: str | torch.device = "cpu"):
        self.cfg = cfg
        self.device = torch.device(device)
        if self.device.type == "cuda" and self.device.index is None:  # warp needs an explicit ordinal
            self.device = torch.device("cuda", torch.cuda.current_device())
        wp.init()
        self.wp_device = wp.device_from_torch(self.device)
        self.k = KERNELS[cfg.dtype]
        self.dtype = cfg.torch_dtype
        self._grids: dict[tuple, tuple] = {}
        self._zero_grids: dict[int, tuple] = {}
        self._scratch_grids: dict[tuple, wp.array] = {}
        self._zero_runs: dict[int, torch.Tensor] = {}
        self._batch: tuple[torch.Tensor, int] | None = None  # (run [N] int32, n_runs) of with_runs
        self._graphs = GraphCache()
        self._refined: dict[int, "MPMSolver"] = {}
        self._windows = wp.zeros(1, dtype=int, device=self.wp_device)  # blocks of the block-summed P2G that took the window

    def refined(self, k: int) -> "MPMSolver":
        """This solver with ``dt / k`` (cached; ``k = 1`` is ``self``): k steps replace each step."""
        if k == 1:
            return self
        if k not in self._refined:
            fine = MPMSolver(dataclasses.replace(self.cfg, dt=self.cfg.dt / k, max_refine=1), self.device)
            self._refined[k] = fine if self._batch is None else fine.with_runs(*self._batch)
        fine = self._refined[k]  # the path switches follow this solver's (a captured CUDA graph keeps its own)
        fine.keep_grid, fine.split_p2g, fine.fuse_analytic = self.keep_grid, self.split_p2g, self.fuse_analytic
        fine.fuse_frames, fine.block_p2g, fine.agg_p2g = self.fuse_frames, self.block_p2g, self.agg_p2g
        fine.agg_g2p, fine.stash_mib, fine.vec4_p2g = self.agg_g2p, self.stash_mib, self.vec4_p2g
        fine.vec4_step, fine.vec4_g2p_adj, fine.hand_p2g_adj = self.vec4_step, self.vec4_g2p_adj, self.hand_p2g_adj
        fine.hand_g2p_adj, fine.frame_mlp_grads = self.hand_g2p_adj, self.frame_mlp_grads
        fine.mlp_stash_mib = self.mlp_stash_mib
        return fine

    def with_runs(self, run: torch.Tensor, n_runs: int) -> "MPMSolver":
        """This solver for a batch of ``n_runs`` independent runs in one launch: every :meth:`step` (and so a
        rollout, a frame, its CUDA graphs) takes ``run`` [N] int32 as the particles' run indices. Pair it with a
        :class:`gca.laws.base.CompositeMaterial` of the runs' materials over the same contiguous slices; each run
        then evolves as it would alone (tested), except that they share the CFL refinement and the health checks.
        """
        batched = copy.copy(self)
        batched._batch = (self._runs(run, run.shape[0], n_runs), int(n_runs))
        batched._graphs, batched._refined = GraphCache(), {}
        batched._windows = wp.zeros(1, dtype=int, device=self.wp_device)  # its own count (block_windows)
        return batched

    def frame_graphs(self, material, n_steps: int, n: int, capture: bool | None = None) -> FrameGraphs:
        """A cached :class:`gca.sim.graph.FrameGraphs` for ``n_steps`` steps of ``material`` on ``n`` particles."""
        return self._graphs.get(self, material, n_steps, n, capture)

    def step(self, x, v, C, F, tau, vol, mass, run=None, n_runs: int = 1, grid=None):
        """Advance the particles by one step of ``cfg.dt``.

        Args:
            x: positions [N, 3] (m, sim frame, in [0, 1]^3).
            v: velocities [N, 3] (m/s).
            C: APIC affine velocity fields [N, 3, 3] (1/s).
            F: elastic deformation gradients [N, 3, 3].
            tau: Kirchhoff stresses of F [N, 3, 3] (Pa).
            vol: initial particle volumes [N] (m^3).
            mass: particle masses [N] (kg).
            run: int32 run index of each particle [N] in [0, n_runs) (default: all 0): ``n_runs`` independent
                simulations in one launch, each on its own grid (``gca.sim.kernels``: runs), equal to stepping
                each run's particles alone (tested). Indices outside the range are clamped to it.
            n_runs: number of runs (grids).
            grid: the grid stash of this step, ``(mv [R G, G, G, 3], m [R G, G, G])`` (:meth:`stash_shapes`; R =
                ``n_runs``): without a gradient to record, P2G scatters into it (zeroed first) and the caller keeps it;
                with one (``keep_grid``), the step takes its grid from it (as the forward made it from these inputs)
                and skips P2G. None: the step's own grid.

        Returns:
            ``(x', v', C', F_trial)`` with the shapes of ``x, v, C, F``; ``F_trial = (I + dt C') F``
            still has to go through the plasticity projection.
        """
        self._check(x, v, C, F, tau, vol, mass)
        if run is None and self._batch is not None:
            run, n_runs = self._batch
        run = self._runs(run, x.shape[0], n_runs)
        grad = torch.is_grad_enabled() and any(t.requires_grad for t in (x, v, C, F, tau))
        keep = self.keep_grid and grad
        if grid is not None:
            grid = self._check_stash(grid, n_runs)
            if grad and not keep:
                raise ValueError(f"{_WHERE}: a stashed grid needs keep_grid for its backward (the reference path "
                                 "recomputes P2G under a tape)")
        return _MPMStep.apply(self, keep, n_runs, run, x, v, C, F, tau, vol, mass, *(grid or ()))

    def stash_shapes(self, n_runs: int | None = None) -> tuple[tuple[int, ...], tuple[int, ...]]:
        """Shapes of one step's grid stash (mv, m) for ``n_runs`` stacked grids (None: this solver's runs, 1 unless
        :meth:`with_runs`)."""
        if n_runs is None:
            n_runs = self._batch[1] if self._batch is not None else 1
        G = grid_size(self.cfg.n_grid)
        return (n_runs * G, G, G, 3), (n_runs * G, G, G)

    def _check_stash(self, grid, n_runs: int) -> tuple[torch.Tensor, torch.Tensor]:
        """The step's grid stash (mv, m), checked against :meth:`stash_shapes`, dtype, device and contiguity."""
        mv, m = grid
        for name, t, shape in zip(("mv", "m"), grid, self.stash_shapes(n_runs)):
            if tuple(t.shape) != shape or t.dtype != self.dtype or t.device.type != self.device.type \
                    or not t.is_contiguous():
                raise ValueError(f"{_WHERE}: the grid stash's {name} must be a contiguous {self.dtype} tensor of shape "
                                 f"{shape} on {self.device}, got {t.dtype} {tuple(t.shape)} on {t.device}")
        return mv, m

    def step_fused(self, x, v, C, F, law, vol, mass, run=None, n_runs: int = 1):
        """:meth:`step` with the analytic law ``law`` evaluated inside P2G (``gca.sim.fused_step``), forward only.

        Args:
            x, v, C, F, vol, mass, run, n_runs: as in :meth:`step` (none of x, v, C, F may require a gradient
                while autograd records: this step has no backward).
            law: a :class:`gca.laws.fused.AnalyticStress` in the solver's dtype and device, moduli [1] or [N].

        Returns:
            ``(x', v', C', F_trial)`` as :meth:`step` with ``tau = law(F)``; equal to it to rounding (tested).
        """
        return self.frame_fused(x, v, C, F, law, vol, mass, 1, run, n_runs)

    def _resolve(self, switch: bool | None) -> bool:
        """A path switch for this solver's device: True / False as set, None: on CUDA only."""
        return self.device.type == "cuda" if switch is None else bool(switch)

    def _resolve_vector(self, switch: bool | None) -> bool:
        """A vector-atomic switch (``vec4_*``): True / False as set, None: where the vector reduction runs (float32 on
        a CUDA device of sm_90 or later; elsewhere the interleaved kernels add component-wise, never measured)."""
        if switch is not None:
            return bool(switch)
        return self.device.type == "cuda" and self.k.T is wp.float32 and self.wp_device.arch >= 90

    @property
    def frames_fused(self) -> bool:
        """Whether a purely elastic frame takes :meth:`frame_fused` (``fuse_frames``, resolved for this device)."""
        return self._resolve(self.fuse_frames)

    @property
    def blocks_p2g(self) -> bool:
        """Whether forward P2G takes the block-summed kernels (``block_p2g``, resolved for this device)."""
        return self._resolve(self.block_p2g)

    @property
    def aggs_p2g(self) -> bool:
        """Whether forward P2G takes the warp-aggregated kernel (``agg_p2g``, resolved for this device)."""
        return self._resolve(self.agg_p2g)

    @property
    def aggs_g2p(self) -> bool:
        """Whether G2P (forward and adjoint) takes the warp-aggregated adjoint (``agg_g2p``, resolved for this
        device)."""
        return self._resolve(self.agg_g2p)

    @property
    def vec4s_p2g(self) -> bool:
        """Whether the fused analytic step scatters onto the interleaved vec4 grid (``vec4_p2g``, resolved for this
        device)."""
        return self._resolve_vector(self.vec4_p2g)

    @property
    def vec4s_step(self) -> bool:
        """Whether the generic step's forward P2G takes the interleaved scratch (``vec4_step``, resolved for this
        device)."""
        return self._resolve_vector(self.vec4_step)

    @property
    def vec4s_g2p_adj(self) -> bool:
        """Whether the step's backward takes ``g2p4``'s adjoint (``vec4_g2p_adj``, resolved for this device)."""
        return self._resolve_vector(self.vec4_g2p_adj)

    @property
    def hands_p2g_adj(self) -> bool:
        """Whether the step's backward takes P2G's written-out adjoint ``p2g_adj`` (``hand_p2g_adj``, resolved for
        this device)."""
        return self._resolve(self.hand_p2g_adj)

    @property
    def hands_g2p_adj(self) -> bool:
        """Whether the step's backward takes G2P's written-out adjoint ``g2p4_adj`` (``hand_g2p_adj``, resolved for
        this device; only where :attr:`vec4s_g2p_adj` and not :attr:`aggs_g2p`)."""
        return self._resolve(self.hand_g2p_adj) and self.vec4s_g2p_adj and not self.aggs_g2p

    def block_windows(self, reset: bool = False) -> int:
        """How many thread blocks of the block-summed P2G (this solver's launches so far, or since the last
        ``reset``) summed their particles in the shared window rather than scattering directly (a host read)."""
        count = int(self._windows.numpy()[0])
        if reset:
            self._windows.zero_()
        return count

    def frame_fused(self, x, v, C, F, law, vol, mass, n_steps: int, run=None, n_runs: int = 1):
        """``n_steps`` steps of a purely elastic material (plasticity the identity, F_e = F_trial) whose law is
        ``law``, in 2 n + 1 kernels (``gca.sim.fused_step``: each step's G2P and the next step's P2G in one pass);
        forward only. Arguments as :meth:`step_fused`.

        Returns:
            ``(x, v, C, F_trial)`` after the last step, equal to ``n_steps`` calls of :meth:`step_fused` with
            F = F_trial between them to rounding (tested; bitwise on the CPU).
        """
        if torch.is_grad_enabled() and any(t.requires_grad for t in (x, v, C, F)):
            raise ValueError(f"{_WHERE}: step_fused / frame_fused have no backward; x, v, C or F requires a gradient "
                             "(use step)")
        if int(n_steps) != n_steps or n_steps < 1:
            raise ValueError(f"{_WHERE}: frame_fused: n_steps={n_steps} must be an integer >= 1")
        self._check(x, v, C, F, F, vol, mass)
        n = x.shape[0]
        for name, t in (("mu", law.mu), ("lam", law.lam)):
            if t.dim() != 1 or t.shape[0] not in (1, n) or t.dtype != self.dtype or t.device.type != self.device.type:
                raise ValueError(f"{_WHERE}: step_fused / frame_fused: {name} must be {self.dtype} of shape [1] or "
                                 f"[{n}] on {self.device}, got {t.dtype} {tuple(t.shape)} on {t.device}")
        if run is None and self._batch is not None:
            run, n_runs = self._batch
        run = self._runs(run, n, n_runs)
        cfg, k = self.cfg, make_fused_step_kernels(self.dtype)
        outs = [torch.empty(t.shape, dtype=t.dtype, device=t.device) for t in (x, v, C, F)]
        with torch.no_grad(), _stream(self.device):
            wx, wv, wC, wF, _, wvol, wmass = self._wrap(x, v, C, F, F, vol, mass)
            wrun = wp.from_torch(run, dtype=wp.int32)
            wouts = [wp.from_torch(o, dtype=ty, requires_grad=False)
                     for o, ty in zip(outs, (self.k.vec3, self.k.vec3, self.k.mat33, self.k.mat33))]
            lo, hi = cfg.clamp_range
            inv_dx, T = 1.0 / cfg.dx, self.k.T
            moduli = [law.kind, wp.from_torch(law.mu, dtype=T), wp.from_torch(law.lam, dtype=T), law.per, law.j_min]
            blocks, aggs = self.blocks_p2g, self.aggs_p2g
            vec4 = self.vec4s_p2g and not (blocks or aggs)
            if vec4:  # the interleaved grid: (mv, m) one vec4 a node
                mvm, gv = self._zeroed_grid4(n_runs)
                grid, update_kernel = [mvm], k.grid_update_zero4
                p2g_stress, g2p_p2g = k.p2g_stress4, k.g2p_p2g4
            else:
                mv, m, gv = self._zeroed_grid(n_runs)
                grid, update_kernel = [mv, m], k.grid_update_zero
                p2g_stress, g2p_p2g = ((k.p2g_stress_block, k.g2p_p2g_block) if blocks else
                                       (k.p2g_stress_agg, k.g2p_p2g_agg) if aggs else (k.p2g_stress, k.g2p_p2g))
            update = [*grid, *self._update_consts(), gv]

            def scatter(kernel, inputs):
                if blocks:
                    launch_blocks(kernel, n, [*inputs, self._windows], self.wp_device)
                else:
                    wp.launch(kernel, dim=n, inputs=inputs, device=self.wp_device)

            try:
                scatter(p2g_stress, [wx, wv, wC, wF, *moduli, wvol, wmass, wrun, cfg.dt, inv_dx, cfg.n_grid, *grid])
                wp.launch(update_kernel, dim=gv.shape, inputs=update, device=self.wp_device)
                src = (wx, wF)
                for _ in range(int(n_steps) - 1):
                    scatter(g2p_p2g, [*src, wrun, gv, *moduli, wvol, wmass, cfg.dt, inv_dx, cfg.n_grid, lo, hi,
                                      wouts[0], wouts[3], *grid])
                    wp.launch(update_kernel, dim=gv.shape, inputs=update, device=self.wp_device)
                    src = (wouts[0], wouts[3])
                wp.launch(k.g2p, dim=n, device=self.wp_device,
                          inputs=[src[0], src[1], wrun, gv, cfg.dt, inv_dx, cfg.n_grid, lo, hi, *wouts])
            except BaseException:  # stopped between a scatter and its zeroing update (Ctrl-C, SIGTERM): re-zero
                for a in grid:
                    a.zero_()
                raise
        return tuple(outs)

    def grid(self, x, v, C, tau, vol, mass):
        """P2G only (diagnostics and tests): node masses and momenta of the padded grid.

        Returns:
            ``(m [G, G, G] kg, mv [G, G, G, 3] kg m/s)`` with ``G = n_grid + 3``; node ``I`` (in
            [-1, n_grid + 1], position ``I * dx``) is stored at index ``I + 1``.
        """
        eye = torch.eye(3, dtype=self.dtype, device=self.device).expand(x.shape[0], 3, 3)
        self._check(x, v, C, eye, tau, vol, mass)
        with torch.no_grad(), _stream(self.device):
            args = self._wrap(x, v, C, eye.contiguous(), tau, vol, mass)
            run = wp.from_torch(self._runs(None, x.shape[0], 1), dtype=wp.int32)
            mv, m, _ = self._scratch(requires_grad=False)
            wp.launch(self.k.p2g, dim=x.shape[0], inputs=self._p2g_args(args, run, mv, m), device=self.wp_device)
            return wp.to_torch(m).clone(), wp.to_torch(mv).clone()

    # -- internals -------------------------------------------------------------------------------

    def _check(self, x, v, C, F, tau, vol, mass):
        n = x.shape[0] if x.dim() == 2 else -1
        expected = {"x": (x, (n, 3)), "v": (v, (n, 3)), "C": (C, (n, 3, 3)), "F": (F, (n, 3, 3)),
                    "tau": (tau, (n, 3, 3)), "vol": (vol, (n,)), "mass": (mass, (n,))}
        for name, (t, shape) in expected.items():
            if not isinstance(t, torch.Tensor) or tuple(t.shape) != shape:
                got = tuple(t.shape) if isinstance(t, torch.Tensor) else type(t).__name__
                raise ValueError(f"{_WHERE}: {name} must have shape {shape} (N from x), got {got}")
            if t.dtype != self.dtype or t.device.type != self.device.type:
                raise ValueError(f"{_WHERE}: {name} is {t.dtype} on {t.device}; the solver runs "
                                 f"{self.dtype} on {self.device} (SimConfig.dtype, MPMSolver device)")

    def _wrap(self, x, v, C, F, tau, vol, mass, grads=None):
        """Alias torch tensors as warp arrays; ``grads`` (same order, or None) become their ``.grad``."""
        types = (self.k.vec3, self.k.vec3, self.k.mat33, self.k.mat33, self.k.mat33, self.k.T, self.k.T)
        tensors = (x, v, C, F, tau, vol, mass)
        grads = grads or (None,) * len(tensors)
        return [wp.from_torch(t.contiguous(), dtype=ty, grad=g, requires_grad=g is not None)
                for t, ty, g in zip(tensors, types, grads)]

    def _runs(self, run, n: int, n_runs: int) -> torch.Tensor:
        """The particles' run indices as a contiguous int32 tensor [N] (all 0 when ``run`` is None; cached per N)."""
        if int(n_runs) != n_runs or n_runs < 1:
            raise ValueError(f"{_WHERE}: n_runs={n_runs} must be an integer >= 1")
        if n_runs * grid_size(self.cfg.n_grid) ** 3 >= 2 ** 31:  # the stacked grids' node index (warp's int32; the
            # aggregated kernels' peer key) would overflow
            raise ValueError(f"{_WHERE}: n_runs={n_runs} grids of {grid_size(self.cfg.n_grid)}^3 nodes pass int32's "
                             "node index; use fewer runs per launch")
        if run is None:
            if n_runs != 1:
                raise ValueError(f"{_WHERE}: n_runs={n_runs} needs the particles' run indices (run=)")
            if n not in self._zero_runs:
                self._zero_runs[n] = torch.zeros(n, dtype=torch.int32, device=self.device)
            return self._zero_runs[n]
        if not isinstance(run, torch.Tensor) or tuple(run.shape) != (n,) or run.dtype != torch.int32 \
                or run.device.type != self.device.type:
            got = f"{tuple(run.shape)} {run.dtype} on {run.device}" if isinstance(run, torch.Tensor) else type(run).__name__
            raise ValueError(f"{_WHERE}: run must be an int32 tensor of shape ({n},) on {self.device}, got {got}")
        return run.contiguous()

    def _scratch(self, requires_grad: bool, n_runs: int = 1):
        """Zeroed grid buffers (mv, m, v) of ``n_runs`` stacked grids, reused across steps; never needed after a step."""
        key = (requires_grad, n_runs)
        if key not in self._grids:
            G = grid_size(self.cfg.n_grid)
            shape = (n_runs * G, G, G)
            self._grids[key] = tuple(
                wp.zeros(shape, dtype=ty, device=self.wp_device, requires_grad=requires_grad)
                for ty in (self.k.vec3, self.k.T, self.k.vec3))
        for a in self._grids[key]:
            a.zero_()
            if requires_grad:
                a.grad.zero_()
        return self._grids[key]

    def _zeroed_grid(self, n_runs: int):
        """Grid buffers (mv, m, v) of ``n_runs`` stacked grids for :meth:`step_fused`: mv and m are zero when made
        and its grid update leaves them zero, so no step zeroes them (and a CUDA graph holds no memset)."""
        if n_runs not in self._zero_grids:
            G = grid_size(self.cfg.n_grid)
            self._zero_grids[n_runs] = tuple(wp.zeros((n_runs * G, G, G), dtype=ty, device=self.wp_device)
                                             for ty in (self.k.vec3, self.k.T, self.k.vec3))
        return self._zero_grids[n_runs]

    def _zeroed_grid4(self, n_runs: int):
        """:meth:`_zeroed_grid` of the interleaved layout (``vec4_p2g``): (mvm [n_runs G, G, G] vec4: mv in components
        0-2, m in 3; v [n_runs G, G, G] vec3), mvm zero when made and left zero by ``grid_update_zero4``."""
        return self._scratch_grid("fused", n_runs), self._scratch_grid("fused_v", n_runs, self.k.vec3)

    def _scratch_grid(self, use: str, n_runs: int, dtype=None):
        """A scratch grid [n_runs G, G, G] of ``dtype`` (default: the interleaved vec4), zero when made and left zero
        by its user: ``"fused"``, ``frame_fused``'s (mv, m) (``grid_update_zero4``), with ``"fused_v"`` its
        velocities (vec3, overwritten each step); ``"p2g"``, the forward's (mv, m) of ``vec4_step``
        (``grid_update_unpack4``); ``"g2p_adj"``, the backward's velocity cotangents of ``vec4_g2p_adj``
        (``grid_unpack_adj4``). One per use and run count, like :meth:`_zeroed_grid`, whatever the stream: a frame's
        warm-up (``gca.sim.graph``) makes it before its capture, so no CUDA graph owns it, and the graphs that replay
        it run one after another. Made during a capture it would belong to that graph: refused."""
        key = (use, n_runs)
        if key not in self._scratch_grids:
            if self.device.type == "cuda" and torch.cuda.is_current_stream_capturing():
                raise RuntimeError(f"{_WHERE}: the interleaved scratch {key} would be made inside a CUDA graph capture "
                                   "(its warm-up did not run this path); run the frame once eagerly first")
            G = grid_size(self.cfg.n_grid)
            self._scratch_grids[key] = wp.zeros((n_runs * G, G, G), dtype=dtype or self.k.vec4,
                                                device=self.wp_device)
        return self._scratch_grids[key]

    def _update_consts(self) -> list:
        """The grid update's arguments between the grid and the velocities: gravity, dt, eps, m_min, n_grid, bound,
        the wall kind and its friction."""
        cfg = self.cfg
        return [self.k.vec3(*cfg.gravity), cfg.dt, cfg.eps_mass, cfg.min_node_mass, cfg.n_grid, cfg.bound,
                BOUNDARY_KINDS[cfg.boundary], cfg.friction]

    def _update_args(self, mv, m, gv) -> list:
        """Arguments of the grid update (``grid_update``, or ``grid_update_zero`` of the fused step) on the wrapped
        grid (mv, m) into velocities ``gv``."""
        return [mv, m, *self._update_consts(), gv]

    def _p2g_args(self, args, run, mv, m):
        x, v, C, _, tau, vol, mass = args
        return [x, v, C, tau, vol, mass, run, self.cfg.dt, 1.0 / self.cfg.dx, self.cfg.n_grid, mv, m]

    def _kernel_args(self, args, run, grid, outs) -> list[tuple]:
        """(kernel, dim, arguments) of P2G, grid update and G2P, in launch order.

        Args:
            args: the wrapped inputs (x, v, C, F, tau, vol, mass).
            run: the wrapped run indices [N] (int32).
            grid: the wrapped grid buffers (mv, m, v_grid) of the stacked runs' grids, zeroed where P2G accumulates.
            outs: the wrapped outputs (x', v', C', F_trial).
        """
        cfg, k = self.cfg, self.k
        mv, m, gv = grid
        lo, hi = cfg.clamp_range
        n = args[0].shape[0]
        return [(k.p2g, n, self._p2g_args(args, run, mv, m)),
                (k.grid_update, mv.shape, self._update_args(mv, m, gv)),
                (k.g2p_agg if self.aggs_g2p else k.g2p, n,
                 [args[0], args[3], run, gv, cfg.dt, 1.0 / cfg.dx, cfg.n_grid, lo, hi, *outs])]

    def _launch(self, args, run, outs, requires_grad: bool, grid=None, n_runs: int = 1, p2g: bool = True):
        """P2G, grid update, G2P from the wrapped inputs ``args`` into the wrapped ``outs`` (on ``grid``, or on
        the reused scratch buffers). Under a tape (``requires_grad``, the reference backward) P2G is the
        per-particle kernel, whose adjoint the tape replays. ``p2g`` False: the grid's (mv, m) are given (a
        stash), the grid update and G2P only."""
        grid = self._scratch(requires_grad, n_runs) if grid is None else grid
        launches = self._kernel_args(args, run, grid, outs)
        if p2g and not requires_grad and self.vec4s_step and not (self.blocks_p2g or self.split_p2g or self.aggs_p2g):
            (_, dim, p2g_args), (_, nodes, update_args), (g2p, _, g2p_args) = launches
            mvm = self._scratch_grid("p2g", n_runs)  # P2G onto the interleaved scratch, unpacked by the grid update
            try:
                wp.launch(self.k.p2g4, dim=dim, inputs=[*p2g_args[:-2], mvm], device=self.wp_device)
                wp.launch(self.k.grid_update_unpack4, dim=nodes, inputs=[mvm, *update_args], device=self.wp_device)
            except BaseException:  # stopped between the scatter and its unpacking (Ctrl-C, SIGTERM): re-zero
                mvm.zero_()
                raise
            wp.launch(g2p, dim=dim, inputs=g2p_args, device=self.wp_device)
            return
        for kernel, dim, kargs in launches[0 if p2g else 1:]:
            if kernel is self.k.p2g and not requires_grad and self.blocks_p2g:
                launch_blocks(self.k.p2g_block, dim, [*kargs, self._windows], self.wp_device)  # summed per block first
                continue
            if kernel is self.k.p2g and self.split_p2g and not requires_grad:
                kernel, dim = self.k.p2g_nodes, 27 * dim  # same inputs, a thread per (particle, node)
            elif kernel is self.k.p2g and self.aggs_p2g and not requires_grad:
                kernel = self.k.p2g_agg  # same inputs, one atomic per node and stencil base in a warp
            wp.launch(kernel, dim=dim, inputs=kargs, device=self.wp_device)

    def _new_grid(self, n_runs: int = 1):
        """Fresh grid tensors of ``n_runs`` stacked grids (mv [R G,G,G,3] and m [R G,G,G] zeroed, v_grid [R G,G,G,3]
        uninitialised)."""
        G = grid_size(self.cfg.n_grid)
        to = dict(dtype=self.dtype, device=self.device)
        R = n_runs * G
        return torch.zeros(R, G, G, 3, **to), torch.zeros(R, G, G, **to), torch.empty(R, G, G, 3, **to)

    def _wrap_grid(self, grid, grads=None):
        """Warp views of grid tensors (mv, m, v_grid); ``grads`` (same order, or None) become their ``.grad``."""
        grads = grads or (None,) * 3
        return [wp.from_torch(t, dtype=ty, grad=g, requires_grad=g is not None)
                for t, ty, g in zip(grid, (self.k.vec3, self.k.T, self.k.vec3), grads)]

    def _forward(self, x, v, C, F, tau, vol, mass, run, n_runs: int = 1, keep_grid: bool = False, stash=None):
        """The step's outputs (x', v', C', F_trial), and its grid tensors (mv, m, v_grid) if ``keep_grid``
        (else None). ``stash`` (mv, m): with ``keep_grid`` the step's grid, P2G skipped (the stash replayed);
        without, P2G's target (zeroed here; the stash recorded)."""
        outs = [torch.empty(t.shape, dtype=t.dtype, device=t.device) for t in (x, v, C, F)]
        if stash is not None:
            grid = (*stash, torch.empty_like(stash[0]))
            if not keep_grid:
                for t in stash:
                    t.zero_()
        else:
            grid = self._new_grid(n_runs) if keep_grid else None
        with _stream(self.device):
            args = self._wrap(x, v, C, F, tau, vol, mass)
            wouts = [wp.from_torch(o, dtype=ty, requires_grad=False)
                     for o, ty in zip(outs, (self.k.vec3, self.k.vec3, self.k.mat33, self.k.mat33))]
            self._launch(args, wp.from_torch(run, dtype=wp.int32), wouts, requires_grad=False,
                         grid=None if grid is None else self._wrap_grid(grid), n_runs=n_runs,
                         p2g=stash is None or not keep_grid)
        return tuple(outs), (grid if keep_grid else None)

    def _backward_from_grid(self, inputs, run, grid, v_outs):
        """Adjoints of G2P, the grid update and P2G, in reverse order, on the forward's kept ``grid``; return the
        gradients for (x, v, C, F, tau). The same launches as ``wp.Tape.backward`` of :meth:`_launch`, without
        replaying the forward first."""
        x, v, C, F, tau, vol, mass = inputs
        # the adjoints accumulate: every gradient buffer zeroed, in one memset (views of one buffer); a step's backward
        # in training is ~100 small kernels, 8 of them were these zeroings (NOTES session 46)
        *v_ins, v_mv, v_m, v_gv = _views(torch.zeros, (x, v, C, F, tau, *grid))
        v_grid = [v_mv, v_m, v_gv]
        # copies: the adjoint of an array store zeroes the stored cotangent, and autograd's must stay intact (one
        # copy kernel for the four)
        cots = _views(lambda n, **to: torch.cat([g.reshape(-1) for g in v_outs]), (x, v, C, F))
        with _stream(self.device):
            args = self._wrap(x, v, C, F, tau, vol, mass, grads=(*v_ins, None, None))
            types = (self.k.vec3, self.k.vec3, self.k.mat33, self.k.mat33)
            outs = [wp.from_torch(torch.empty(t.shape, dtype=t.dtype, device=t.device), dtype=ty, grad=g,
                                  requires_grad=True)
                    for t, ty, g in zip((x, v, C, F), types, cots)]
            wgrid = self._wrap_grid(grid, grads=v_grid)
            wrun = wp.from_torch(run, dtype=wp.int32)
            launches = list(reversed(self._kernel_args(args, wrun, wgrid, outs)))
            if self.vec4s_g2p_adj and not self.aggs_g2p:  # G2P's adjoint scatters into the interleaved accumulator
                (_, dim, g2p_args), rest = launches[0], launches[1:]
                gv = wgrid[2]
                acc = self._scratch_grid("g2p_adj", gv.shape[0] // grid_size(self.cfg.n_grid))
                kargs = [*g2p_args[:4], acc, *g2p_args[4:]]
                try:
                    if self.hands_g2p_adj:  # written out: (x, F, run, grid_v, acc, dt, inv_dx, n_grid, lo, hi), the
                        # outputs' cotangents, then the gradients of x and F it adds to
                        wx, wF = kargs[0], kargs[1]
                        wp.launch(self.k.g2p4_adj, dim=dim, inputs=[*kargs[:10], *(o.grad for o in kargs[10:]),
                                                                    wx.grad, wF.grad], device=self.wp_device)
                    else:
                        wp.launch(self.k.g2p4, dim=dim, inputs=kargs, adj_inputs=[_adjoint(a) for a in kargs],
                                  adjoint=True, device=self.wp_device)
                    wp.launch(self.k.grid_unpack_adj4, dim=gv.shape, inputs=[acc, gv.grad], device=self.wp_device)
                except BaseException:  # stopped between the scatter and its unpacking: re-zero
                    acc.zero_()
                    raise
                launches = rest
            if self.hands_p2g_adj:  # P2G's adjoint last, written out: the gather adds into the inputs' gradients
                (_, dim, p2g_args), launches = launches[-1], launches[:-1]
            for kernel, dim_k, kargs in launches:
                wp.launch(kernel, dim=dim_k, inputs=kargs, adj_inputs=[_adjoint(a) for a in kargs], adjoint=True,
                          device=self.wp_device)
            if self.hands_p2g_adj:
                wx, wv, wC, wtau, *_, wmv, wm = p2g_args
                wp.launch(self.k.p2g_adj, dim=dim, inputs=[*p2g_args[:-2], wmv.grad, wm.grad, wx.grad, wv.grad,
                                                           wC.grad, wtau.grad], device=self.wp_device)
        return tuple(v_ins)

    def _backward(self, inputs, run, v_outs, n_runs: int = 1):
        """Recompute the step under a tape; return the gradients for (x, v, C, F, tau)."""
        x, v, C, F, tau, vol, mass = inputs
        v_ins = [torch.zeros(t.shape, dtype=t.dtype, device=t.device) for t in (x, v, C, F, tau)]
        with _stream(self.device):
            args = self._wrap(x, v, C, F, tau, vol, mass, grads=(*v_ins, None, None))
            types = (self.k.vec3, self.k.vec3, self.k.mat33, self.k.mat33)
            outs = [wp.from_torch(torch.empty(t.shape, dtype=t.dtype, device=t.device), dtype=ty,
                                  grad=g.contiguous().clone())
                    for t, ty, g in zip((x, v, C, F), types, v_outs)]
            tape = wp.Tape()
            with tape:
                self._launch(args, wp.from_torch(run, dtype=wp.int32), outs, requires_grad=True, n_runs=n_runs)
            tape.backward()
        return tuple(v_ins)


class _MPMStep(torch.autograd.Function):
    """torch.autograd bridge of :meth:`MPMSolver.step` (backward recomputes the step)."""

    @staticmethod
    def forward(ctx, solver, keep_grid, n_runs, run, x, v, C, F, tau, vol, mass, *stash):
        ctx.solver, ctx.n_runs, ctx.n_stash = solver, n_runs, len(stash)
        inputs = tuple(t.contiguous() for t in (x, v, C, F, tau, vol, mass))
        outs, grid = solver._forward(*inputs, run, n_runs=n_runs, keep_grid=keep_grid, stash=stash or None)
        ctx.save_for_backward(*inputs, run, *(grid or ()))
        return outs

    @staticmethod
    @once_differentiable
    def backward(ctx, v_x, v_v, v_C, v_F):
        saved = ctx.saved_tensors
        inputs, run, grid = saved[:7], saved[7], saved[8:]
        cot = (v_x, v_v, v_C, v_F)
        solver = ctx.solver
        v_ins = solver._backward_from_grid(inputs, run, grid, cot) if grid else \
            solver._backward(inputs, run, cot, ctx.n_runs)
        return (None, None, None, None, *v_ins, None, None, *(None,) * ctx.n_stash)


def _views(make, like) -> list[torch.Tensor]:
    """Tensors shaped as ``like`` (one dtype and device) as views of one flat buffer ``make(n, dtype=, device=)``
    of their total size ``n``: one kernel (a memset, a concatenation) where one per tensor was launched."""
    sizes = [t.numel() for t in like]
    flat = make(sum(sizes), dtype=like[0].dtype, device=like[0].device)
    return [part.view(t.shape) for part, t in zip(flat.split(sizes), like)]


def _adjoint(a):
    """The adjoint argument of a kernel argument, as ``wp.Tape`` forms it here: an array's ``.grad`` (None
    without one), None for a value (the step's scalars and the gravity vector get no gradient)."""
    return a.grad if isinstance(a, wp.array) else None


__all__ = ["SimConfig", "MPMSolver", "PAD"]
