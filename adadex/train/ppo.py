"""PPO for trackers, built from TorchRL parts: a collector (``Collector``, ``MultiSyncCollector`` or
``RayCollector``), ``GAE``, ``ClipPPOLoss`` and a ``TensorDictReplayBuffer`` sampled without
replacement. No PPO maths is written here; this module wires the parts, logs, checkpoints and
evaluates.

One iteration: collect ``frames_per_batch`` frames with the current policy (exploring), compute
advantages with GAE, run ``epochs`` passes of minibatch updates (a minibatch whose loss or gradient
is non-finite is skipped and counted as ``skipped_minibatches``; an iteration with nothing but such
minibatches raises :class:`TrainingDiverged`), push the new weights to the collector's workers, log,
and every ``checkpoint_every`` iterations write a checkpoint (:mod:`adadex.train.checkpoint`). The
observation normalizers are fitted on the first batch (before any update); with ``ppo.obs_norm =
"running"`` every later batch is merged into their statistics after its update, so the next collection
and the next update normalize alike (:class:`~adadex.modules.nets.ObservationMoments`, kept in the
checkpoint). The statistics travel inside the modules' state. The loss reads a residual tracker's
action bounds from the batch, where the collecting policy wrote them
(:func:`~adadex.modules.nets.stored_bounds_actor`), rather than computing its object anchor again
for every minibatch.

Example (a few iterations on a tiny dataset)::

    from adadex.train.config import TrainConfig, PPOConfig, CollectorConfig
    from adadex.train.ppo import train
    result = train(TrainConfig(dataset="data/tiny", out="runs/t", ppo=PPOConfig(total_frames=2048,
                   frames_per_batch=512, minibatch_size=256), collector=CollectorConfig(worlds=8)))
    result["tracker"]            # runs/t/tracker.pt, loads with Tracker.load
    result["updates"]            # median KL and clip fraction of the updates (update_health)

A run whose updates mostly ran past PPO's clip range (median clip fraction above
:data:`TRUST_REGION_CLIP`) ends with a one-line warning naming the settings that keep them within it.
For a modulator deciding every k steps (``Modulator(decide_every=k)``) only its decisions, about one
sample in k, carry a log-probability, so ``result["updates"]`` adds the medians at the decisions (k ×
the loss's means) and the warning reads those.
A recurrent policy (TorchRL's ``GRUModule`` / ``LSTMModule`` in its actor or critic) gets its state
primed in the env and is updated on whole sequences (:meth:`PPOTrainer._update`).

Your own modules: ``PPOTrainer(cfg, policy=…, loss=…, env_transforms=…)`` trains a policy you built
(any :class:`~adadex.modules.nets.ActorCritic`, e.g. one with your own critic), with any TorchRL PPO
loss built on its actor and critic, on envs carrying your extra transforms (see :class:`PPOTrainer`
and docs/training.md, "Your own modules").
"""

from __future__ import annotations

import copy
import functools
import json
import os
import pickle
import sys
import time
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np
import torch
from tensordict import TensorDictBase
from torch import nn
from torchrl.data import Bounded, Composite, LazyTensorStorage, TensorDictReplayBuffer
from torchrl.data.replay_buffers.samplers import SamplerWithoutReplacement
from torchrl.modules import set_recurrent_mode
from torchrl.objectives import ClipPPOLoss, LossModule
from torchrl.objectives.value import GAE

from adadex.data.reference import ReferenceDataset
from adadex.envs.observation import ERRORS as ERRORS_KEY
from adadex.envs.observation import OBSERVATION, REFERENCE_INDEX, REWARD_TERMS, STEP
from adadex.envs.tracking import TrackingConfig, episode_references
from adadex.errors import AdadexError, ConfigError
from adadex.eval.evaluate import evaluate
from adadex.eval.metrics import ERROR_NAMES, SUMMARY_SCALE, frame_success, with_units
from adadex.modules.nets import (ActorCritic, Normalizer, ObservationMoments, fit_normalizers,
                                 recurrent_state_shapes, stored_bounds_actor)
from adadex.modules.channels import CHANNELS, ModulationConfig
from adadex.modules.modulator import Modulator
from adadex.modules.tracker import Tracker
from adadex.progress import progress_bar
from adadex.train.checkpoint import TRAINING_RUN, check_run, save_checkpoint, set_rng_state, start_run
from adadex.train.collectors import make_collector, start_worker_server
from adadex.sim.robot import NUM_JOINTS
from adadex.train.config import PPOConfig, TrainConfig
from adadex.train.envs import ModulatedEnv, StatePrimer, TrackingEnvFactory
from adadex.transforms.policy import make_policy, state_primer
from adadex.train.logs import RunLog
from adadex.train.threads import torch_threads


class TrainingDiverged(AdadexError, RuntimeError):
    """Every minibatch update of an iteration had a non-finite loss or gradient (none was applied)."""


ERRORS = ("next", *ERRORS_KEY)


