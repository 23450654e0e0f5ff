"""Training configuration: one dataclass tree that the Hydra recipes fill and the trainer reads.

>>> cfg = TrainConfig(dataset="data/small", out="runs/a", ppo=PPOConfig(total_frames=20_000))
>>> cfg.ppo.frames_per_batch, cfg.collector.backend
(4096, 'local')
>>> TrainConfig(dataset="d", out="o", collector=CollectorConfig(backend="slurm"))
Traceback (most recent call last):
...
adadex.errors.ConfigError: CollectorConfig.backend must be 'local' or 'ray', got 'slurm'
"""

from __future__ import annotations

import dataclasses
import re
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from adadex.errors import ConfigError, check_number, check_numbers, from_known_keys


#: how PPO normalizes observations (:attr:`PPOConfig.obs_norm`)
OBS_NORMS = ("running", "first_batch")
#: how PPO credits an action (:attr:`PPOConfig.advantage`)
ADVANTAGES = ("gae", "group")


@dataclass
class PPOConfig:
    """PPO on TorchRL parts (GAE + ClipPPOLoss); frames count env steps of all worlds.

    The learner's settings of a :class:`TrainConfig` (the recipes' ``ppo:`` block). Each iteration
    collects ``frames_per_batch`` frames with the exploring policy, computes advantages with GAE and
    runs ``epochs`` passes of clipped-PPO minibatch updates (Adam) over them.

    Attributes:
        total_frames: length of the run, in frames (env steps of all worlds together); rounded up to
            whole batches (default 1 M).
        frames_per_batch: frames collected per iteration, all workers together (default 4096); a
            multiple of worlds × workers.
        epochs: passes over each batch (default 4).
        minibatch_size: frames per minibatch update (default 1024).
        lr: Adam's learning rate (default 3e-4): the constant rate, the start of ``anneal_lr``'s
            schedule, or the start of ``desired_kl``'s adaptation.
        gamma: discount per control step, 12 Hz (default 0.99).
        lmbda: GAE's λ (default 0.95).
        clip_epsilon: PPO's clip range of the probability ratio (default 0.2).
        entropy_coef: weight of the entropy bonus (default 1e-3).
        critic_coef: weight of the critic's loss (default 0.5).
        max_grad_norm: each minibatch's gradient is clipped to this norm (default 1).
        imitation_coef: weight of the DexTrack-style imitation term, which needs a teacher table
            (default 0: plain PPO).
        update_threads: torch threads for the minibatch updates (default 0: all cores); collection
            always runs torch on one.
        desired_kl: > 0 adapts the learning rate to keep each minibatch's approximate KL near this
            value — ÷1.5 above 2×, ×1.5 below ½×, within [``lr_min``, ``lr_max``], the schedule of
            large-batch dexterous PPO; 0: a constant ``lr`` (default 0.016; why: docs/training.md).
        lr_min: lower bound of the adapted or annealed learning rate (default 1e-6).
        lr_max: upper bound of the adapted learning rate (default 1e-2).
        anneal_lr: decay the learning rate linearly from ``lr`` at the first frame to ``lr_min`` at
            ``total_frames`` (each iteration's rate follows the frame counter, so a resumed run
            continues on the schedule; :meth:`annealed_lr`). Excludes ``desired_kl`` (default off).
        advantage: what each step's action is credited with: ``"gae"`` (default) — GAE over the critic's
            values; ``"group"`` — GAE's value target (the λ-return) less the mean of the same over the
            other worlds of its group at the same step (``collector.group_size`` ≥ 2 worlds that start
            together on one reference and one randomization draw, meeting the same noise): a
            leave-one-out baseline (RLOO, as GRPO's group baseline) that needs no critic and, on worlds
            that differ only in the policy's own samples, sees the effect of the action and little else
            — what a choice latched for the episode needs (docs/modulation.md).
        obs_norm: observation normalization: ``"first_batch"`` (default) — fitted once, on the first
            batch; ``"running"`` — every normalizer holds the mean and standard deviation of all
            observations collected so far, merged after each iteration's update
            (:class:`~adadex.modules.nets.ObservationMoments`). The first batch holds only the
            episodes' first steps (why it is the default: docs/training.md).
        device: where the policy, the critic, GAE and the minibatch updates run: ``"cpu"`` (default)
            or a CUDA device (``"cuda"``, ``"cuda:1"``). The env stays where its backend puts it (the
            host for ``sim.backend=rollout``, the GPU for ``warp``) and the collector stores each batch
            there, moving each step's observation to the policy's device when it is another; the
            update moves the batch to this device (with ``sim.backend=warp ppo.device=cuda`` nothing
            leaves the GPU). A CUDA device needs the local collector with one worker.
    """

    total_frames: int = 1_000_000
    frames_per_batch: int = 4096
    epochs: int = 4
    minibatch_size: int = 1024
    lr: float = 3e-4
    gamma: float = 0.99
    lmbda: float = 0.95
    clip_epsilon: float = 0.2
    entropy_coef: float = 1e-3
    critic_coef: float = 0.5
    max_grad_norm: float = 1.0
    imitation_coef: float = 0.0
    update_threads: int = 0
    desired_kl: float = 0.016
    lr_min: float = 1e-6
    lr_max: float = 1e-2
    anneal_lr: bool = False
    advantage: str = "gae"
    obs_norm: str = "first_batch"
    device: str = "cpu"

    def __post_init__(self):
        check_number("PPOConfig.update_threads", self.update_threads, integer=True)
        if not (isinstance(self.device, str) and re.fullmatch(r"cpu|cuda(:\d+)?", self.device)):
            raise ConfigError(f"PPOConfig.device (ppo.device) must be 'cpu' or a CUDA device ('cuda', 'cuda:1'), "
                              f"got {self.device!r}")
        for k in ("total_frames", "frames_per_batch", "epochs", "minibatch_size"):
            check_number(f"PPOConfig.{k}", getattr(self, k), low=1, integer=True)
        check_numbers("PPOConfig", self, ("lr", "clip_epsilon", "entropy_coef", "critic_coef", "max_grad_norm",
                                          "imitation_coef", "desired_kl", "lr_min", "lr_max"))
        if not 0 < self.lr_min <= self.lr <= self.lr_max:
            raise ConfigError(f"PPOConfig: need 0 < lr_min ≤ lr ≤ lr_max, got lr_min={self.lr_min}, lr={self.lr}, "
                              f"lr_max={self.lr_max}")
        for k in ("gamma", "lmbda"):
            check_number(f"PPOConfig.{k}", getattr(self, k), high=1.0)
        if self.advantage not in ADVANTAGES:
            raise ConfigError(f"PPOConfig.advantage must be one of {ADVANTAGES}, got {self.advantage!r}")
        if self.obs_norm not in OBS_NORMS:
            raise ConfigError(f"PPOConfig.obs_norm must be one of {OBS_NORMS}, got {self.obs_norm!r}")
        if self.anneal_lr and self.desired_kl > 0:
            raise ConfigError(f"PPOConfig: anneal_lr and desired_kl={self.desired_kl} both set the learning rate; "
                              f"set desired_kl=0 to anneal it")

    def annealed_lr(self, frames: int) -> float:
        """``anneal_lr``'s rate for an iteration that starts after ``frames`` frames: linear from ``lr``
        at 0 to ``lr_min`` at ``total_frames``.

        >>> PPOConfig(total_frames=1000, lr=1e-3, lr_min=1e-5, anneal_lr=True, desired_kl=0).annealed_lr(500)
        0.000505
        """
        done = min(max(frames / self.total_frames, 0.0), 1.0)
        return self.lr + (self.lr_min - self.lr) * done


