"""Distillation: behaviour cloning of a generalist :class:`~adadex.modules.tracker.Tracker` from the
specialists' successful rollouts (paper Sec. 3.2; the buffer: :mod:`adadex.train.rollouts`).

The student is the same class as the teachers, reading the same observation (the flat 273-D vector
and, for a residual tracker, ``("proprio", "joint_target")``), with the teachers' ``residual`` and
``max_action`` (read from the teachers' Tracker configs recorded in ``rollouts.json``): a residual
student's action is kinematic replay's plus a learned correction, exactly like its teachers', so
imitating them means learning their corrections.

Training: the student's observation normalizers are fitted once on (a sample of) the buffer's
observations; then each step samples a minibatch *without replacement* (TorchRL's
``SamplerWithoutReplacement``: an epoch visits every stored step once) and takes an Adam step on

    loss = mean over the batch and the 22 joints of (student's deterministic action − teacher action)²

**Why MSE on the deterministic action, not the negative log-likelihood**: the generalist is used
deterministically (evaluation, and frozen under the modulator), so the deterministic action is what
has to match; the teachers' actions are themselves deterministic samples, so there is no spread to
fit; and the TanhNormal's log-likelihood of actions near its bounds (a saturated correction) grows
without limit and lets a few steps dominate, while the squared error stays bounded, in radians.

Checkpoints, resume and logs work like the PPO trainer's (:mod:`adadex.train.checkpoint`,
:class:`~adadex.train.logs.RunLog`): ``out/checkpoint.pt`` (student, optimizer, step, RNG states and
the sampler's position, so a resumed run continues exactly where the killed one was),
``out/metrics.csv`` (+ TorchRL CSV / wandb loggers), and ``out/tracker.pt`` (``Tracker.load``).
The same seed gives the same student.

Example::

    from adadex.train.distill import DistillConfig, distill
    result = distill(DistillConfig(rollouts="runs/rollouts", out="runs/generalist", steps=2000))
    result["tracker"]           # runs/generalist/tracker.pt
"""

from __future__ import annotations

import dataclasses
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from torchrl.data import LazyTensorStorage, TensorDictReplayBuffer
from torchrl.data.replay_buffers.samplers import SamplerWithoutReplacement
from torchrl.envs.utils import ExplorationType, set_exploration_type

from adadex.errors import ConfigError, check_number, check_numbers, from_known_keys
from adadex.modules.nets import fit_normalizers
from adadex.modules.tracker import Tracker
from adadex.progress import progress_bar
from adadex.train.checkpoint import (DISTILLATION_RUN, CheckpointError, check_run, save_checkpoint,
                                     set_rng_state, start_run)
from adadex.train.logs import RunLog
from adadex.train.threads import torch_threads
from adadex.train.rollouts import RolloutsError, load_rollouts, rollouts_info

TRACKER = "tracker.pt"