def training_references(cfg: TrainConfig, dataset: ReferenceDataset, window: int) -> list[int]:
    """The dataset indices a run trains on (see :class:`TrainConfig`)."""
    if cfg.references is not None:
        return list(cfg.references)
    refs = episode_references(dataset, cfg.split, window)
    if cfg.group is not None:
        refs = [i for i in refs if dataset.entries[i]["group"] == cfg.group]
        if not refs:
            groups = sorted({dataset.entries[i]["group"] for i in episode_references(dataset, cfg.split, window)})
            raise ConfigError(f"{dataset.path}: semantic group {cfg.group} has no reference in split "
                              f"{cfg.split} with a {window}-frame window; groups there: {groups[:20]}")
    if not refs:
        raise ConfigError(f"{dataset.path}: no reference in split {cfg.split} has a {window}-frame window")
    return refs


def group_advantage(data: TensorDictBase, group_size: int, keys=None) -> None:
    """``ppo.advantage="group"``: each step's advantage becomes its value target (GAE's λ-return) less
    the mean of the value targets of the other ``group_size − 1`` worlds of its group at the same step
    (leave-one-out, so the baseline does not depend on the step's own action and the estimate stays
    unbiased). ``data`` is a batch [N, T] whose rows come in groups of ``group_size`` consecutive
    worlds (:class:`~adadex.envs.tracking.TrackingEnv`'s ``group_size``: one reference, one draw, the
    same noise); written in place.

    Example:
        >>> from tensordict import TensorDict
        >>> td = TensorDict({"value_target": torch.tensor([[[1.0]], [[3.0]], [[0.0]], [[4.0]]]),
        ...                  "advantage": torch.zeros(4, 1, 1)}, batch_size=[4, 1])
        >>> group_advantage(td, 2)
        >>> td["advantage"].flatten().tolist()
        [-2.0, 2.0, -4.0, 4.0]
    """
    adv_key = "advantage" if keys is None else keys.advantage
    target_key = "value_target" if keys is None else keys.value_target
    target = data[target_key]
    n = target.shape[0]
    if group_size < 2 or n % group_size:
        raise ConfigError(f"group advantage: {n} worlds in the batch do not split into groups of {group_size}")
    g = target.reshape(n // group_size, group_size, *target.shape[1:])
    others = (g.sum(1, keepdim=True) - g) / (group_size - 1)
    data.set(adv_key, (g - others).reshape(target.shape))


def default_loss(ppo: PPOConfig) -> Callable[..., LossModule]:
    """The loss factory a run uses unless given one: ``(actor, critic) ->`` TorchRL's ``ClipPPOLoss``
    with ``ppo.clip_epsilon``, ``ppo.entropy_coef``, ``ppo.critic_coef`` and normalized advantages.

    Args:
        ppo: the PPO settings (:class:`~adadex.train.config.PPOConfig`).

    Returns:
        a ``functools.partial`` of ``ClipPPOLoss``: call it with ``(actor, critic)``.
    """
    return functools.partial(ClipPPOLoss, clip_epsilon=ppo.clip_epsilon, entropy_coeff=ppo.entropy_coef,
                             critic_coeff=ppo.critic_coef, normalize_advantage=True)


class PPOTrainer:
    """A PPO run (see the module docstring); :meth:`train` runs it. The policy trained is a
    :class:`Tracker` (specialists, the vanilla-PPO baseline), or — with ``cfg.modulator`` — a
    :class:`Modulator` on the modulated env with the generalist frozen inside it (paper Sec. 3.2).

    Args:
        cfg: the run's settings.
        env_config: the episode settings (default ``TrackingConfig()``); the run's reward settings go on top.
        run_name: the name in the logs and the progress bar.
        teacher: DexTrack-style imitation's teacher table (needs ``ppo.imitation_coef`` > 0).
        policy: your own module to train instead of the one ``cfg`` builds: an ``nn.Module`` with
            ``.actor`` (a TorchRL ``ProbabilisticActor`` writing ``"action"`` and its log-prob, with an
            action spec), ``.critic`` (writing ``"state_value"``), ``.kind``, ``.save(path)`` and
            optionally ``.obs_key`` (the key its :class:`~adadex.modules.nets.Normalizer` s read,
            default ``"observation"``) — e.g. a :class:`Tracker` of your own sizes, or a subclass of
            :class:`~adadex.modules.nets.ActorCritic` with your own critic. Given, ``cfg.policy`` is not
            used, nor the settings of ``cfg.modulator`` that build the modulator (``hidden``,
            ``init_scale``, ``loc_bound``); the env's settings (``cfg.modulator.tracker``, ``channels``,
            ``modulation``, ``inputs``, ``history``) still make the modulated env. A ``policy`` that
            does not fit the run is refused (:class:`~adadex.errors.ConfigError`): a tracker given to a
            modulator run or a modulator to a tracker run, or an actor whose action size is not that of
            the env's action spec (22 for a tracker; the channels' size for a modulator). Its actor
            samples in the collector through ``policy.sampling_policy()`` where it has one that works
            (an actor from :func:`~adadex.modules.nets.make_actor`), else the actor itself. Its
            normalizers, if any, are fitted as the built policy's are — unless all of them are fitted
            already (a trained policy given to fine-tune, e.g. ``Tracker.load(path)``): they are kept,
            so the run starts from the policy exactly as it acts.
        loss: a factory ``(actor, critic) -> LossModule`` (default :func:`default_loss`: ``ClipPPOLoss``
            with ``cfg.ppo``'s settings), e.g. ``functools.partial(KLPENPPOLoss, dtarg=0.01)``. GAE
            (``cfg.ppo.gamma``, ``lmbda``) writes the advantage and value target before it; the
            minibatch update adds every ``loss_*`` entry the loss returns. The checkpoint holds the
            loss's state dict, so a resumed run must be given the same kind of loss and policy.
        env_transforms: picklable zero-argument callables (``functools.partial(StepCounter,
            max_steps=…)``, a class, a module-level function), each returning a TorchRL ``Transform``
            appended to every collector env after adadex's own (the modulation, ``RewardSum``), in
            this process and in every worker. The evaluation envs (``eval_every``, the final
            evaluation) do not get them.
    """

    def __init__(self, cfg: TrainConfig, *, env_config: TrackingConfig | None = None, run_name: str = "ppo",
                 teacher: tuple[torch.Tensor, torch.Tensor] | None = None, policy: nn.Module | None = None,
                 loss: Callable[..., LossModule] | None = None, env_transforms: Sequence[Callable] = ()):
        env_config = cfg.env_config(env_config)              # with the run's reward settings
        self.cfg, self.env_config, self.run_name = cfg, env_config, run_name
        self.out = Path(cfg.out)
        if cfg.collector.backend == "local" and cfg.collector.workers > 1:
            start_worker_server(cfg.collector.start_method)        # it imports while this sets up
        self.dataset = ReferenceDataset(cfg.dataset)
        self.references = training_references(cfg, self.dataset, env_config.window)
        torch.manual_seed(cfg.seed)
        np.random.seed(cfg.seed)
        m = cfg.modulator
        #: the user's extra env transforms (factories), after adadex's own
        self.env_transforms = self._check_env_transforms(env_transforms)
        # a given modulator decides as it was built to (its view's interval), else as the settings say
        decide = getattr(getattr(policy, "view", None), "decide_every", None) or (m.decide_every if m else 1)
        #: the policy's decision interval: between decisions no sample carries a log-probability, so the
        #: loss's KL and clip fraction (means over all samples) count about one sample in this many
        self.decide_every = int(decide)
        self.transform = None if m is None else ModulatedEnv(m.tracker, m.channels, ModulationConfig(**m.modulation),
                                                             history=m.history if m.inputs == "view" else None,
                                                             decide_every=decide)
        if policy is not None:
            self._check_policy(policy)
            self.policy = policy
        elif m is None:
            self.policy = cfg.policy.tracker(max_action=env_config.max_action)
        else:
            env_channels = ModulationConfig(**m.modulation)
            self.policy = Modulator(m.channels, hidden=m.hidden, init_scale=m.init_scale, loc_bound=m.loc_bound,
                                    inputs=m.inputs, history=m.history, prior=m.prior, hold_steps=m.hold_steps,
                                    hold_scale=m.hold_scale, context_free=m.context_free, focus=m.focus,
                                    lambda_palm=env_channels.lambda_palm,
                                    prior_lookahead=env_channels.reach_lookahead if m.prior is not None else 1,
                                    prior_reach=m.prior_reach,
                                    core=m.core, core_size=m.core_size, decide_every=m.decide_every,
                                    **{c.latch: getattr(env_channels, c.latch) for c in CHANNELS.values() if c.latch})
        #: the state a recurrent policy (TorchRL's GRUModule / LSTMModule in its actor or critic) carries in
        #: the env, ``{key: shape}``; empty for a feed-forward one. The env primes it; updates run on whole sequences
        self.recurrent = {**recurrent_state_shapes(self.policy.actor), **recurrent_state_shapes(self.policy.critic)}
        if self.recurrent:
            self.env_transforms = (*self.env_transforms, StatePrimer(tuple(self.recurrent.items())))
        self.ppo = cfg.ppo
        self.device = self._check_device(torch.device(self.ppo.device))
        self.policy.to(self.device)                # before the loss takes its parameters
        actor = self.policy.actor
        if getattr(actor, "_sampling_parts", None) is not None:          # built by make_actor
            actor = stored_bounds_actor(actor)
        self.loss = (loss if loss is not None else default_loss(self.ppo))(actor, self.policy.critic)
        if not isinstance(self.loss, LossModule):
            raise ConfigError(f"{run_name}: loss must build a TorchRL LossModule from (actor, critic), "
                              f"got {type(self.loss).__name__}")
        self.gae = GAE(gamma=self.ppo.gamma, lmbda=self.ppo.lmbda, value_network=self.policy.critic,
                       average_gae=False)
        self.optim = torch.optim.Adam(self.loss.parameters(), lr=self.ppo.lr)
        #: what the policy's normalizers read (the tracker's observation, or the modulator's view)
        self.obs_key = getattr(self.policy, "obs_key", OBSERVATION)
        #: DexTrack-style imitation (paper B.2.1): (actions [references, window, 22], mask [references,
        #: window]) — the teacher's action for each dataset reference and step, where one was logged
        self.teacher = None if teacher is None else tuple(t.to(self.device) for t in teacher)
        if teacher is not None and not self.ppo.imitation_coef > 0:
            raise ConfigError("a teacher table was given but ppo.imitation_coef is 0")
        if teacher is not None and self.recurrent:
            raise ConfigError(f"{run_name}: imitation of a teacher (IL+RL) scores single frames; the policy has a "
                              f"recurrent core (state {sorted(self.recurrent, key=str)})")
        self.iteration, self.frames = 0, 0
        #: ``tracker.pt`` or ``modulator.pt``: loads with ``Tracker.load`` / ``Modulator.load``
        self.policy_path = self.out / f"{self.policy.kind}.pt"
        #: every observation collected so far (or the first batch alone: ``ppo.obs_norm``); a given
        #: policy's own fit, if it has one, counts as its first batch
        self.moments = ObservationMoments()
        self.fitted = policy is not None and self._moments_from_normalizers()
        self.buffer: TensorDictReplayBuffer | None = None

    # -- pieces -----------------------------------------------------------------------------------
    def _check_device(self, device: torch.device) -> torch.device:
        """``ppo.device`` if this run can use it: a CUDA device torch sees, with the local one-worker
        collector (workers in other processes or on other machines get the weights on the host)."""
        if device.type == "cpu":
            return device
        if not torch.cuda.is_available():
            raise ConfigError(f"{self.run_name}: ppo.device={self.ppo.device!r} but torch sees no CUDA device "
                              f"(torch {torch.__version__}); use ppo.device=cpu")
        if device.index is not None and device.index >= torch.cuda.device_count():
            raise ConfigError(f"{self.run_name}: ppo.device={self.ppo.device!r} but torch sees "
                              f"{torch.cuda.device_count()} CUDA device(s)")
        c = self.cfg.collector
        if c.backend != "local" or c.workers != 1:
            raise ConfigError(f"{self.run_name}: ppo.device={self.ppo.device!r} needs collector.backend=local "
                              f"collector.workers=1 (got {c.backend}, {c.workers} workers)")
        return device

    def _check_env_transforms(self, env_transforms) -> tuple:
        out = tuple(env_transforms)
        for t in out:
            if not callable(t):
                raise ConfigError(f"{self.run_name}: env_transforms holds {t!r}, not a callable returning a "
                                  f"Transform (e.g. functools.partial(StepCounter, max_steps=100))")
            try:
                pickle.dumps(t)
            except Exception as e:           # a lambda, a local function: no worker could build it
                raise ConfigError(f"{self.run_name}: env_transforms holds {t!r}, which cannot be pickled for "
                                  f"the collector's workers ({e}); use functools.partial or a module-level "
                                  f"class or function") from e
        return out

    def env_action_dim(self) -> int:
        """The size of the action the run's env takes: the tracker's joint-target change, or — with
        ``cfg.modulator`` — what the modulated env's action spec says (its transforms' own spec)."""
        spec = Composite(action=Bounded(low=-self.env_config.max_action, high=self.env_config.max_action,
                                        shape=(1, NUM_JOINTS)), shape=(1,))
        if self.transform is not None:
            spec = self.transform().transform_action_spec(spec)
        return int(spec["action"].shape[-1])

    def _check_policy(self, policy) -> None:
        """Refuse a ``policy`` this run cannot train, in one line (see the class docstring)."""
        run = "tracker" if self.cfg.modulator is None else "modulator"
        name = type(policy).__name__
        if not isinstance(policy, nn.Module):
            raise ConfigError(f"{self.run_name}: policy must be a torch.nn.Module with .actor and .critic (e.g. an "
                              f"ActorCritic), got {name}")
        missing = [a for a in ("actor", "critic", "kind", "save") if not hasattr(policy, a)]
        if missing:
            raise ConfigError(f"{self.run_name}: policy {name} has no {', '.join(missing)} (see ActorCritic)")
        if isinstance(policy, ActorCritic) and not isinstance(getattr(policy, "config", None), dict):
            raise ConfigError(f"{self.run_name}: policy {name} has no config dict, which ActorCritic.save writes "
                              f"(set self.config in its __init__)")
        kind = policy.kind
        if {run, kind} == {"tracker", "modulator"}:
            why = "cfg.modulator is set" if run == "modulator" else "cfg.modulator is None"
            raise ConfigError(f"{self.run_name}: a {run} run ({why}) cannot train the {kind} given as policy ({name})")
        spec = getattr(policy.actor, "spec", None)
        action = spec.get("action", None) if isinstance(spec, Composite) else spec
        if action is not None and action.shape:
            want = self.env_action_dim()
            if int(action.shape[-1]) != want:
                env = (f"the modulated env (channels {self.cfg.modulator.channels})" if run == "modulator"
                       else "the tracking env")
                raise ConfigError(f"{self.run_name}: policy {name}'s actor writes a {int(action.shape[-1])}-D "
                                  f"action, but {env} takes a {want}-D action (its action spec)")

    def collecting_policy(self):
        """The policy the collector runs: ``policy.sampling_policy()`` (one call per step, same
        distribution) where the policy has one that works, else its actor."""
        sampling = getattr(self.policy, "sampling_policy", None)
        if sampling is not None:
            try:
                return sampling()
            except TypeError:           # SamplingPolicy needs an actor built by make_actor
                pass
        return self.policy.actor

    def env_factory(self, seed: int) -> TrackingEnvFactory:
        c = self.cfg.collector
        return TrackingEnvFactory(str(self.dataset.path), tuple(self.references), num_worlds=c.worlds, seed=seed,
                                  randomize=self.cfg.randomization_config(),
                                  config=self.env_config, nthread=c.env_threads, transform=self.transform,
                                  transforms=self.env_transforms, backend=self.cfg.sim.backend,
                                  group_size=c.group_size)

    def _resume(self) -> bool:
        """Check ``out`` (:func:`~adadex.train.checkpoint.check_run`: someone else's folder, a run there
        without ``resume``, a resume with settings that change the result are refused) and, with
        ``resume``, load its checkpoint; ``True`` when there was one to continue from. Here, as for the
        pipeline's stages, ``resume`` without a checkpoint starts a fresh run; the recipes refuse it."""
        blob = check_run(self.out, TRAINING_RUN, self.cfg.to_dict(), resume=self.cfg.resume, strict=False)
        if blob is None:
            return False
        self.loss.load_state_dict(blob["module"])
        self.optim.load_state_dict(blob["optimizer"])
        self.iteration, self.frames = blob["iteration"], blob["frames"]
        set_rng_state(blob["rng"])
        moments = blob.get("extra", {}).get("obs_moments")
        if moments is not None:
            self.moments.load_state_dict(moments)
        else:                   # a checkpoint from before the running statistics: its fit, as one batch
            self._moments_from_normalizers(force=True)
        self.fitted = True
        return True

    def _moments_from_normalizers(self, force: bool = False) -> bool:
        """Seed :attr:`moments` with the policy's normalizer statistics, as one batch, when every
        normalizer is fitted (``force``: the first one's, whatever it holds); whether it did."""
        norms = [m for m in self.policy.modules() if isinstance(m, Normalizer)]
        if not norms or not (force or all(n.fitted for n in norms)):
            return False
        n = self.ppo.frames_per_batch
        self.moments.load_state_dict({"count": n, "mean": norms[0].loc.double(),
                                      "m2": norms[0].scale.double() ** 2 * (n - 1)})
        return True

    def _checkpoint(self) -> None:
        save_checkpoint(self.out, module=self.loss, optimizer=self.optim, iteration=self.iteration,
                        frames=self.frames, config=self.cfg.to_dict(),
                        extra={"obs_moments": self.moments.state_dict()})
        self.policy.save(self.policy_path)

    def _update(self, data: TensorDictBase) -> dict:
        """GAE, then ``epochs`` passes of minibatch PPO updates over ``data`` ([N, T]).

        A minibatch is ``ppo.minibatch_size`` frames drawn at random, or for a recurrent policy
        (:attr:`recurrent`) ``minibatch_size // T`` whole rows: each world's T steps in order, which
        TorchRL's recurrent mode runs from the state the collector stored at the row's first step (and
        from zero after an ``"is_init"``). Its log-probabilities are then those of the collection, as
        they would be frame by frame from each step's stored state, but the gradient also reaches back
        through the sequence, so the core learns what to keep from earlier steps."""
        data = data.to(self.device)
        with torch.no_grad(), set_recurrent_mode(bool(self.recurrent)):
            self.gae(data)
            if self.ppo.advantage == "group":
                group_advantage(data, self.cfg.collector.group_size, self.loss.tensor_keys)
        if self.recurrent:
            items = data.select(*self._minibatch_keys())                 # [N, T]: rows of whole sequences
            per = max(1, min(items.shape[0], self.ppo.minibatch_size // items.shape[-1]))
        else:
            items = data.select(*self._minibatch_keys()).reshape(-1)
            per = self.ppo.minibatch_size
        if self.buffer is None or self.buffer.storage.max_size != items.shape[0] or self.buffer.batch_size != per:
            self.buffer = TensorDictReplayBuffer(storage=LazyTensorStorage(items.shape[0], device=self.device),
                                                 sampler=SamplerWithoutReplacement(), batch_size=per)
        buffer = self.buffer
        buffer.empty()
        buffer.extend(items)
        stats: dict[str, list] = {}
        steps = max(1, items.shape[0] // per)
        skipped = 0
        if self.ppo.anneal_lr:
            self._set_lr(self.ppo.annealed_lr(self.frames))
        for _ in range(self.ppo.epochs):
            for _ in range(steps):
                batch = buffer.sample()
                with set_recurrent_mode(bool(self.recurrent)):
                    out = self.loss(batch)
                total = out["loss_objective"] + out["loss_critic"] + out.get("loss_entropy", 0.0)
                for k in sorted(k for k in out.keys() if isinstance(k, str) and k.startswith("loss_")
                                and k not in ("loss_objective", "loss_critic", "loss_entropy")):
                    total = total + out[k]          # another loss's terms (ClipPPOLoss has none)
                if self.teacher is not None:
                    imitation = self._imitation(batch)
                    total = total + self.ppo.imitation_coef * imitation
                self.optim.zero_grad()
                if not bool(torch.isfinite(total)):
                    skipped += 1
                    continue
                total.backward()
                grad = torch.nn.utils.clip_grad_norm_(self.loss.parameters(), self.ppo.max_grad_norm)
                if not bool(torch.isfinite(grad)):
                    self.optim.zero_grad()
                    skipped += 1
                    continue
                self.optim.step()
                if self.teacher is not None:
                    stats.setdefault("loss_imitation", []).append(float(imitation.detach()))
                if self.ppo.desired_kl > 0 and "kl_approx" in out.keys():
                    self._adapt_lr(self.decide_every * float(out["kl_approx"].detach().mean()))
                for k in ("loss_objective", "loss_critic", "loss_entropy", "entropy", "kl_approx", "clip_fraction",
                          "ESS", "kl"):
                    if k in out.keys():
                        stats.setdefault(k, []).append(float(out[k].detach().mean()))
                stats.setdefault("grad_norm", []).append(float(grad))
        if skipped == self.ppo.epochs * steps:
            raise TrainingDiverged(
                f"{self.run_name}: iteration {self.iteration + 1}: the loss or its gradient was non-finite on every "
                f"minibatch ({skipped}), so the policy was left as it was; the last checkpoint in {self.out} "
                f"(every {self.cfg.checkpoint_every} iterations) holds the weights before this. One cause seen: a "
                f"saturated TanhNormal (pre-tanh means far past its bounds), whose log-probabilities of the same "
                f"action then differ by tens of nats between collection and update")
        stats["lr"] = [self.optim.param_groups[0]["lr"]]
        stats["skipped_minibatches"] = [skipped]
        return {k: float(np.mean(v)) for k, v in stats.items()}

    def _minibatch_keys(self) -> list:
        """What a minibatch update reads: the actor's and critic's inputs, the action, its log-prob, GAE's
        outputs, the loss's other inputs at the step (e.g. ``KLPENPPOLoss``'s distribution parameters;
        not those under ``"next"``, which only a loss computing its own advantage reads) and the imitation
        term's keys. The buffer holds only these — a collected batch has ~60 entries, and each is copied
        on every minibatch draw."""
        k = self.loss.tensor_keys
        keys = {*self.loss.actor_network.in_keys, *self.loss.critic_network.in_keys, k.action, k.sample_log_prob,
                k.advantage, k.value_target, k.value}
        keys |= {key for key in self.loss.in_keys if not (isinstance(key, tuple) and key[0] == "next")}
        if self.teacher is not None:
            keys |= {REFERENCE_INDEX, STEP}
        return sorted(keys, key=str)

    def _adapt_lr(self, kl: float) -> None:
        """The KL-adaptive learning rate (``ppo.desired_kl``): ÷1.5 when the minibatch's approximate
        KL from the collecting policy exceeds twice the target, ×1.5 below half of it. The rate lives
        in the optimizer's state, so a resumed run continues with it. For a modulator deciding every k
        steps the KL is that at its decisions (k × the minibatch's mean, :attr:`decide_every`)."""
        c = self.ppo
        lr = self.optim.param_groups[0]["lr"]
        if kl > 2.0 * c.desired_kl:
            lr = max(lr / 1.5, c.lr_min)
        elif kl < 0.5 * c.desired_kl:
            lr = min(lr * 1.5, c.lr_max)
        self._set_lr(lr)

    def _set_lr(self, lr: float) -> None:
        for g in self.optim.param_groups:
            g["lr"] = lr

    def _imitation(self, batch: TensorDictBase) -> torch.Tensor:
        """Mean squared difference between the policy's deterministic action and the teacher's logged
        action at the same (reference, step) — keyed by time index, no observation matching (B.2.1);
        steps without a logged teacher action do not count.

        In radians, not in units of the policy's scale: a scale-free form (the teacher's action before
        the tanh, over the detached σ) tried once pulled ~10³ × harder and made IL+RL worse
        as it trained (Table 1 settings, 2 seeds: the training batches' frame success fell from 75–78 % to
        44–48 % by 300–380 k frames, where vanilla PPO held 77–79 %). The teacher's action
        at a time index comes from another episode — another object displacement, so another anchored
        feed-forward and joint target — and copying it hard is copying the wrong state's action."""
        actions, mask = self.teacher
        ref, step = batch[REFERENCE_INDEX].long(), batch[STEP].long().clamp(max=actions.shape[1] - 1)
        keep = mask[ref, step]
        if not keep.any():
            return torch.zeros((), requires_grad=True)
        # the loss optimizes its own (functional) copy of the actor's parameters: compute under it
        with self.loss.actor_network_params.to_module(self.loss.actor_network):
            dist = self.loss.actor_network.get_dist(batch[keep])
        return ((dist.deterministic_sample - actions[ref[keep], step[keep]]) ** 2).sum(-1).mean()

    @staticmethod
    def batch_metrics(data: TensorDictBase) -> dict:
        """Rollout statistics of one batch: reward, its terms, errors (named with their units, as the
        evaluation's: :func:`~adadex.eval.metrics.with_units`), frame success, episodes ended."""
        nxt = data["next"]
        out = {"reward": float(nxt["reward"].mean())}
        errs = data.get(ERRORS)
        out.update(with_units({k: float(errs[k].mean()) * SUMMARY_SCALE[k] for k in ERROR_NAMES}))
        out["frame_success_pct"] = 100.0 * float(frame_success({k: errs[k] for k in ERROR_NAMES}).float().mean())
        done, term = nxt["done"], nxt["terminated"]
        out["episodes_done"] = float(done.sum())
        out["terminated_frac"] = float(term.sum()) / max(1.0, float(done.sum()))
        if "episode_reward" in nxt.keys():
            ep = nxt["episode_reward"][done]
            if ep.numel():
                out["episode_return"] = float(ep.mean())
        terms = nxt.get(REWARD_TERMS, None)
        if terms is not None:
            for k in terms.keys():
                out[f"reward_{k}"] = float(terms[k].mean())
        return out

    def evaluate(self, references=None) -> dict:
        """``eval_*`` metrics of the current policy on up to ``eval_max_references`` references (none: {})."""
        if self.cfg.eval_max_references == 0:
            return {}
        refs = references if references is not None else self.references
        eval_refs = (episode_references(self.dataset, self.cfg.eval_split, self.env_config.window)
                     if self.cfg.eval_split is not None else refs)[: self.cfg.eval_max_references]
        # evaluated on the host, beside the env: a copy when the run trains on another device
        trained = self.policy if self.device.type == "cpu" else copy.deepcopy(self.policy).to("cpu")
        policy, primer = trained.actor, (state_primer(self.recurrent) if self.recurrent else None)
        if self.transform is not None:
            t = self.transform
            policy = make_policy(Tracker.load(t.tracker), trained, channels=t.channels, config=t.config)
            primer = policy.primer
        res = evaluate(policy, self.dataset, split=None, references=eval_refs, env_transform=primer,
                       max_worlds=self.cfg.collector.worlds, config=self.env_config, progress=False,
                       randomize=self.cfg.randomization_config(), seed=self.cfg.seed + 17,
                       nthread=self.cfg.collector.env_threads, backend=self.cfg.sim.backend)
        s = res["summary"]
        return with_units({k: v for k, v in s.items() if isinstance(v, (int, float))}, "eval_")

    # -- the run ----------------------------------------------------------------------------------
    def train(self) -> dict:
        resumed = self._resume()                    # checks out (nothing written before)
        start_run(self.out, TRAINING_RUN, fresh=False)
        if self.cfg.modulator is not None and self.cfg.modulator.learner == "paired":
            return self._paired(resumed)
        if self.frames >= self.ppo.total_frames:
            return self._result(resumed)
        log = RunLog(self.out, name=self.run_name, config=self.cfg.to_dict(), wandb=self.cfg.wandb,
                     keep_until=self.iteration if resumed else -1)
        remaining = self.ppo.total_frames - self.frames
        # a resumed run draws new references and randomizations: seeds move on with the iteration
        factory = self.env_factory(self.cfg.seed + 7919 * self.iteration)
        collector = make_collector(factory, self.collecting_policy(), self.cfg.collector,
                                   frames_per_batch=self.ppo.frames_per_batch, total_frames=remaining)
        bar = progress_bar(total=self.ppo.total_frames, initial=self.frames, unit="frame", desc=self.run_name,
                   disable=not self.cfg.progress)
        with torch_threads(1):                  # collection: one torch thread beside MuJoCo's
            try:
                collector.update_policy_weights_()   # sets up the weight sync before the first batch (Ray warns otherwise)
                t_iter = time.perf_counter()
                for data in collector:
                    t_collected = time.perf_counter()
                    # [worlds (of all workers), T], where the updates run (a no-op when the env is there too)
                    data = data.reshape(-1, data.shape[-1]).to(self.device)
                    first = not self.fitted
                    if first:
                        fit_normalizers(self.policy, data[self.obs_key])    # as every run before obs_norm
                        self.moments.update(data[self.obs_key])
                        self.fitted = True
                    stats = self.batch_metrics(data)
                    with torch_threads(self.ppo.update_threads or os.cpu_count() or 1):
                        stats.update(self._update(data))
                    if not first and self.ppo.obs_norm == "running":
                        self.moments.update(data[self.obs_key])
                        self.moments.apply(self.policy)
                    collector.update_policy_weights_()
                    n = data.numel()
                    self.frames += n
                    self.iteration += 1
                    now = time.perf_counter()
                    stats.update(frames=self.frames, fps=n / (now - t_iter), collect_fps=n / (t_collected - t_iter))
                    if self.cfg.eval_every and self.iteration % self.cfg.eval_every == 0:
                        stats.update(self.evaluate())
                    # the row before the checkpoint: a run killed between the two resumes from the earlier
                    # checkpoint and drops the row (keep_until), where the other order left a gap
                    log.log(self.iteration, stats)
                    if self.iteration % self.cfg.checkpoint_every == 0:
                        self._checkpoint()
                    bar.update(n)
                    bar.set_postfix(ret=f"{stats['reward']:.3f}", succ=f"{stats['frame_success_pct']:.0f}%")
                    t_iter = time.perf_counter()
            finally:
                bar.close()
                collector.shutdown()
        self._checkpoint()
        final = self.evaluate()
        if final:
            log.log(self.iteration, {**final, "frames": self.frames})
        log.close()
        updates = update_health(log.rows)
        every = self.decide_every
        if updates and every > 1:   # between decisions no sample moves: the loss's means count about 1 in k
            updates.update(decide_every=every,
                           clip_fraction_median_at_decisions=min(1.0, every * updates["clip_fraction_median"]),
                           kl_median_at_decisions=every * updates["kl_median"])
        clip = updates.get("clip_fraction_median_at_decisions", updates.get("clip_fraction_median", 0.0))
        if clip > TRUST_REGION_CLIP:
            kl = updates.get("kl_median_at_decisions", updates.get("kl_median"))
            where = " at the modulator's decisions" if every > 1 else ""
            print(f"warning: {self.run_name}: the updates ran past PPO's trust region (median clip fraction{where} "
                  f"{clip:.2f}, approximate KL {kl:.3g} over "
                  f"{updates['iterations']} iterations): most samples were clipped; a lower ppo.lr or the "
                  f"KL-adaptive rate (ppo.desired_kl=0.016) keeps the updates within it", file=sys.stderr)
        return {**self._result(resumed, final), "updates": updates}

    def _paired(self, resumed: bool) -> dict:
        """``modulator.learner=paired``: the latched heads fitted once to paired rollouts of the arms
        (:func:`~adadex.train.paired_choice.fit_paired_choice`; its report in ``out/paired_fit.json``)
        in place of PPO; a resumed run has its fit already."""
        if resumed:
            return self._result(True)
        from adadex.io import atomic_write_text
        from adadex.train.paired_choice import fit_paired_choice

        m = self.cfg.modulator
        log = RunLog(self.out, name=self.run_name, config=self.cfg.to_dict(), wandb=self.cfg.wandb, keep_until=-1)
        report = fit_paired_choice(self.policy, Tracker.load(m.tracker).freeze(), self.dataset, self.references,
                                   m.paired_config(), seed=self.cfg.seed, config=self.env_config,
                                   modulation=ModulationConfig(**m.modulation),
                                   randomize=self.cfg.randomization_config(), max_worlds=self.cfg.collector.worlds,
                                   progress=self.cfg.progress, nthread=self.cfg.collector.env_threads,
                                   backend=self.cfg.sim.backend)
        atomic_write_text(self.out / "paired_fit.json", json.dumps(report))
        self.frames, self.iteration = report["frames"], 1
        self._checkpoint()
        final = self.evaluate()
        held = report["holdout"]
        log.log(self.iteration, {**final, "frames": self.frames, "fit_step": report["step"],
                                 "fit_holdout_return": held["fitted"]["return"],
                                 **{f"arm{k}_holdout_return": a["return"] for k, a in enumerate(held["arms"])}})
        log.close()
        return self._result(False, final)

    def _result(self, resumed: bool, final: dict | None = None) -> dict:
        return {"policy": self.policy_path, "tracker": self.policy_path, "frames": self.frames,
                "iterations": self.iteration,
                "resumed": resumed, "eval": final or {}}


#: a run whose median clip fraction exceeds this is told its updates ran past PPO's trust region (the
#: pipeline's R, R+T, R+O+T modulators at a constant 3e-4: 0.75; its specialists and baselines 0.42–0.47;
#: the KL-adaptive rate holds about 0.25–0.3)
TRUST_REGION_CLIP = 0.6


def update_health(rows: Sequence[dict]) -> dict:
    """How far a run's updates moved the policy: the medians over its metrics rows of ``kl_approx`` and
    ``clip_fraction`` (the loss's, per iteration) and how many iterations had them; ``{}`` when none did.

    Rows read back from ``metrics.csv`` (a resumed run) hold ``""`` where a row had no value, e.g. the
    evaluation row a finished run ends with; they count as missing.

    >>> update_health([{"kl_approx": 0.5, "clip_fraction": 0.7}, {"kl_approx": 0.1, "clip_fraction": 0.3},
    ...                {"eval_completion_pct": 80.0}, {"kl_approx": "", "clip_fraction": ""}])
    {'iterations': 2, 'kl_median': 0.3, 'clip_fraction_median': 0.5}
    """
    had = [r for r in rows if r.get("kl_approx") not in (None, "") and r.get("clip_fraction") not in (None, "")]
    kl = [float(r["kl_approx"]) for r in had]
    clip = [float(r["clip_fraction"]) for r in had]
    if not kl:
        return {}
    return {"iterations": len(kl), "kl_median": float(np.median(kl)), "clip_fraction_median": float(np.median(clip))}


def train(cfg: TrainConfig, **kwargs) -> dict:
    """Run :class:`PPOTrainer` on ``cfg`` (``kwargs``: its keyword arguments — ``policy``, ``loss``,
    ``env_transforms``, …); returns the policy path, counters, final evaluation and the updates' medians.

    Args:
        cfg: the run's settings (:class:`~adadex.train.config.TrainConfig`).
        **kwargs: :class:`PPOTrainer`'s keyword arguments (``env_config``, ``run_name``,
            ``teacher``, ``policy``, ``loss``, ``env_transforms``).

    Returns:
        :meth:`PPOTrainer.train`'s result dict.
    """
    return PPOTrainer(cfg, **kwargs).train()