#: how local collector workers can start (:func:`adadex.train.collectors.start_worker_server`)
START_METHODS = ("forkserver", "spawn")


@dataclass
class CollectorConfig:
    """Where the env steps run: in this process, in worker processes, or on a Ray cluster.

    ``local``: ``workers`` = 1 steps the envs in this process (TorchRL ``Collector``), more starts
    that many processes (``MultiSyncCollector``); ``ray``: ``workers`` remote collectors on a Ray
    cluster (``RayCollector``; a local cluster unless ``ray_address``). Splitting the worlds over
    workers lets collection use more cores than one process's policy and physics threads.

    Attributes:
        workers: collector processes (default 1: collect in this process).
        backend: ``"local"`` (default) or ``"ray"``.
        worlds: B, worlds of each worker's env (default 64).
        env_threads: MuJoCo rollout threads per env (default 2); 0 steps physics on the env's own
            thread, with no hand-off to a pool thread — faster for the 1-thread workers of a split
            (``workers=2 worlds=32``; docs/training-log.md, "Speed").
        ray_address: the Ray cluster to join (default ``None``: start a local one).
        group_size: worlds of a group that share their episodes' draws — the reference, Table 3's
            physics, the object's displacement and every step's noise — and start together (default 1:
            every world draws alone); must divide ``worlds``. Common random numbers for
            ``ppo.advantage="group"`` (:class:`~adadex.envs.tracking.TrackingEnv`'s ``group_size``).
        start_method: how local worker processes start (``multiprocessing``): ``"forkserver"``
            (default) forks each from a server process that imported torch, TorchRL and MuJoCo once,
            so only the first pays the imports; ``"spawn"`` (TorchRL's default) starts each as a new
            interpreter that imports them again.
    """

    workers: int = 1
    backend: str = "local"
    worlds: int = 64
    env_threads: int = 2
    ray_address: str | None = None
    start_method: str = "forkserver"
    group_size: int = 1

    def __post_init__(self):
        check_number("CollectorConfig.workers", self.workers, low=1, integer=True)
        check_number("CollectorConfig.worlds", self.worlds, low=1, integer=True)
        check_number("CollectorConfig.env_threads", self.env_threads, low=0, integer=True)
        check_number("CollectorConfig.group_size", self.group_size, low=1, integer=True)
        if self.worlds % self.group_size:
            raise ConfigError(f"CollectorConfig.group_size={self.group_size} must divide worlds={self.worlds}")
        if self.backend not in ("local", "ray"):
            raise ConfigError(f"CollectorConfig.backend must be 'local' or 'ray', got {self.backend!r}")
        if self.start_method not in START_METHODS:
            raise ConfigError(f"CollectorConfig.start_method must be one of {START_METHODS}, got {self.start_method!r}")