@dataclass
class DistillConfig:
    """A behaviour-cloning run: where the rollouts are, where results go, the learner's settings.

    Attributes:
        rollouts: a teacher-rollouts folder (:mod:`adadex.train.rollouts`).
        out: the run folder (student, checkpoint, metrics).
        steps: Adam steps (default 5000).
        batch_size: buffer rows per step (default 1024).
        lr: Adam's learning rate (default 3e-4).
        seed: seeds torch, numpy and the buffer's sampling (default 0).
        resume: continue from the checkpoint in ``out`` (default False).
        checkpoint_every: steps between checkpoints (default 500; a kill loses at most this many).
        log_every: steps between metrics rows (default 50).
        hidden: the student's hidden widths (default (256, 256, 128)); its ``residual`` and
            ``max_action`` are the teachers'.
        max_grad_norm: gradient-norm clip (default 1.0).
        normalizer_samples: buffer rows the observation normalizers are fitted on (default 200 000).
        probe_samples: fixed buffer rows the logged ``probe_loss`` is measured on (default 8192).
        fraction: < 1: learn from the rollouts of only this fraction of the stored references (a
            seeded draw, at least one) — the data-scaling study (paper Fig. 6); default 1.0.
        threads: torch threads for the updates (0: all cores; default 1, see
            :mod:`adadex.train.threads`).
        wandb: also log to wandb (default True; offline unless ``WANDB_MODE`` says otherwise).
        progress: show a progress bar (default True).
    """

    rollouts: str                          # a teacher-rollouts folder (adadex.train.rollouts)
    out: str
    steps: int = 5000                      # Adam steps
    batch_size: int = 1024
    lr: float = 3e-4
    seed: int = 0
    resume: bool = False
    checkpoint_every: int = 500            # steps (a kill loses at most this many)
    log_every: int = 50                    # steps between metrics rows
    hidden: tuple[int, ...] = (256, 256, 128)   # the student's width (residual, max_action: the teachers')
    max_grad_norm: float = 1.0
    normalizer_samples: int = 200_000      # buffer rows the observation normalizers are fitted on
    probe_samples: int = 8192              # fixed buffer rows the logged probe_loss is measured on
    #: < 1: learn from the rollouts of only this fraction of the stored references (a seeded draw,
    #: at least one) — the data-scaling study (paper Fig. 6)
    fraction: float = 1.0
    #: torch threads for the updates (0: all cores; see :mod:`adadex.train.threads` for why 1)
    threads: int = 1
    wandb: bool = True                     # offline unless WANDB_MODE says otherwise
    progress: bool = True

    def __post_init__(self):
        check_number("DistillConfig.threads", self.threads, integer=True)
        check_number("DistillConfig.fraction", self.fraction, high=1.0, strict_low=True)
        self.hidden = tuple(int(h) for h in self.hidden)
        for k in ("steps", "batch_size", "checkpoint_every", "log_every", "normalizer_samples", "probe_samples"):
            check_number(f"DistillConfig.{k}", getattr(self, k), low=1, integer=True)
        check_number("DistillConfig.seed", self.seed, integer=True)
        check_number("DistillConfig.lr", self.lr, strict_low=True)
        check_numbers("DistillConfig", self, ("max_grad_norm",))
        if not self.hidden or min(self.hidden) < 1:
            raise ConfigError(f"DistillConfig.hidden must be positive layer widths, got {self.hidden}")

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, d: dict) -> DistillConfig:
        return from_known_keys(cls, d)


def reference_subset(buffer, fraction: float, seed: int) -> TensorDictReplayBuffer:
    """An in-memory buffer of the rows of ``round(fraction · n)`` (at least one) of the ``n`` references
    stored in ``buffer``, drawn with ``seed``: every kept reference keeps all its episodes."""
    rows = buffer[:]
    refs = rows["reference"].unique()
    k = max(1, round(fraction * len(refs)))
    chosen = refs[torch.randperm(len(refs), generator=torch.Generator().manual_seed(seed))[:k]]
    keep = torch.isin(rows["reference"], chosen)
    subset = TensorDictReplayBuffer(storage=LazyTensorStorage(int(keep.sum())), sampler=SamplerWithoutReplacement())
    subset.extend(rows[keep])
    return subset


def teacher_settings(info: dict) -> dict:
    """The Tracker settings a student must share with its teachers (``residual``, ``max_action``,
    ``anchor``, ``anchor_reach``, ``anchor_iterations``, ``anchor_lookahead``), from the teachers' configs in
    ``rollouts.json`` (a key a teacher's checkpoint predates takes the value it then meant); teachers
    that disagree are refused."""
    configs = [Tracker.upgrade_config(dict(t["config"])) for t in info["teachers"]]
    out = {}
    anchored = ("anchor_iterations", "anchor_lookahead")        # only an anchor iterates and looks ahead
    for k in ("residual", "max_action", "anchor", "anchor_reach", *anchored):
        values = sorted({float(c.get(k, 1 if k == "anchor_lookahead" else 0.0)) for c in configs
                         if k not in anchored or float(c.get("anchor", 0.0)) > 0})
        if len(values) > 1:
            raise RolloutsError(f"the teachers disagree on Tracker.{k} ({values}); one student cannot imitate "
                                f"them all with one setting")
        if values:
            out[k] = int(values[0]) if k in anchored else values[0]
    out["init_scale"] = float(configs[0].get("init_scale", 1.0))
    out["loc_bound"] = float(configs[0].get("loc_bound", 0.0))
    return out


