"""Training knobs (params.yaml sections ``train`` and ``velocity``)."""

from __future__ import annotations

import dataclasses
import math

from gca.config import NOT_A_PARAM
from gca.laws.neural import MLP_KERNELS


#: train.matmul_precision's values: torch.set_float32_matmul_precision levels (``medium``, bfloat16, is not offered)
MATMUL_PRECISIONS = ("highest", "high")

#: train's knobs that choose how the same numbers are computed, not which (the same law and gradient to float
#: rounding, tested: tests/test_sim_rollout.py's reverse sweep, tests/test_laws_mlp_kernel.py), with the values at which
#: each is so (None: any value). A grid state does not record them (``gca.pipeline.grid._made_under``): one made
#: before a knob existed, or under another of these values, goes on under this one, as one made on another machine
#: does (float32 noise). ``matmul_precision: high`` and ``mlp_kernel: triton_tf32`` (TF32) are not rounding-equal,
#: so they are recorded.
EXECUTION_ONLY = {"reverse_sweep": None, "loss_chunk_frames": None, "mlp_kernel": ("torch", "warp", "simt"),
                  "matmul_precision": ("highest",)}


@dataclasses.dataclass(frozen=True)
class TrainConfig:
    """Optimisation of the constitutive law from video (NeuMA recipe + GCA losses).

    Attributes:
        iterations: optimiser steps (one full rollout + backward each).
        lr_elasticity, lr_plasticity: Adam learning rates of the two networks' trainable weights.
        lr_explicit: learning rate of explicit-law parameters (log E, nu, ...) for the PAC-NeRF rows.
        cosine_floor: final learning rate as a fraction of the initial one (cosine decay).
        grad_clip: max global gradient norm (NeuMA: 1.0 synthetic).
        curriculum_start: fraction of the video's frames supervised at the first iteration.
        curriculum_until: fraction of the iterations after which every frame is supervised.
        lambda_color: weight of the pixel colour L2 loss.
        lambda_depth_l1: weight of the L1 monocular-depth loss (PAC-NeRF + depth row).
        cpr_every: apply CPR on every n-th supervised frame.
        term_shares_every: every k-th iteration (0 = never) also each declared loss term's gradient norm and
            its cosine with the total gradient (``share/<term>/norm|cos`` in the history and MLflow; one backward
            pass per image term on those iterations, the total their sum; ``Objective.gradient(shares=True)``).
        checkpoint_every: save a resumable checkpoint every n iterations.
        max_spread_growth: a rollout whose particles spread further from their centre of mass than
            at rest by more than this [m] is treated as diverged (particles flying away).
        seeds: one training run per seed and method (params ``train.seeds``); the report averages a
            (scene, method) over its seeds (mean and sample std).
        seed: the seed of this run, one of ``seeds`` (LoRA's A matrices, CPR's particle subset); set per
            run by the train stage (default: the first of ``seeds``).
        max_rejections: updates after which the rollout diverged that are taken back and retaken with a
            smaller learning rate, in a row, before the run is declared diverged (0: the first
            divergence ends the run).
        backtrack_factor: learning-rate multiplier applied at each rejected update (for the rest of the run).
        optimizer: the GCA-recipe methods' optimiser (params ``train.optimizer``): ``radam`` (default) or ``adam``;
            NeuMA's recipe always uses ``radam`` (:func:`neuma_recipe`). Interpretation: the paper names no optimiser;
            GCA adapts the prior with NeuMA's LoRA scheme, whose published recipe is RAdam, and with one optimiser
            for both, Table 1 compares their objectives. Adam at these learning rates (the default until session 14)
            diverged on the calibration scene calib_torus (benchmarks/NOTES.md, session 14).
        frame_decay_start, frame_decay_until, frame_decay_every: NeuMA's rollout weighting (:func:`frame_weights`):
            video frame j weighs ``decay ** (j // (frame_decay_every * n_video))``, decay rising linearly from
            ``frame_decay_start`` to 1 over the first ``frame_decay_until`` of the iterations; start 1 = off.
        neuma_lr_scale: multiplies NeuMA's published learning rates (:func:`neuma_recipe`); 1 = as published. A
            tuning knob (``gca.pipeline.tuning``): NeuMA's rates are its recipe's, not ``lr_elasticity``'s.
        reverse_sweep: differentiate the rollout frame by frame, last first, while the frames' losses are evaluated
            (``gca.sim.rollout.ReverseSweep``; on CUDA the simulator's backward then overlaps the losses' host work)
            instead of one autograd pass after all of them; the same gradient up to float rounding. Term-share
            iterations take the autograd pass (each term is differentiated through the whole rollout there).
        loss_chunk_frames: supervised video frames whose losses are evaluated and differentiated in one call, the
            chunks last first (0: the whole horizon in one; ``gca.train.objective.Objective._frame_losses``): each
            chunk's terms are one call on [T, ...] tensors, the launches of one frame (NOTES session 40); a chunk keeps
            its frames' loss graphs (RDGA's soft ranks of every match) until its backward, and a swept rollout's
            adjoints start once the first chunk's are queued. The same loss and gradient to float rounding.
        matmul_precision: torch's float32 matrix-product precision while training
            (``torch.set_float32_matmul_precision``, restored after): ``highest`` (default: FP32 products) or
            ``high`` (TF32 tensor cores on CUDA: 10 mantissa bits in the neural law's products; on a CPU torch may
            use its own reduced-precision kernels). A speed option, off by default, measured side by side in
            ``benchmarks/bench_law_precision.py``; whether its deviation is acceptable is decided on calibration
            scenes only. Evaluation always runs at ``highest`` (a separate stage; a frame graph captured under one
            precision is never replayed under another, ``gca.sim.graph.FrameGraphs.matches``).
        mlp_kernel: how the neural laws run their MLP while training (``NeuralElasticity.mlp_kernel``, set on the
            run's networks for the run and restored after): ``torch`` (default), ``simt`` (the forward one thread
            per particle, torch's backward; ``gca.laws.mlp_kernel.simt_mlp``) or ``warp`` (one tile kernel each
            way); both measured slower on the H100 (NOTES s34-35). The same law to float rounding; a speed option
            measured in ``benchmarks/bench_mlp.py``. ``triton_tf32`` (one fused Triton kernel each way,
            ``gca.laws.mlp_triton``): faster on an H200 (NOTES s37) but TF32 products, so not the same numbers,
            and recorded in a grid's state. params.yaml's paper profile runs it (adopted in session 44 by the
            precision rule on the calibration scenes, ``benchmarks/precision_decision.py``), its CI profile torch;
            the dataclass default is torch, the CI value, so a config built in code runs on a CPU. A run on a
            device the kernel cannot use stops before reading data (``gca.laws.neural.mlp_kernel_problem``).
            Evaluation runs torch's.
        keep: which law the run returns: "best", the one with the lowest training loss over the whole
            video among those evaluated (the final law is evaluated once more for it), or "last", the
            final iterate. Selection uses the training objective only, never the ground truth.
    """

    iterations: int = 200
    # the tuned knobs (tuning/record.json: GCA trial 4, PAC-NeRF-style trial 1, NeuMA trial 1; before: 8e-3, 8e-4,
    # 2e-2, lambda_depth_l1 1.0, neuma_lr_scale 1.0): params.yaml holds the same (test_pipeline_schema)
    lr_elasticity: float = 0.0037684174767120488
    lr_plasticity: float = 0.0003768417476712049
    lr_explicit: float = 0.0030879228346255643
    cosine_floor: float = 0.025
    grad_clip: float = 1.0
    curriculum_start: float = 0.3
    curriculum_until: float = 0.33
    lambda_color: float = 1.0
    lambda_depth_l1: float = 0.641716702733418
    cpr_every: int = 2
    checkpoint_every: int = 10
    max_spread_growth: float = 0.5
    seeds: tuple[int, ...] = (0,)
    seed: int | None = dataclasses.field(default=None, metadata=NOT_A_PARAM)  # set per run, not in params
    max_rejections: int = 3
    backtrack_factor: float = 0.5
    keep: str = "best"
    term_shares_every: int = 20
    neuma_lr_scale: float = 1.7511264560616377
    optimizer: str = "radam"
    reverse_sweep: bool = True
    loss_chunk_frames: int = 8
    matmul_precision: str = "highest"
    mlp_kernel: str = "torch"
    frame_decay_start: float = dataclasses.field(default=1.0, metadata=NOT_A_PARAM)  # set by the method's recipe
    frame_decay_until: float = dataclasses.field(default=0.33, metadata=NOT_A_PARAM)  # set by the method's recipe
    frame_decay_every: float = dataclasses.field(default=0.2, metadata=NOT_A_PARAM)  # set by the method's recipe

    def __post_init__(self):
        if isinstance(self.term_shares_every, bool) or not isinstance(self.term_shares_every, int) \
                or self.term_shares_every < 0:
            raise ValueError(f"train.term_shares_every must be an integer >= 0, got {self.term_shares_every!r}")
        seeds = check_seeds(self.seeds)
        object.__setattr__(self, "seeds", seeds)
        if self.seed is None:
            object.__setattr__(self, "seed", seeds[0])
        elif self.seed not in seeds:
            raise ValueError(f"train.seed {self.seed!r} is not one of train.seeds {list(seeds)} "
                             "(params name the seeds; each run takes one)")
        if self.optimizer not in ("adam", "radam"):
            raise ValueError(f"train.optimizer must be 'adam' or 'radam', got {self.optimizer!r}")
        if not 0.0 < self.frame_decay_start <= 1.0 or not 0.0 < self.frame_decay_every <= 1.0:
            raise ValueError("train.frame_decay_start and frame_decay_every must be in (0, 1]")
        if not (math.isfinite(self.neuma_lr_scale) and self.neuma_lr_scale > 0):
            raise ValueError(f"train.neuma_lr_scale must be > 0, got {self.neuma_lr_scale}")
        if self.matmul_precision not in MATMUL_PRECISIONS:
            raise ValueError(f"train.matmul_precision must be one of {list(MATMUL_PRECISIONS)}, got "
                             f"{self.matmul_precision!r}")
        if isinstance(self.loss_chunk_frames, bool) or not (isinstance(self.loss_chunk_frames, int)
                                                             and self.loss_chunk_frames >= 0):
            raise ValueError(f"train.loss_chunk_frames must be an integer >= 0 (0 = every frame in one call), got "
                             f"{self.loss_chunk_frames!r}")
        if self.mlp_kernel not in MLP_KERNELS:
            raise ValueError(f"train.mlp_kernel must be one of {list(MLP_KERNELS)}, got {self.mlp_kernel!r}")
        if self.keep not in ("best", "last"):
            raise ValueError(f"train.keep must be 'best' or 'last', got {self.keep!r}")
        if self.max_rejections < 0:
            raise ValueError(f"train.max_rejections must be >= 0, got {self.max_rejections}")
        if not 0.0 < self.backtrack_factor < 1.0:
            raise ValueError(f"train.backtrack_factor must be in (0, 1), got {self.backtrack_factor}")