@dataclass
class SimConfig:
    """The envs' physics (recipes: ``sim.backend=warp``): which simulator steps the worlds.

    Attributes:
        backend: ``"rollout"`` (default) — MuJoCo's ``mujoco.rollout`` thread pool on the CPU cores —
            or ``"warp"`` — MuJoCo Warp on its default device, a GPU when there is one
            (``pip install "adadex[warp]"``; see :mod:`adadex.sim.warp_backend`).
    """

    backend: str = "rollout"

    def __post_init__(self):
        from adadex.sim.batched import BACKENDS

        if self.backend not in BACKENDS:
            raise ConfigError(f"SimConfig.backend (sim.backend) must be one of {', '.join(map(repr, BACKENDS))}, "
                              f"got {self.backend!r}")


@dataclass
class PolicyConfig:
    """The tracker trained (:class:`adadex.modules.tracker.Tracker` arguments).

    Built by :meth:`tracker`, the one place a tracker is made from settings, so every trainer and
    benchmark trains the same network (``policy.*`` in the recipes).

    Attributes:
        hidden: widths of the actor's and the critic's hidden layers (default (256, 256, 128)).
        residual: > 0 (default 0.25 rad): the action is kinematic replay plus a learned correction
            within ±``residual`` rad (see Tracker); the target is then q̂_{t+1} + correction, so this
            bounds how far the policy may leave the reference. 0: a plain policy.
        init_scale: initial pre-tanh exploration scale of the correction (default 0.05, ±0.0125 rad
            at residual 0.25).
        loc_bound: bound of the pre-tanh mean, ``b·tanh(loc/b)`` (TorchRL's tanh_loc; default 5; 0:
            none; why: docs/training.md, "Numerical safety").
        anchor: > 0 (default 0.05 m): the feed-forward is replay of the reference shifted onto the
            object where it started the episode, fading out over this many metres of the reference
            object's travel (Tracker ``anchor``, :class:`~adadex.modules.anchor.ObjectAnchor`); 0:
            plain replay.
        anchor_reach: > 0: objects displaced this far (m) or farther from the reference's start are
            left unanchored (Tracker ``anchor_reach``): holding them, every frame fails the paper's
            10 cm position threshold (:class:`~adadex.modules.anchor.ObjectAnchor`); 0 (default): no
            limit. Needs ``anchor`` > 0.
        anchor_iterations: Gauss–Newton steps placing the anchored palm (Tracker
            ``anchor_iterations``; default 3; 1: the linearization alone).
        anchor_lookahead: control steps ahead at which the anchor reads the reference object's
            travel (Tracker ``anchor_lookahead``; 1, 2, 4 or 12; default 1): further ahead, the hand
            starts bringing the object back onto the reference path before the reference moves it.
            Needs ``anchor`` > 0 when not 1.
    """

    hidden: tuple[int, ...] = (256, 256, 128)
    residual: float = 0.25
    init_scale: float = 0.05
    loc_bound: float = 5.0
    anchor: float = 0.05
    anchor_reach: float = 0.0
    anchor_iterations: int = 3
    anchor_lookahead: int = 1

    def __post_init__(self):
        from adadex.modules.anchor import LOOKAHEADS

        self.hidden = tuple(int(h) for h in self.hidden)
        check_numbers("PolicyConfig", self, ("residual", "init_scale", "loc_bound", "anchor", "anchor_reach"))
        check_number("PolicyConfig.anchor_iterations", self.anchor_iterations, low=1, integer=True)
        if self.anchor_reach > 0 and not self.anchor > 0:
            raise ConfigError(f"PolicyConfig.anchor_reach={self.anchor_reach} limits the object anchor, which is off "
                              f"(anchor={self.anchor}); set policy.anchor > 0 or drop anchor_reach")
        if isinstance(self.anchor_lookahead, bool) or self.anchor_lookahead not in LOOKAHEADS:    # as ObjectAnchor
            raise ConfigError(f"PolicyConfig.anchor_lookahead must be one of {LOOKAHEADS} (control steps ahead), "
                              f"got {self.anchor_lookahead!r}")
        self.anchor_lookahead = int(self.anchor_lookahead)
        if self.anchor_lookahead != 1 and not self.anchor > 0:
            raise ConfigError(f"PolicyConfig.anchor_lookahead={self.anchor_lookahead} times the object anchor, which "
                              f"is off (anchor={self.anchor}); set policy.anchor > 0 or drop anchor_lookahead")

    def tracker(self, max_action: float | None = None):
        """The :class:`~adadex.modules.tracker.Tracker` these settings describe (untrained): the one place a
        tracker is built from them, so every trainer and benchmark builds the same one. ``max_action``:
        the env's action bound (``TrackingConfig.max_action``; default the Tracker's own)."""
        from adadex.modules.tracker import Tracker

        return Tracker.from_config(self, max_action=max_action)


