"""Optimiser state of a training run: the lr schedule, the undo of a rejected update, the best law seen and
the checkpoint that holds them all, so an interrupted run resumes exactly where it stopped."""

from __future__ import annotations

import copy
import math
from pathlib import Path

import torch

from gca.io import save_torch
from gca.train.config import TrainConfig
from gca.train.law import LearnedLaw


class Schedule:
    """Cosine decay from each group's lr to ``cosine_floor`` of it, times a backtracking scale.

    ``scale`` starts at 1 and shrinks by ``backtrack_factor`` at each rejected update; it is part of
    the checkpoint so a resumed run keeps the smaller steps.
    """

    def __init__(self, opt: torch.optim.Optimizer, cfg: TrainConfig):
        self.opt, self.cfg, self.scale = opt, cfg, 1.0
        self.base = [g["lr"] for g in opt.param_groups]
        self.it = 0
        self._apply()

    def factor(self, it: int) -> float:
        c, floor = self.cfg, self.cfg.cosine_floor
        return self.scale * (floor + (1 - floor) * 0.5 * (1 + math.cos(math.pi * min(it, c.iterations) / c.iterations)))

    def _apply(self, it: int | None = None) -> None:
        for group, base in zip(self.opt.param_groups, self.base):
            group["lr"] = base * self.factor(self.it if it is None else it)

    def step(self) -> None:
        self.it += 1
        self._apply()

    def shrink(self) -> None:
        self.scale *= self.cfg.backtrack_factor
        self._apply()

    def state_dict(self) -> dict:
        return {"it": self.it, "scale": self.scale}

    def load_state_dict(self, state: dict) -> None:
        self.it = int(state.get("it", state.get("last_epoch", 0)))  # LambdaLR checkpoints: last_epoch
        self.scale = float(state.get("scale", 1.0))
        self._apply()


def make_optimizer(law: LearnedLaw, cfg: TrainConfig):
    kind = torch.optim.RAdam if cfg.optimizer == "radam" else torch.optim.Adam
    opt = kind([{"params": g["params"], "lr": g["lr"]} for g in law.groups])
    return opt, Schedule(opt, cfg)


class Undo:
    """What one optimiser update changed, so it can be taken back and retaken with a smaller lr:
    the parameters and Adam's state before it, the (clipped) gradient it used and its schedule step."""

    def __init__(self, law: LearnedLaw, opt: torch.optim.Optimizer, sched: Schedule):
        params = law.trainable()
        self.params = [p.detach().clone() for p in params]
        self.grads = [None if p.grad is None else p.grad.detach().clone() for p in params]
        self.opt_state = copy.deepcopy(opt.state_dict())
        self.it = sched.it

    def restore(self, law: LearnedLaw, opt: torch.optim.Optimizer) -> None:
        """The parameters, gradients and Adam state as they were before the update (lrs untouched)."""
        with torch.no_grad():
            for p, saved, g in zip(law.trainable(), self.params, self.grads):
                p.copy_(saved)
                p.grad = None if g is None else g.clone()
        lrs = [group["lr"] for group in opt.param_groups]
        opt.load_state_dict(copy.deepcopy(self.opt_state))
        for group, lr in zip(opt.param_groups, lrs):  # load_state_dict brings the old lrs back too
            group["lr"] = lr

    def retake(self, law: LearnedLaw, opt: torch.optim.Optimizer, sched: Schedule) -> None:
        """Restore, then step again from the same gradient at the update's own schedule step and the
        schedule's current (shrunk) scale."""
        self.restore(law, opt)
        sched._apply(self.it)
        opt.step()
        sched._apply()

    def state(self) -> dict:
        """For the checkpoint: a run resumed after update ``it`` can still take it back (a diverging rollout right
        after the resume) and keep the law before it (``_select``), as the uninterrupted run would."""
        return {"params": self.params, "grads": self.grads, "opt_state": self.opt_state, "it": self.it}

    @classmethod
    def load(cls, state: dict | None) -> "Undo | None":
        """The :meth:`state` saved (None for a checkpoint without one: before update 0, or written before session
        43, when a resumed run could take back no update)."""
        if not state:
            return None
        undo = cls.__new__(cls)
        undo.params, undo.grads, undo.opt_state, undo.it = (state["params"], state["grads"], state["opt_state"],
                                                             state["it"])
        return undo


class BestLaw:
    """The law with the lowest training loss over the whole video so far: its trainable parameters,
    loss and iteration (the loss of iteration ``it`` is that of the law *before* update ``it``)."""

    def __init__(self):
        self.loss, self.iteration, self.params = math.inf, None, None

    def offer(self, law: LearnedLaw, loss: float, it: int) -> None:
        if loss < self.loss:
            self.loss, self.iteration = loss, it
            self.params = [p.detach().clone() for p in law.trainable()]

    def restore(self, law: LearnedLaw) -> None:
        params = law.trainable()
        if len(params) != len(self.params):
            raise ValueError(f"gca/train/loop.py: the best law has {len(self.params)} parameter tensors, "
                             f"the law {len(params)} (a checkpoint of another method?)")
        with torch.no_grad():
            for p, saved in zip(params, self.params):
                p.copy_(saved)

    def state(self) -> dict:
        return {"loss": self.loss, "iteration": self.iteration, "params": self.params}

    def load(self, state: dict | None) -> None:
        if state:
            self.loss, self.iteration, self.params = float(state["loss"]), state["iteration"], state["params"]


def save_checkpoint(path: Path, law: LearnedLaw, opt, sched, it: int, history: list, rejected: list,
                     best: BestLaw, seconds: float, objective=None, undo: Undo | None = None,
                     processes: list[dict] | None = None) -> None:
    """Everything a resumed run needs to go on as the uninterrupted one would (``objective``: an
    :class:`gca.train.objective.Objective`, whose CPR fits carry over between iterations; ``undo``: the last
    update's :class:`Undo`, small: the LoRA parameters and their Adam state; ``processes``: one dict per process
    that trained the run so far, ``{"resumed_at": <its first iteration>, **<its caller's metadata>}``, the last
    one's last)."""
    save_torch({"law": law.state(), "opt": opt.state_dict(), "sched": sched.state_dict(), "iteration": it,
                "history": history, "rejected": rejected, "best": best.state(), "seconds": seconds,
                "objective": None if objective is None else objective.state(),
                "undo": None if undo is None else undo.state(), "processes": list(processes or [])}, path)


def resume_checkpoint(path: Path | None, law: LearnedLaw, opt, sched, best: BestLaw,
                      objective=None) -> tuple[int, list, list, float, Undo | None, list[dict]]:
    """Load a checkpoint into the law, optimiser, schedule, best-law tracker and (given) the objective;
    returns ``(iteration, history, rejected updates, training seconds spent before it, the last update's Undo,
    the processes that trained it)``: :func:`save_checkpoint`'s ``processes``, ``[]`` for a checkpoint written
    before they were kept (its earlier processes unknown)."""
    if path is None or not path.is_file():
        return 0, [], [], 0.0, None, []
    ckpt = torch.load(path, weights_only=False, map_location=law.trainable()[0].device)
    law.load_state(ckpt["law"])
    opt.load_state_dict(ckpt["opt"])
    sched.load_state_dict(ckpt["sched"])
    best.load(ckpt.get("best"))
    if objective is not None:
        objective.load_state(ckpt.get("objective"))
    return (int(ckpt["iteration"]), list(ckpt["history"]), list(ckpt.get("rejected", [])),
            float(ckpt.get("seconds", 0.0)), Undo.load(ckpt.get("undo")),
            [dict(p) for p in ckpt.get("processes") or []])