def student_inputs(tracker: Tracker) -> list:
    """The keys the tracker's actor reads (the flat observation, and the joint targets when residual)."""
    return list(dict.fromkeys(tracker.actor.in_keys))


def deterministic_action(tracker: Tracker, data) -> torch.Tensor:
    """The tracker's deterministic action on ``data`` (which holds its input keys), with gradients."""
    with set_exploration_type(ExplorationType.DETERMINISTIC):
        return tracker.actor(data.select(*student_inputs(tracker)))["action"]


@torch.no_grad()
def imitation_loss(tracker: Tracker, data, piece: int = 8192) -> float:
    """Mean squared difference (rad²) between the tracker's deterministic action and ``data["action"]``
    over every row of ``data`` (a TensorDict or a replay buffer)."""
    n = len(data)
    total = 0.0
    for i in range(0, n, piece):
        rows = data[i:min(n, i + piece)]
        total += float(F.mse_loss(deterministic_action(tracker, rows), rows["action"], reduction="sum"))
    return total / (n * rows["action"].shape[-1])


class Distiller:
    """A behaviour-cloning run (see the module docstring); :meth:`train` runs it.

    Building it opens the rollouts (:func:`~adadex.train.rollouts.load_rollouts`), seeds torch and
    numpy with ``cfg.seed`` and makes the student :class:`Tracker` with the teachers' settings.

    Args:
        cfg: the run's settings.
        run_name: the name in the logs and the progress bar (default ``"distill"``).
    """

    def __init__(self, cfg: DistillConfig, run_name: str = "distill"):
        self.cfg, self.run_name = cfg, run_name
        self.out = Path(cfg.out)
        self.info = rollouts_info(cfg.rollouts)
        self.buffer = load_rollouts(cfg.rollouts)
        if cfg.fraction < 1:
            self.buffer = reference_subset(self.buffer, cfg.fraction, cfg.seed)
        self.teacher = teacher_settings(self.info)
        torch.manual_seed(cfg.seed)
        np.random.seed(cfg.seed)
        self.student = Tracker(hidden=cfg.hidden, **self.teacher)
        missing = [k for k in student_inputs(self.student) if k not in self.buffer.storage[0:1].keys(True)]
        if missing:
            raise RolloutsError(f"{cfg.rollouts}: the buffer lacks {missing}, which the student reads")
        self.optim = torch.optim.Adam(self.student.actor.parameters(), lr=cfg.lr)
        self.rng = torch.Generator().manual_seed(cfg.seed)
        self.buffer.set_rng(self.rng)
        self.step, self.samples = 0, 0
        n = len(self.buffer)
        # a fixed, evenly spread probe set: the same rows before and after, whatever the seed
        self.probe = self.buffer[torch.linspace(0, n - 1, min(n, cfg.probe_samples)).round().long()]

    def _fit_normalizers(self) -> None:
        n = len(self.buffer)
        idx = torch.randperm(n, generator=self.rng)[: self.cfg.normalizer_samples].sort().values
        obs = self.buffer[idx]["observation"]
        if obs.shape[0] < 2:
            raise RolloutsError(f"{self.cfg.rollouts}: {obs.shape[0]} stored step is too few to fit the "
                                f"observation normalizers")
        fit_normalizers(self.student, obs)

    def _resume(self) -> bool:
        """Check ``out`` and load its checkpoint with ``resume``, as the PPO trainer does
        (:func:`~adadex.train.checkpoint.check_run`; ``resume`` without a checkpoint: a fresh run here,
        refused by the recipe)."""
        blob = check_run(self.out, DISTILLATION_RUN, self.cfg.to_dict(), resume=self.cfg.resume, strict=False)
        if blob is None:
            return False
        try:
            self.student.load_state_dict(blob["module"])
            self.optim.load_state_dict(blob["optimizer"])
        except (RuntimeError, ValueError, KeyError) as e:
            raise CheckpointError(f"{self.out}: the checkpoint does not belong to this distillation run "
                                  f"({type(e).__name__}: {str(e).splitlines()[0]})") from e
        self.step, self.samples = blob["iteration"], blob["frames"]
        set_rng_state(blob["rng"])
        extra = blob.get("extra") or {}
        if "sampler" in extra:
            self.buffer.sampler.load_state_dict(extra["sampler"])
            self.rng.set_state(extra["generator"])
        return True

    def _checkpoint(self) -> None:
        save_checkpoint(self.out, module=self.student, optimizer=self.optim, iteration=self.step, frames=self.samples,
                        config=self.cfg.to_dict(),
                        extra={"sampler": self.buffer.sampler.state_dict(), "generator": self.rng.get_state(),
                               "teacher": self.teacher})
        self.student.save(self.out / TRACKER)

    def train(self) -> dict:
        cfg = self.cfg
        resumed = self._resume()                    # checks out (nothing written before)
        start_run(self.out, DISTILLATION_RUN, fresh=False)
        if self.step >= cfg.steps:
            return self._result(resumed)
        log = RunLog(self.out, name=self.run_name, config=cfg.to_dict(), wandb=cfg.wandb,
                     keep_until=self.step if resumed else -1)
        if not resumed:
            self._fit_normalizers()
            log.log(0, {"probe_loss": imitation_loss(self.student, self.probe), "samples": 0})
        bar = progress_bar(total=cfg.steps, initial=self.step, unit="step", desc=self.run_name, disable=not cfg.progress)
        params = list(self.student.actor.parameters())
        losses, grads = [], []
        try:
            while self.step < cfg.steps:
                batch = self.buffer.sample(cfg.batch_size)
                loss = F.mse_loss(deterministic_action(self.student, batch), batch["action"])
                self.optim.zero_grad()
                loss.backward()
                grads.append(float(torch.nn.utils.clip_grad_norm_(params, cfg.max_grad_norm)))
                self.optim.step()
                losses.append(float(loss.detach()))
                self.step += 1
                self.samples += batch.shape[0]
                bar.update(1)
                last = self.step == cfg.steps
                if self.step % cfg.log_every == 0 or last:
                    stats = {"loss": float(np.mean(losses)), "grad_norm": float(np.mean(grads)),
                             "samples": self.samples, "epochs": self.samples / len(self.buffer)}
                    if last:
                        stats["probe_loss"] = imitation_loss(self.student, self.probe)
                    log.log(self.step, stats)
                    bar.set_postfix(loss=f"{stats['loss']:.2e}")
                    losses, grads = [], []
                if self.step % cfg.checkpoint_every == 0 and not last:
                    self._checkpoint()
        finally:
            bar.close()
        self._checkpoint()
        log.close()
        return self._result(resumed)

    def _result(self, resumed: bool) -> dict:
        return {"tracker": self.out / TRACKER, "steps": self.step, "samples": self.samples, "resumed": resumed,
                "frames": len(self.buffer), "teacher": self.teacher}


def distill(cfg: DistillConfig, **kwargs) -> dict:
    """Run :class:`Distiller` on ``cfg``; returns the student's path and counters.

    Runs with ``cfg.threads`` torch threads (0: every core).

    Args:
        cfg: the run's settings.
        **kwargs: :class:`Distiller`'s keyword arguments (``run_name``).
    """
    with torch_threads(cfg.threads or os.cpu_count() or 1):
        return Distiller(cfg, **kwargs).train()