@dataclass
class ModulatorSettings:
    """Modulator RL (paper Sec. 3.2): PPO on ``TransformedEnv(TrackingEnv, modulation(channels, tracker))``
    with the generalist ``tracker`` (a checkpoint) frozen inside the env; the policy trained is a
    :class:`~adadex.modules.modulator.Modulator` for ``channels``.

    Set as :attr:`TrainConfig.modulator` (``modulator.*`` in the recipes), it turns a tracker run into
    a modulator run; the tracker checkpoint is loaded here, before any work, so a bad one fails at once.

    Attributes:
        tracker: path of the frozen tracker's checkpoint (required; it must load).
        channels: the modulation channels, ``"R+O+T"`` (default), ``"C+T"``, … (see
            :class:`~adadex.modules.channels.ModulationLayout`).
        hidden: widths of the modulator's trunk and critic hidden layers (default (256, 256, 128)).
        init_scale: initial exploration scale (pre-tanh): ``None`` (default) — each channel's own,
            sized so that sampling an untrained modulator leaves the tracker's success intact
            (``CHANNELS[c].init_scale``; docs/modulation.md, "Exploration sized per channel"); a number
            for all channels; or ``{channel: scale}``.
        loc_bound: bound of the pre-tanh mean, as :attr:`PolicyConfig.loc_bound` (default 5).
        modulation: :class:`~adadex.modules.channels.ModulationConfig` fields to override (λ's,
            bounds, persistence; default none).
        inputs: what the modulator reads: ``"view"`` (default: the tracker's observation plus the
            original reference, its edit, servo lag, last action, phase and ``history`` previous
            frames) or ``"observation"``.
        history: previous frames in the view (default 3).
        prior: ``"anchor"``: channel C's palm action is an offset around the object anchor's palm
            shift (the untrained modulator *is* the anchored feed-forward); ``None`` (default): around
            zero. See :class:`~adadex.modules.modulator.Modulator` and docs/modulation.md.
        prior_reach: m; > 0: the prior leaves objects displaced this far or farther where they lie
            (``Tracker(anchor_reach=…)``); 0 (default): it reaches for every object. Needs ``prior``.
        hold_steps: > 0: while sampling, the ``hold_scale`` entries are shifted by noise redrawn every
            ``hold_steps`` steps and held in between (exploration that lasts long enough to reach;
            PPO's ratios stay exact); 0 (default): no held noise.
        hold_scale: the held noise's scale per channel (``{"C": 0.1}``) or entry (``{"palm": 0.2}``),
            or one number; required when ``hold_steps`` > 0 (default ``None``).
        context_free: channels whose choice reads no observation: one learned distribution for every
            episode (e.g. ``["K"]``, a robot's servo gains); default none. See
            :class:`~adadex.modules.modulator.Modulator`.
        focus: ``{channel: view parts}``: channels whose choice reads only those parts of the view,
            through a small trunk of its own (e.g. ``{A: [start_offset]}``); default none. See
            :class:`~adadex.modules.modulator.Modulator`.
        learner: ``"ppo"`` (default) or ``"paired"``: a modulator whose channels all latch once per
            episode (A, L, K) fitted to paired rollouts of candidate choices
            (:mod:`adadex.train.paired_choice`) instead of PPO; ``ppo.*`` is then unused.
        paired: :class:`~adadex.train.paired_choice.PairedChoiceConfig` fields for ``learner=paired``
            (``arms``, ``repeats``, ``steps``, …; default none changed).
        core: ``"gru"``: a recurrent core (TorchRL's ``GRUModule``) over the modulator's input, its state
            carried in the env and PPO's updates run on whole sequences; ``None`` (default): none. Not
            with ``prior``, ``hold_steps`` or ``learner=paired``. See :class:`~adadex.modules.modulator.Modulator`.
        core_size: the core's hidden size (default 128).
        decide_every: k > 1: the modulator decides every k control steps and its action holds in
            between (PPO scores one choice per k steps); 1 (default): every step. Not with ``prior``,
            ``hold_steps`` or ``learner=paired``; needs ``inputs="view"``. See
            :class:`~adadex.modules.modulator.Modulator`.
    """

    tracker: str
    channels: str = "R+O+T"
    hidden: tuple[int, ...] = (256, 256, 128)
    init_scale: Any = None                 # float | dict | None (OmegaConf: a union of containers)
    loc_bound: float = 5.0
    modulation: dict = field(default_factory=dict)
    inputs: str = "view"
    history: int = 3
    prior: str | None = None
    prior_reach: float = 0.0
    hold_steps: int = 0
    hold_scale: Any = None                 # float | dict | None
    context_free: tuple[str, ...] = ()
    focus: dict = field(default_factory=dict)
    learner: str = "ppo"
    paired: dict = field(default_factory=dict)
    core: str | None = None
    core_size: int = 128
    decide_every: int = 1

    def __post_init__(self):
        from adadex.modules.modulator import INPUTS, ModulationLayout, channel_scales

        if self.prior not in (None, "anchor"):
            raise ConfigError(f"ModulatorSettings.prior (modulator.prior) must be 'anchor' or null, got {self.prior!r}")
        check_number("ModulatorSettings.prior_reach (modulator.prior_reach)", self.prior_reach)
        if self.prior_reach > 0 and self.prior is None:
            raise ConfigError(f"ModulatorSettings.prior_reach={self.prior_reach} (modulator.prior_reach) limits the "
                              f"anchor prior, which is off; set modulator.prior=anchor or modulator.prior_reach=0")
        check_number("ModulatorSettings.hold_steps", self.hold_steps, low=0, integer=True)
        if isinstance(self.hold_scale, Mapping):
            self.hold_scale = {str(k): v for k, v in self.hold_scale.items()}
        if self.hold_steps > 0 and not self.hold_scale:
            raise ConfigError(f"ModulatorSettings: hold_steps={self.hold_steps} holds noise of no size; set "
                              f"modulator.hold_scale (e.g. {{palm: 0.1}})")

        self.hidden = tuple(int(h) for h in self.hidden)
        self.context_free = tuple(str(c) for c in self.context_free)
        layout = ModulationLayout(self.channels)
        unknown = [c for c in self.context_free if c not in layout.channels]
        if unknown:
            raise ConfigError(f"ModulatorSettings.context_free (modulator.context_free): channels {unknown} are not "
                              f"among {layout.name}")
        if isinstance(self.init_scale, Mapping):
            self.init_scale = {str(k): v for k, v in self.init_scale.items()}
        if not isinstance(self.focus, Mapping):
            raise ConfigError(f"ModulatorSettings.focus (modulator.focus) must be {{channel: [view parts]}}, "
                              f"got {self.focus!r}")
        self.focus = {str(k): [v] if isinstance(v, str) else [str(p) for p in v] for k, v in self.focus.items()}
        if self.focus:            # the modulator's own check, before any work
            from adadex.modules.modulator import checked_focus
            from adadex.modules.modulator_view import ViewLayout

            view = ViewLayout(layout.channels, int(self.history)) if self.inputs == "view" else None
            try:
                checked_focus(self.focus, layout, view, self.context_free)
            except (ConfigError, ValueError) as e:
                raise ConfigError(f"ModulatorSettings.focus (modulator.focus): {e}") from None
        try:
            channel_scales(ModulationLayout(self.channels), self.init_scale)
        except ValueError as e:
            raise ConfigError(f"ModulatorSettings: {e}") from None
        check_number("ModulatorSettings.loc_bound", self.loc_bound)
        check_number("ModulatorSettings.history", self.history, integer=True)
        self._check_core()
        self._check_decide_every()
        if self.inputs not in INPUTS:
            raise ConfigError(f"ModulatorSettings.inputs must be one of {INPUTS}, got {self.inputs!r}")
        from adadex.modules.channels import ModulationConfig
        from adadex.train.schema import changes

        self.modulation = changes(ModulationConfig, self.modulation, "ModulatorSettings.modulation")
        self._check_learner(layout, ModulationConfig(**self.modulation))
        if not Path(self.tracker).is_file():
            raise ConfigError(f"ModulatorSettings.tracker: no tracker checkpoint at {self.tracker!r} "
                              f"(train or distill one first)")
        from adadex.errors import CheckpointError
        from adadex.modules.tracker import Tracker

        try:                               # before any work: the recipe loads it first in the collector
            Tracker.load(self.tracker)
        except CheckpointError as e:
            raise ConfigError(f"ModulatorSettings.tracker: {e}") from None


    def _check_core(self) -> None:
        """``core`` and ``core_size``, and what a core cannot be combined with, before any work."""
        from adadex.modules.nets import CORES

        if self.core not in CORES:
            raise ConfigError(f"ModulatorSettings.core (modulator.core) must be one of {CORES}, got {self.core!r}")
        check_number("ModulatorSettings.core_size", self.core_size, strict_low=True, integer=True)
        if self.core is None:
            return
        clash = [name for name, on in (("prior", self.prior is not None), ("hold_steps", self.hold_steps > 0),
                                       ("learner=paired", self.learner == "paired")) if on]
        if clash:
            raise ConfigError(f"ModulatorSettings.core={self.core!r} (modulator.core) cannot be combined with "
                              f"{', '.join(clash)}")

    def _check_decide_every(self) -> None:
        """``decide_every`` and what it cannot be combined with, before any work."""
        check_number("ModulatorSettings.decide_every (modulator.decide_every)", self.decide_every, low=1, integer=True)
        if self.decide_every == 1:
            return
        clash = [name for name, on in (("prior", self.prior is not None), ("hold_steps", self.hold_steps > 0),
                                       ("learner=paired", self.learner == "paired"),
                                       (f"inputs={self.inputs!r}", self.inputs != "view")) if on]
        if clash:
            raise ConfigError(f"ModulatorSettings.decide_every={self.decide_every} (modulator.decide_every) cannot be "
                              f"combined with {', '.join(clash)}")

    def _check_learner(self, layout, modulation) -> None:
        """``learner`` and ``paired``, before any work (a paired fit needs every channel latched)."""
        from adadex.train.paired_choice import PairedChoiceConfig, check_latched
        from adadex.train.schema import changes

        if self.learner not in ("ppo", "paired"):
            raise ConfigError(f"ModulatorSettings.learner (modulator.learner) must be 'ppo' or 'paired', "
                              f"got {self.learner!r}")
        self.paired = changes(PairedChoiceConfig, self.paired, "ModulatorSettings.paired")
        if "arms" in self.paired:
            self.paired["arms"] = [v if isinstance(v, (int, float)) else list(v) for v in self.paired["arms"]]
        self.paired_config()
        if self.learner == "paired":
            check_latched(layout, modulation)

    def paired_config(self):
        """The :class:`~adadex.train.paired_choice.PairedChoiceConfig` of ``learner=paired``."""
        from adadex.train.paired_choice import PairedChoiceConfig

        p = dict(self.paired)
        if "arms" in p:
            p["arms"] = tuple(v if isinstance(v, (int, float)) else tuple(v) for v in p["arms"])
        return PairedChoiceConfig(**p)