#: NeuMA's published fine-tuning recipe (XJay18/NeuMA at a3e8e663, ``experiments/finetune.py`` and
#: ``experiments/configs/synthetic/finetune-*.yaml``; /work/shared/reference/nclaw-neuma.md section 4.5):
#: RAdam (one per network, weight decay 0), cosine decay to a floor, grad-norm clip 1.0, pixel L2 summed over
#: frames and views, every frame rolled out from the first epoch with the rollout weight
#: ``decay ** ((frame - 1) // decay_steps)``, decay rising 0.5 -> 1 over the first 33% of the epochs,
#: decay_steps 80 of its 400 synthetic frames (here 0.2 of the video). Learning rates (elasticity, plasticity,
#: cosine floor) by base model M0, which NeuMA picks per object as this project picks the prior family:
#: bouncy ball / jelly duck (jelly) 8e-3, 8e-4, 0.025; rubber pawn / clay cat (plasticine) 2e-2, 2e-3, 0.01;
#: honey bottle / sand fish (sand) 5e-3, 5e-4, 0.04. NeuMA has no fluid base model: a fluid family keeps
#: ``train``'s rates. Its 1000 epochs become ``train.iterations`` (the same budget as GCA).
NEUMA_LR: dict[str, tuple[float, float, float]] = {"jelly": (8e-3, 8e-4, 0.025), "plasticine": (2e-2, 2e-3, 0.01),
                                                   "sand": (5e-3, 5e-4, 0.04)}