def _modulator_from(d: Mapping) -> ModulatorSettings | None:
    """A recipe's ``modulator`` node: ``None`` (a tracker run) while ``modulator.tracker`` is unset —
    refused if other modulator settings differ from their defaults — else :class:`ModulatorSettings`."""
    from adadex.train.schema import changes

    d = dict(d)
    if d.get("tracker") is not None:
        return ModulatorSettings(**d)
    from adadex.modules.channels import ModulationConfig

    from adadex.train.paired_choice import PairedChoiceConfig

    d.pop("tracker", None)
    given = {f"modulation.{k}": v for k, v in changes(ModulationConfig, d.pop("modulation", None),
                                                          "TrainConfig.modulator.modulation").items()}
    given.update({f"paired.{k}": v for k, v in changes(PairedChoiceConfig, d.pop("paired", None),
                                                       "TrainConfig.modulator.paired").items()})
    given.update(changes(ModulatorSettings, d, "TrainConfig.modulator", drop=("tracker", "modulation", "paired")))
    if given:
        raise ConfigError(f"modulator.{sorted(given)[0]}={given[sorted(given)[0]]!r} is a modulator setting: give "
                          f"modulator.tracker (the frozen generalist) to train a modulator, or use "
                          f"recipes/train_modulator.py")
    return None


def randomization_with(changes: dict, where: str):
    """Table 3's :class:`~adadex.envs.randomization.Randomization` with ``changes`` (field → value; lists
    become tuples); a bad field or value raises :class:`ConfigError` naming ``where``."""
    from adadex.envs.randomization import Randomization

    fixed = sorted(set(changes) & {"effects", "patch"})
    if fixed:
        raise ConfigError(f"{where}: {fixed} cannot be set here; build a Randomization in code "
                          f"(Randomization.from_patch) for per-joint ranges and patches")
    values = {k: tuple(v) if isinstance(v, (list, tuple)) else v for k, v in changes.items()}
    try:
        return from_known_keys(Randomization, values)
    except (ValueError, TypeError) as e:
        raise ConfigError(f"{where}: {e}") from e


@dataclass
class TrainConfig:
    """A PPO tracker run: which references, which env, which learner, where results go.

    One dataclass tree that the Hydra recipes fill (``recipes/train_ppo.py key=value``) and
    :func:`~adadex.train.ppo.train` reads; it is saved with every checkpoint, so a resumed run can be
    checked against the settings it started with.

    The references trained on: ``references`` (dataset indices) if given; else the references of
    ``split`` (``[name, part]``; the vanilla-PPO baseline: all training references), narrowed to the
    semantic group ``group`` (a group id: a specialist, paper A.3.1) when one is given.

    Attributes:
        dataset: the reference dataset's folder (required).
        out: the run's folder: checkpoint, logs, the trained policy (required).
        seed: seeds torch, numpy and the envs (default 0).
        resume: continue the run in ``out`` from its checkpoint (default off: a run already in
            ``out`` is refused); settings that would change the result must match the checkpoint's.
        split: ``(name, part)`` of the references trained on (default the unseen-trajectory training
            part); ``None``: every reference. Ignored when ``references`` is given.
        group: a semantic group id: train a specialist on that group of ``split`` (default ``None``:
            every group).
        references: dataset indices to train on instead of a split (default ``None``).
        randomize: Table 3 domain randomization, in training and its evaluations (default on).
        ppo: the learner (:class:`PPOConfig`).
        collector: where the env steps run (:class:`CollectorConfig`).
        sim: the envs' physics (:class:`SimConfig`).
        policy: the tracker trained (:class:`PolicyConfig`).
        modulator: set: train a modulator around this frozen tracker instead of a tracker
            (:class:`ModulatorSettings`; default ``None``).
        env: :class:`~adadex.envs.tracking.TrackingConfig` fields to change for this run (``{"window":
            60}``; the reward has its own setting); the rest keep their defaults (or those of the
            ``env_config`` the trainer is given). Checked here.
        reward: :class:`~adadex.envs.reward.RewardConfig` fields to change for this run
            (``{"w_prox": 1.0}``); the rest keep their defaults (or those of the ``env_config`` the
            trainer is given). Checked here.
        randomization: :class:`~adadex.envs.randomization.Randomization` fields to change when
            ``randomize`` is on (``{"object_xy_std": 0.02, "object_mass": [0.9, 1.1]}``), for
            training and its evaluations; the rest keep Table 3's values. Per-joint effect ranges
            and patches are set in code. Checked here.
        checkpoint_every: iterations between checkpoints (default 5).
        eval_every: iterations between evaluations during training (default 0: only at the end).
        eval_split: ``(name, part)`` of the references evaluated (default ``None``: the training
            references themselves).
        eval_max_references: at most this many references evaluated (default 64; 0: no evaluation,
            periodic or final).
        wandb: log to Weights & Biases, offline unless ``WANDB_MODE`` says otherwise (default on).
        progress: show a progress bar (default on).
    """

    dataset: str
    out: str
    seed: int = 0
    resume: bool = False
    split: tuple[str, str] | None = ("unseen_trajectory", "train")
    group: int | None = None
    references: tuple[int, ...] | None = None
    randomize: bool = True
    ppo: PPOConfig = field(default_factory=PPOConfig)
    collector: CollectorConfig = field(default_factory=CollectorConfig)
    sim: SimConfig = field(default_factory=SimConfig)
    policy: PolicyConfig = field(default_factory=PolicyConfig)
    modulator: ModulatorSettings | None = None
    env: dict = field(default_factory=dict)
    reward: dict = field(default_factory=dict)
    randomization: dict = field(default_factory=dict)
    checkpoint_every: int = 5
    eval_every: int = 0
    eval_split: tuple[str, str] | None = None
    eval_max_references: int = 64
    wandb: bool = True
    progress: bool = True

    def __post_init__(self):
        if self.split is not None:
            self.split = tuple(self.split)
            if len(self.split) != 2 or not all(isinstance(s, str) for s in self.split):
                raise ConfigError(f"TrainConfig.split must be [name, part], e.g. [unseen_trajectory, train], "
                                  f"got {self.split!r}")
        if self.eval_split is not None:
            self.eval_split = tuple(self.eval_split)
        if self.references is not None:
            self.references = tuple(int(i) for i in self.references)
        check_number("TrainConfig.seed", self.seed, integer=True)
        if self.group is not None:
            check_number("TrainConfig.group", self.group, integer=True)
        check_number("TrainConfig.checkpoint_every", self.checkpoint_every, low=1, integer=True)
        check_number("TrainConfig.eval_every", self.eval_every, integer=True)
        check_number("TrainConfig.eval_max_references", self.eval_max_references, integer=True)
        if isinstance(self.modulator, Mapping):
            self.modulator = _modulator_from(self.modulator)
        for name, sub in (("ppo", PPOConfig), ("collector", CollectorConfig), ("sim", SimConfig),
                          ("policy", PolicyConfig), ("modulator", ModulatorSettings)):
            v = getattr(self, name)
            if isinstance(v, Mapping):
                setattr(self, name, sub(**v))
        if self.ppo.advantage == "group" and self.collector.group_size < 2:
            raise ConfigError(f"ppo.advantage=group needs groups of worlds to compare: collector.group_size ≥ 2, "
                              f"got {self.collector.group_size}")
        from adadex.envs.randomization import Randomization
        from adadex.envs.reward import RewardConfig
        from adadex.envs.tracking import TrackingConfig
        from adadex.train.schema import ENV_CODE_ONLY, RANDOMIZATION_CODE_ONLY, changes

        self.env = changes(TrackingConfig, self.env, "TrainConfig.env", drop=ENV_CODE_ONLY)
        self.reward = changes(RewardConfig, self.reward, "TrainConfig.reward")
        self._reward_config(None)             # out-of-range reward settings fail here
        self.env_config()                     # … and env settings
        if self.randomization and set(self.randomization) & set(RANDOMIZATION_CODE_ONLY):
            self._randomization()             # says where effects and patches are set
        self.randomization = changes(Randomization, self.randomization, "TrainConfig.randomization",
                                     drop=RANDOMIZATION_CODE_ONLY)
        self._randomization()                 # … and randomization settings

    def _reward_config(self, base):
        from adadex.envs.reward import RewardConfig

        base = RewardConfig() if base is None else base
        return from_known_keys(RewardConfig, {**dataclasses.asdict(base), **self.reward})

    def _randomization(self):
        return randomization_with(self.randomization, "TrainConfig.randomization")

    def randomization_config(self):
        """The run's :class:`~adadex.envs.randomization.Randomization` (Table 3 with this run's
        ``randomization`` settings), or None when ``randomize`` is off."""
        return self._randomization() if self.randomize else None

    def env_config(self, base=None):
        """``base`` (a :class:`~adadex.envs.tracking.TrackingConfig`, default: the defaults) with this
        run's env and reward settings."""
        from adadex.envs.tracking import TrackingConfig

        base = TrackingConfig() if base is None else base
        try:
            return dataclasses.replace(base, **self.env, reward=self._reward_config(base.reward))
        except (TypeError, ValueError) as e:
            raise ConfigError(f"TrainConfig.env: {e}") from None

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, d: dict) -> TrainConfig:
        return from_known_keys(cls, d)