def neuma_recipe(cfg: TrainConfig, family: str) -> TrainConfig:
    """``cfg`` with NeuMA's optimiser, schedule and rollout weighting (:data:`NEUMA_LR`) for prior ``family``; its
    learning rates x ``cfg.neuma_lr_scale`` (1: as published)."""
    lr_e, lr_p, floor = NEUMA_LR.get(family, (cfg.lr_elasticity, cfg.lr_plasticity, cfg.cosine_floor))
    lr_e, lr_p = lr_e * cfg.neuma_lr_scale, lr_p * cfg.neuma_lr_scale
    return dataclasses.replace(cfg, optimizer="radam", lr_elasticity=lr_e, lr_plasticity=lr_p, cosine_floor=floor,
                               grad_clip=1.0, curriculum_start=1.0, frame_decay_start=0.5, frame_decay_until=0.33,
                               frame_decay_every=0.2)


def frame_weights(cfg: TrainConfig, it: int, n_video: int) -> list[float] | None:
    """Each video frame's loss weight at iteration ``it`` (NeuMA's rollout weighting), or None when off."""
    if cfg.frame_decay_start >= 1.0:
        return None
    ramp = max(1.0, cfg.frame_decay_until * cfg.iterations)
    decay = cfg.frame_decay_start + (1.0 - cfg.frame_decay_start) * min(1.0, it / ramp)
    group = max(1, round(cfg.frame_decay_every * n_video))
    return [decay ** (j // group) for j in range(n_video)]


def check_seeds(value) -> tuple[int, ...]:
    """``train.seeds`` as a tuple: a non-empty list of distinct integers >= 0 (a ValueError otherwise)."""
    seeds = tuple(value) if isinstance(value, (list, tuple)) else (value,)
    if not seeds or any(isinstance(s, bool) or not isinstance(s, int) or s < 0 for s in seeds) \
            or len(set(seeds)) != len(seeds):
        raise ValueError(f"train.seeds must be a non-empty list of distinct integers >= 0, got {value!r}")
    return seeds


def run_dir_name(method: str, seed: int) -> str:
    """The folder and metrics-file name of one (method, seed) run: ``gca`` for seed 0, ``gca@seed2`` otherwise
    (``runs/<scene>/<name>/``, ``metrics/eval/<scene>/<name>.json``: what the report stage reads back)."""
    return method if seed == 0 else f"{method}@seed{seed}"


@dataclasses.dataclass(frozen=True)
class VelocityConfig:
    """Initial velocity estimation from the first video frames with the prior law (NeuMA stage A).

    Attributes:
        iterations: optimiser steps.
        n_video_frames: how many of the first video frames supervise it.
        lr: Adam learning rate [m/s per step].
        lambda_mask, lambda_color: weights of the silhouette and colour losses.
        angular: also fit an angular velocity about the centre of mass (NeuMA fits v0 only).
        reg_view_axis: weight of the L2 prior on v0's component along the camera axis [(m/s)^-2].
        lambda_track: weight of the point tracks' reprojection error (``gca.train.velocity.track_loss``) [px^-2];
            0 = silhouettes only (NeuMA); 10 chosen on the calibration scenes (benchmarks/NOTES.md s22).
        track_k: particles carrying each tracked point [count].
        track_huber_px: the Huber loss's quadratic zone [px].
    """

    iterations: int = 100
    n_video_frames: int = 8
    lr: float = 0.5
    lambda_mask: float = 1.0
    lambda_color: float = 0.0
    angular: bool = True
    reg_view_axis: float = 0.0
    lambda_track: float = 10.0
    track_k: int = 4
    track_huber_px: float = 2.0
