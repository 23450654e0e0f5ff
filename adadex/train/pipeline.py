"""The paper's Table 1 from one command: specialists → teacher rollouts → distilled generalist →
(replay and the generalist evaluated) → modulators → baselines → evaluation of the other rows →
``table1.md`` / ``table1.json`` and the figures.

Per training seed (``seed_<s>/`` under ``out``):

=========================  ==========================================================================
``specialists/spec_<k>``   PPO specialists (paper A.3.1), each on a block of the training split's
                           semantic groups (the small presets cannot afford one per group)
``rollouts``               their successful randomized rollouts, a TorchRL memmap replay buffer
``generalist``             the distilled generalist tracker (behaviour cloning, paper A.3.2)
``modulators/<row>``       modulator RL with the generalist frozen: R, RT, ROT, O (paper Sec. 3.2)
``baselines/ppo``          vanilla PPO on all training references (paper B.2)
``baselines/il_rl``        DexTrack-style IL+RL: PPO + imitation of the logged teacher actions (B.2.1)
``scaling/frac_<f>``       generalists distilled from a fraction of the references (Fig. 6)
``eval/<split>/<cond>/``   one ``<row>/stage.json`` per row: the evaluation summary, per-reference and
                           per-episode results, and the return–completion rank correlation
``eval/teachers/spec_<k>`` the generalist against specialist k on k's own training references, paired
                           (``eval/teachers_vs_replay/spec_<k>``: specialist k against replay there)
``eval/channel_usage``     the first seed's: each modulator's mean |action| per channel (``<row>/``;
                           ``figures/channel_usage.png``)
=========================  ==========================================================================

then, over all seeds, ``table1.json`` (``{split: {condition: {row: {metric: mean, metric_ci95:
[lo, hi], diff_vs_tracker: {metric: d}, diff_vs_tracker_ci95: {metric: [lo, hi]}}}}}``: intervals
bootstrapped over test references pooled across seeds, differences paired per episode, as every row
of a seed meets the same draws; :mod:`adadex.eval.table1`), ``table1.md`` and ``figures/``: the
ablation bars, Fig. 4 (original, modulated and executed object path), Fig. 5 (the modulated latent
decoded against the object), Fig. 6 (data scaling), Fig. 12 (latent smoothness ρ), and how much each
modulator uses each of its channels (``channel_usage.png`` / ``.json``: mean |action| per entry), and
``generalist_vs_teachers.json``: per seed, what each specialist gained over kinematic replay on its own
references and how much of its completion the distilled generalist kept there.

**Settings.** :class:`PipelineConfig`: the dataset, the seeds, what every stage shares (``env``,
``reward``, ``randomization``, ``sim``, ``collector``) and one group per stage — ``specialist``,
``rollouts``, ``distill``, ``modulator``, ``baseline``, ``evaluation`` — each with its own learner
where it trains (``specialist.ppo.total_frames``, ``modulator.ppo.total_frames``,
``baseline.ppo.total_frames``). The recipe's keys are these fields (the ``adadex_pipeline`` node of
:mod:`adadex.train.schema`).

**Seeds side by side.** ``seed_workers=2`` (the default) runs each seed's chain in its own process (the table
and figures are made in the main one). On 2 cores this fills the core that one seed leaves idle while it
updates, distils or evaluates on one torch thread; the results are the same as one seed after another.

**Resuming.** Every stage writes ``stage.json`` (its settings and result) when it has finished; a
stage whose ``stage.json`` exists with the same settings is skipped, one with *other* settings is
refused (use a new ``out``). A killed training stage continues from its ``checkpoint.pt``; rollouts
and evaluations are written as one unit, so a killed one simply runs again.

Example::

    from adadex.train.pipeline import PipelineConfig, run_pipeline
    result = run_pipeline(PipelineConfig(out="runs/table1", dataset_preset="tiny", seeds=(0,),
                                         specialist={"count": 2, "ppo": {"total_frames": 512}}, ...))
    result["table"]["unseen_trajectory"]["randomized"]["ROT"]["completion_pct"]
"""

from __future__ import annotations

import dataclasses
import json
import time
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from adadex.data.reference import ReferenceDataset
from adadex.envs.randomization import Randomization
from adadex.envs.reward import RewardConfig
from adadex.envs.tracking import TrackingConfig, episode_references
from adadex.errors import ConfigError, check_number, from_known_keys
from adadex.io import atomic_write_text, check_output_dir, mark_output_dir
from adadex.train.config import (CollectorConfig, ModulatorSettings, PolicyConfig, PPOConfig, SimConfig,
                                 TrainConfig, randomization_with)
from adadex.train.schema import ENV_CODE_ONLY, RANDOMIZATION_CODE_ONLY, changes, check_fields, field_default
from adadex.train.stages import PIPELINE_RUN, earlier_pipeline, run_in_processes, run_stage
from adadex.train.table_so_far import collect

#: modulator rows of the table → the channel set each trains
MODULATOR_ROWS = {"R": "R", "RT": "R+T", "ROT": "R+O+T", "O": "O"}
#: the rows every seed evaluates, in the order it evaluates them
EVAL_ROWS = ("replay", "ppo", "il_rl", "tracker", *MODULATOR_ROWS)
EVAL_SPLITS = ("unseen_trajectory", "unseen_object")
#: the :class:`ModulatorSettings` fields a :class:`ModulatorStage` sets for every modulator row (the
#: tracker, the channels and ``modulation`` are the pipeline's; ``learner``/``paired`` are not among them:
#: the paired learner fits only channels chosen once per episode, and every row of :data:`MODULATOR_ROWS`
#: acts every step)
MODULATOR_SETTINGS = ("hidden", "init_scale", "loc_bound", "inputs", "history", "prior", "prior_reach", "hold_steps",
                      "hold_scale", "context_free", "focus", "core", "core_size", "decide_every")


def _pipeline_ppo(total_frames: int) -> PPOConfig:
    """PPO as Table 1 was measured: one torch thread for the updates (adadex.train.threads) and the
    constant learning rate (``PPOConfig.desired_kl``'s adaptive default was chosen on anchored
    specialists, which the pipeline does not train); ``<stage>.ppo.desired_kl=0.016`` turns it on."""
    return PPOConfig(total_frames=total_frames, desired_kl=0.0, update_threads=1)


def _modulator_ppo() -> PPOConfig:
    """The modulators' learner: the pipeline's, with the KL-adaptive rate (``desired_kl=0.016``). At the
    constant 3e-4 the modulators' updates run far past PPO's trust region (median clip fraction ~0.8): most
    samples are clipped in every update, and the reach-prior modulators learned nothing resolved against
    themselves untrained, where with the adaptive rate they gain a couple of completion points
    (docs/modulation.md). ``modulator.ppo.desired_kl=0`` restores the constant rate."""
    return dataclasses.replace(_pipeline_ppo(250_000), desired_kl=0.016)


def _pipeline_policy() -> PolicyConfig:
    """The pipeline's trackers are plain residual trackers (kinematic replay plus a learned correction),
    not object-anchored ones (``PolicyConfig.anchor``, which the specialist recipes keep): the full anchor
    costs Table 1's randomized completion several points against replay. ``specialist.policy.anchor=0.05``
    (``baseline.policy.anchor=0.05``) restores it; with ``anchor_reach=0.10`` and ``anchor_lookahead=4`` the
    anchored chain carries the object (object completion about ten points above replay) but completes a few
    points fewer frames than replay, both resolved over three seeds (docs/table1.md). The paper's metric is
    the headline, so the default stays unanchored; the anchored setting is for where carrying the object is
    what counts."""
    return PolicyConfig(anchor=0.0)


def _modulator_default(name: str):
    """:class:`ModulatorSettings`' default of field ``name``, as a field of :class:`ModulatorStage` (one
    default per setting: written once, there)."""
    f = next(f for f in dataclasses.fields(ModulatorSettings) if f.name == name)
    if f.default_factory is not dataclasses.MISSING:
        return field(default_factory=f.default_factory)
    return field(default=f.default)


def _group(owner, name: str, cls, where: str):
    """``owner.name`` as a ``cls``: one as is, or a mapping of ``cls`` fields that change the field's
    default (``{"total_frames": 512}`` keeps the stage's other PPO settings); a key that is not a field, or
    a bad value, is one :class:`ConfigError` naming ``where``."""
    value = getattr(owner, name)
    if isinstance(value, cls):
        return value
    if not isinstance(value, Mapping):
        raise ConfigError(f"{where} must be a mapping of {cls.__name__} fields, got {value!r}")
    check_fields(cls, value, where)
    base = field_default(type(owner), name)
    try:
        return dataclasses.replace(base, **value) if isinstance(base, cls) else cls(**value)
    except ConfigError as e:
        raise ConfigError(str(e) if str(e).startswith(where) else f"{where}: {e}") from None


@dataclass
class SpecialistStage:
    """The PPO specialists (paper A.3.1), each on a block of the training split's semantic groups
    (``specialist.*`` in the recipe).

    Attributes:
        count: specialists; the unseen-trajectory training split's semantic groups are shared out in
            this many blocks of whole groups (default 4; the paper has one per group).
        ppo: each specialist's learner (:class:`~adadex.train.config.PPOConfig`; default 250 000 frames,
            the constant learning rate and one update thread, as Table 1 was measured).
        policy: the trackers trained (:class:`~adadex.train.config.PolicyConfig`; default without the
            object anchor, ``anchor=0``). Its ``hidden`` is also the distilled generalist's, and the
            modulator runs carry it.
    """

    count: int = 4
    ppo: PPOConfig = field(default_factory=lambda: _pipeline_ppo(250_000))
    policy: PolicyConfig = field(default_factory=_pipeline_policy)

    def __post_init__(self):
        check_number("PipelineConfig.specialist.count", self.count, low=1, integer=True)
        self.ppo = _group(self, "ppo", PPOConfig, "PipelineConfig.specialist.ppo")
        self.policy = _group(self, "policy", PolicyConfig, "PipelineConfig.specialist.policy")


@dataclass
class RolloutStage:
    """The specialists' randomized teacher rollouts (``rollouts.*``; :mod:`adadex.train.rollouts`).

    Attributes:
        episodes: randomized teacher episodes per reference (default 4).
        criterion: which teacher episodes are kept: ``"mean_error"`` (default) or ``"completion>=x"``
            (:func:`adadex.train.rollouts.success_criterion`).
    """

    episodes: int = 4
    criterion: str = "mean_error"

    def __post_init__(self):
        from adadex.train.rollouts import success_criterion

        check_number("PipelineConfig.rollouts.episodes", self.episodes, low=1, integer=True)
        try:
            success_criterion(self.criterion)
        except ConfigError as e:
            raise ConfigError(f"PipelineConfig.rollouts.criterion: {e}") from None


@dataclass
class DistillStage:
    """The generalist distilled from the teacher rollouts, and the data-scaling study's generalists
    (``distill.*``; :mod:`adadex.train.distill`). Its network is the specialists' ``policy.hidden``.

    Attributes:
        steps: the distillation's Adam steps (default 3000).
        batch_size: the distillation's batch size (default 1024).
    """

    steps: int = 3000
    batch_size: int = 1024

    def __post_init__(self):
        for k in ("steps", "batch_size"):
            check_number(f"PipelineConfig.distill.{k}", getattr(self, k), low=1, integer=True)


@dataclass
class ModulatorStage:
    """Modulator RL around the frozen generalist, one run per row of :data:`MODULATOR_ROWS`
    (``modulator.*``; :class:`~adadex.train.config.ModulatorSettings`, whose defaults these are).

    Attributes:
        ppo: each modulator's learner (:class:`~adadex.train.config.PPOConfig`; default 250 000
            frames, the KL-adaptive rate at ``desired_kl=0.016`` and one update thread).
        reference_channel: the reference channel of the R rows (R, RT, ROT): ``"C"`` (default) — the
            compact edit, a palm offset through the arm Jacobian and a closure per finger (7 numbers,
            :class:`adadex.transforms.modulation.CompactModulation`), whose palm starts at the object
            anchor's shift (``prior``); ``"R"`` — the full per-frame residuals (112 numbers).
        modulation: :class:`~adadex.modules.channels.ModulationConfig` fields to change (λ's, bounds,
            persistence), for training and evaluating every modulator; kept as the changes from
            its defaults (default ``{"reach_lookahead": 4}``: the prior reads the reference object four
            frames ahead, ahead of the servos' lag).
        hidden: widths of the modulator's hidden layers (:attr:`ModulatorSettings.hidden`).
        init_scale: initial exploration scale: a number (default 0.03 for every channel: sampling the
            untrained +R+O+T row around a generalist then costs a couple of completion points, about three
            times that at the channels' own scales; docs/modulation.md), ``None`` (each channel's own) or
            ``{channel: scale}`` (:attr:`ModulatorSettings.init_scale`).
        loc_bound: bound of the pre-tanh mean (:attr:`ModulatorSettings.loc_bound`).
        inputs: what the modulator reads, ``"view"`` or ``"observation"``
            (:attr:`ModulatorSettings.inputs`).
        history: previous frames in the view (:attr:`ModulatorSettings.history`).
        prior: ``"anchor"`` (default) or ``None``: what channel C's palm action is an offset around
            (:attr:`ModulatorSettings.prior`), in the rows with C (``reference_channel="C"``): the untrained
            modulator reaches for the object where Table 3 moved it, and training learns corrections.
        prior_reach: m; > 0: the prior leaves objects displaced this far or farther where they lie
            (:attr:`ModulatorSettings.prior_reach`; default 0.10: past ~10 cm the paper's thresholds fail a
            hand that holds the object).
        hold_steps: > 0: held exploration noise, redrawn every this many steps
            (:attr:`ModulatorSettings.hold_steps`).
        hold_scale: the held noise's scale per channel or entry (:attr:`ModulatorSettings.hold_scale`).
        context_free: channels whose choice reads no observation (:attr:`ModulatorSettings.context_free`),
            in the rows that train them (default none).
        focus: ``{channel: view parts}`` read by those channels' heads alone (:attr:`ModulatorSettings.focus`),
            in the rows that train them (default none).
        core: ``"gru"``: a recurrent core over each modulator's input (:attr:`ModulatorSettings.core`);
            default ``None``.
        core_size: its hidden size (:attr:`ModulatorSettings.core_size`).
        decide_every: k > 1: each modulator decides every k control steps, its action held in between
            (:attr:`ModulatorSettings.decide_every`); default 1: every step.
        group_size: the modulators' worlds in groups on common random numbers
            (:attr:`~adadex.train.config.CollectorConfig.group_size`; with ``ppo.advantage=group``);
            default ``None``: the chain's ``collector.group_size``.
    """

    ppo: PPOConfig = field(default_factory=_modulator_ppo)
    reference_channel: str = "C"
    modulation: dict = field(default_factory=lambda: {"reach_lookahead": 4})
    hidden: tuple[int, ...] = _modulator_default("hidden")
    init_scale: Any = 0.03
    loc_bound: float = _modulator_default("loc_bound")
    inputs: str = _modulator_default("inputs")
    history: int = _modulator_default("history")
    prior: str | None = "anchor"
    prior_reach: float = 0.10
    hold_steps: int = _modulator_default("hold_steps")
    hold_scale: Any = _modulator_default("hold_scale")
    context_free: tuple[str, ...] = _modulator_default("context_free")
    focus: dict = _modulator_default("focus")
    core: str | None = _modulator_default("core")
    core_size: int = _modulator_default("core_size")
    decide_every: int = _modulator_default("decide_every")
    group_size: int | None = None

    def __post_init__(self):
        from adadex.modules.channels import ModulationConfig

        self.ppo = _group(self, "ppo", PPOConfig, "PipelineConfig.modulator.ppo")
        if self.group_size is not None:
            check_number("PipelineConfig.modulator.group_size", self.group_size, low=1, integer=True)
        if self.reference_channel not in ("R", "C"):
            raise ConfigError(f"PipelineConfig.modulator.reference_channel must be 'R' or 'C', "
                              f"got {self.reference_channel!r}")
        self.modulation = changes(ModulationConfig, self.modulation, "PipelineConfig.modulator.modulation")
        try:
            ModulationConfig(**self.modulation)
        except (ConfigError, ValueError, TypeError) as e:
            raise ConfigError(f"PipelineConfig.modulator.modulation: {e}") from None
        self.hidden = tuple(int(h) for h in self.hidden)
        from adadex.modules.channels import parse_channels

        try:
            self.context_free = parse_channels(self.context_free)
        except ConfigError as e:
            raise ConfigError(f"PipelineConfig.modulator.context_free: {e}") from None
        for mapping in ("init_scale", "hold_scale"):
            if isinstance(getattr(self, mapping), Mapping):
                setattr(self, mapping, {str(k): v for k, v in getattr(self, mapping).items()})
        # every row's settings checked now, not after the specialists: ModulatorSettings checks them all
        # before it looks for the tracker, which here is no file (the last check, the one let through)
        for row in MODULATOR_ROWS:
            try:
                ModulatorSettings(tracker="", channels=self.row_channels(row), modulation=dict(self.modulation),
                                  **self.settings(row))
            except ConfigError as e:
                if not str(e).startswith("ModulatorSettings.tracker:"):
                    raise ConfigError(f"PipelineConfig.modulator (row {row}): {e}") from None

    def row_channels(self, row: str) -> str:
        """The channels a modulator row trains: :data:`MODULATOR_ROWS` with ``reference_channel`` for R."""
        return "+".join(self.reference_channel if c == "R" else c for c in MODULATOR_ROWS[row].split("+"))

    def rows_note(self) -> str:
        """One line for ``table1.md``: what each modulator row trains (the R rows' reference channel, C's prior)."""
        rows = ", ".join(f"{label} = {self.row_channels(row)}" for label, row in
                         (("+R", "R"), ("+R+T", "RT"), ("+R+O+T", "ROT"), ("O only", "O")))
        prior = ""
        if self.prior == "anchor" and self.reference_channel == "C":
            reach = f" for objects within {100 * self.prior_reach:g} cm" if self.prior_reach > 0 else ""
            prior = f"; C's palm edit starts at the object anchor's shift{reach} (`modulator.prior=anchor`)"
        return f"The modulator rows train {rows}{prior}."

    def settings(self, row: str) -> dict:
        """The :data:`MODULATOR_SETTINGS` fields for ``row``, as :class:`ModulatorSettings` takes them
        (``context_free``: those of the row's channels)."""
        out = {k: getattr(self, k) for k in MODULATOR_SETTINGS}
        if "C" not in self.row_channels(row).split("+"):      # C's prior: nothing to shift in the O row
            out.update(prior=None, prior_reach=0.0)
        out["context_free"] = tuple(c for c in self.context_free if c in self.row_channels(row).split("+"))
        out["focus"] = {c: parts for c, parts in self.focus.items() if c in self.row_channels(row).split("+")}
        return out


@dataclass
class BaselineStage:
    """The baselines, vanilla PPO and DexTrack-style IL+RL (paper B.2), both on all training references
    (``baseline.*``).

    Attributes:
        ppo: both baselines' learner (:class:`~adadex.train.config.PPOConfig`; default 500 000 frames —
            they see all training references — the constant learning rate and one update thread).
        policy: the trackers trained (:class:`~adadex.train.config.PolicyConfig`; default without the
            object anchor, as the specialists).
        imitation_coef: IL+RL's imitation weight (default 1.0; vanilla PPO's is 0).
    """

    ppo: PPOConfig = field(default_factory=lambda: _pipeline_ppo(500_000))
    policy: PolicyConfig = field(default_factory=_pipeline_policy)
    imitation_coef: float = 1.0

    def __post_init__(self):
        self.ppo = _group(self, "ppo", PPOConfig, "PipelineConfig.baseline.ppo")
        self.policy = _group(self, "policy", PolicyConfig, "PipelineConfig.baseline.policy")
        check_number("PipelineConfig.baseline.imitation_coef", self.imitation_coef, strict_low=True)


@dataclass
class EvaluationStage:
    """The evaluations, the data-scaling study (Fig. 6) and the latent smoothness (Fig. 12)
    (``evaluation.*``).

    Attributes:
        repeats: Table 1's randomized evaluations: episodes per test reference, each on its own Table 3
            draw (default 16: with 47 references and 3 seeds, enough that a row's paired difference to
            the tracker has a bootstrap half-width ≤ 1.5 completion points; docs/table1.md).
        check_repeats: the same for the data-scaling study (Fig. 6) and the generalist-against-teachers
            check, which compare fewer, larger differences (default 4).
        scaling_fractions: the reference fractions of the data-scaling study, each in (0, 1]
            (default (0.125, 0.25, 0.5, 1.0)).
        smoothness_samples: observations ρ is measured on (Fig. 12; default 512).
    """

    repeats: int = 16
    check_repeats: int = 4
    scaling_fractions: tuple[float, ...] = (0.125, 0.25, 0.5, 1.0)
    smoothness_samples: int = 512

    def __post_init__(self):
        for k in ("repeats", "check_repeats", "smoothness_samples"):
            check_number(f"PipelineConfig.evaluation.{k}", getattr(self, k), low=1, integer=True)
        self.scaling_fractions = tuple(sorted({float(f) for f in self.scaling_fractions}))
        for f in self.scaling_fractions:
            check_number("PipelineConfig.evaluation.scaling_fractions[…]", f, high=1.0, strict_low=True)


#: the stage groups of :class:`PipelineConfig`: field → class
STAGES = {"specialist": SpecialistStage, "rollouts": RolloutStage, "distill": DistillStage,
          "modulator": ModulatorStage, "baseline": BaselineStage, "evaluation": EvaluationStage}


@dataclass
class PipelineConfig:
    """Everything the pipeline runs with; ``recipes/pipeline.yaml`` and its presets fill it.

    One group per stage; the recipe's keys are these fields (``specialist.ppo.total_frames``,
    ``env.window``, …). A group may be given as a mapping of its fields (``specialist={"count": 2,
    "ppo": {"total_frames": 512}}``); what it leaves out keeps the group's default.

    Attributes:
        out: the pipeline's folder (every stage's run, the table and the figures).
        dataset: a reference dataset folder; None (default): ``out/data``, built from
            ``dataset_preset`` when missing.
        dataset_preset: the preset built when ``dataset`` is None (default ``"small"``).
        dataset_seed: the seed of that build (default 0).
        dataset_planned_grasp: the built dataset holds the object with a pinch planned for the hand
            (:mod:`adadex.data.planned_grasp`), so its references carry what they grasp (nominal replay
            lifts 110 of 146 rising objects, against 15 of 161 with the retargeted human grasp; default
            True).
        seeds: training seeds: the whole chain runs once per seed (default (0, 1, 2): three seeds,
            over which every row's interval pools the test references).
        seed_workers: seeds trained side by side, each chain in its own process (default 2: on 2 cores
            it fills the core that one seed's single-threaded updates, distillation and evaluations
            leave idle).
        env: :class:`~adadex.envs.tracking.TrackingConfig` fields to change (``{"window": 60}``: frames
            per episode; only references that long take part), for every training stage, the teacher
            rollouts and the evaluations; kept as the changes from its defaults.
        reward: :class:`~adadex.envs.reward.RewardConfig` fields to change (``{"w_prox": 1.0}``), for
            every training stage and the evaluations; kept as the changes from its defaults.
        randomization: ``Randomization`` fields to change from Table 3 (``{"object_xy_std": 0.02}``),
            for every training stage, the teacher rollouts and the "randomized" evaluations alike;
            kept as the changes from Table 3.
        sim: the physics of every env of the chain (:class:`~adadex.train.config.SimConfig`;
            ``{"backend": "warp"}`` with ``ppo.device=cuda`` of each stage: the whole pipeline on a GPU;
            default ``mujoco.rollout`` on the CPU).
        collector: where each training stage's env steps run, and the worlds and physics threads of
            the teacher rollouts and evaluations too (:class:`~adadex.train.config.CollectorConfig`;
            local collectors only: ``backend="local"``, no ``ray_address``).
        specialist: the PPO specialists (:class:`SpecialistStage`).
        rollouts: their teacher rollouts (:class:`RolloutStage`).
        distill: the distilled generalist (:class:`DistillStage`).
        modulator: modulator RL on the generalist (:class:`ModulatorStage`).
        baseline: vanilla PPO and IL+RL (:class:`BaselineStage`).
        evaluation: the evaluations and the figures' samples (:class:`EvaluationStage`).
        wandb: each training stage also logs to wandb, offline unless ``WANDB_MODE`` says otherwise
            (default True).
        progress: show progress bars (default True).
    """

    out: str
    dataset: str | None = None
    dataset_preset: str = "small"
    dataset_seed: int = 0
    dataset_planned_grasp: bool = True
    seeds: tuple[int, ...] = (0, 1, 2)
    seed_workers: int = 2
    env: dict = field(default_factory=dict)
    reward: dict = field(default_factory=dict)
    randomization: dict = field(default_factory=dict)
    sim: SimConfig = field(default_factory=SimConfig)
    collector: CollectorConfig = field(default_factory=CollectorConfig)
    specialist: SpecialistStage = field(default_factory=SpecialistStage)
    rollouts: RolloutStage = field(default_factory=RolloutStage)
    distill: DistillStage = field(default_factory=DistillStage)
    modulator: ModulatorStage = field(default_factory=ModulatorStage)
    baseline: BaselineStage = field(default_factory=BaselineStage)
    evaluation: EvaluationStage = field(default_factory=EvaluationStage)
    wandb: bool = True
    progress: bool = True

    def __post_init__(self):
        self.seeds = tuple(int(s) for s in self.seeds)
        if not self.seeds or len(set(self.seeds)) != len(self.seeds):
            raise ConfigError(f"PipelineConfig.seeds must be distinct training seeds, got {list(self.seeds)}")
        check_number("PipelineConfig.seed_workers", self.seed_workers, low=1, integer=True)
        self.sim = _group(self, "sim", SimConfig, "PipelineConfig.sim")
        self.collector = _group(self, "collector", CollectorConfig, "PipelineConfig.collector")
        if self.collector.backend != "local" or self.collector.ray_address is not None:
            raise ConfigError(f"PipelineConfig.collector: the pipeline's stages collect locally (backend='local', "
                              f"ray_address=null), got backend={self.collector.backend!r}, "
                              f"ray_address={self.collector.ray_address!r}")
        for name, cls in STAGES.items():
            setattr(self, name, _group(self, name, cls, f"PipelineConfig.{name}"))
        for name in STAGES:                  # a stage's learner and its worlds agree before any stage runs
            ppo = getattr(getattr(self, name), "ppo", None)
            if ppo is not None and ppo.advantage == "group" and self.group_size(name) < 2:
                raise ConfigError(f"PipelineConfig.{name}.ppo.advantage=group needs groups of worlds to compare: "
                                  + ("modulator.group_size" if name == "modulator" else "collector.group_size")
                                  + f" ≥ 2, got {self.group_size(name)}")
        if self.collector.worlds % self.group_size("modulator"):
            raise ConfigError(f"PipelineConfig.modulator.group_size={self.group_size('modulator')} must divide "
                              f"collector.worlds={self.collector.worlds}")
        self.env = changes(TrackingConfig, self.env, "PipelineConfig.env", drop=ENV_CODE_ONLY)
        self.reward = changes(RewardConfig, self.reward, "PipelineConfig.reward")
        self.env_config()                    # a bad env or reward value fails here, before any stage runs
        if self.randomization and set(self.randomization) & set(RANDOMIZATION_CODE_ONLY):
            self.randomization_config()      # says where effects and patches are set
        self.randomization = changes(Randomization, self.randomization, "PipelineConfig.randomization",
                                     drop=RANDOMIZATION_CODE_ONLY)
        self.randomization_config()

    def group_size(self, stage: str) -> int:
        """The group size ``stage``'s worlds train with: the modulators' own where set, else the chain's."""
        own = self.modulator.group_size if stage == "modulator" else None
        return self.collector.group_size if own is None else own

    def row_channels(self, row: str) -> str:
        """The channels a modulator row trains (:meth:`ModulatorStage.row_channels`)."""
        return self.modulator.row_channels(row)

    @property
    def backend(self) -> str:
        """The physics backend of every env of the chain (``sim.backend``)."""
        return self.sim.backend

    def env_config(self) -> TrackingConfig:
        """The episodes of the whole chain: :class:`TrackingConfig` with this pipeline's ``env`` and
        ``reward`` changes."""
        try:
            reward = from_known_keys(RewardConfig, self.reward)
        except (ValueError, TypeError) as e:
            raise ConfigError(f"PipelineConfig.reward: {e}") from None
        try:
            return dataclasses.replace(TrackingConfig(), **self.env, reward=reward)
        except (ConfigError, ValueError, TypeError) as e:
            raise ConfigError(f"PipelineConfig.env: {e}") from None

    def randomization_config(self) -> Randomization:
        """Table 3 with this pipeline's ``randomization`` changes (checked as a training run checks them)."""
        return randomization_with(self.randomization, "PipelineConfig.randomization")

    @classmethod
    def from_dict(cls, d: dict) -> PipelineConfig:
        """The config from a mapping of its fields (a composed recipe config); unknown keys refused."""
        return from_known_keys(cls, d)

    @classmethod
    def node(cls) -> dict:
        """The recipe's node (:func:`adadex.train.config_store.pipeline_node`): every field with its default,
        the stage groups as their defaults' mappings, ``env``/``reward``/``randomization`` and
        ``modulator.modulation`` with every field of their classes (the modulators' own changes in it)."""
        from adadex.train.schema import change_nodes, defaults_of, modulation_node

        modulation = {**modulation_node(), **field_default(ModulatorStage, "modulation")}   # the stage's own defaults
        return defaults_of(cls, expand={**change_nodes(),
                                        "modulator": defaults_of(ModulatorStage, expand={"modulation": modulation})})


def specialist_blocks(dataset: ReferenceDataset, k: int, window: int) -> list[list[int]]:
    """The unseen-trajectory training references in ``k`` blocks of whole semantic groups (contiguous
    group ids, sizes as even as the groups allow): one block per specialist."""
    refs = episode_references(dataset, ("unseen_trajectory", "train"), window)
    groups = sorted({dataset.entries[i]["group"] for i in refs})
    if k > len(groups):
        raise ConfigError(f"{dataset.path}: {k} specialists but only {len(groups)} semantic groups to share out")
    blocks = [[int(g) for g in b] for b in np.array_split(np.asarray(groups), k)]
    return [[i for i in refs if dataset.entries[i]["group"] in set(b)] for b in blocks]


class Pipeline:
    """The stages of :func:`run_pipeline` (see the module docstring)."""

    def __init__(self, cfg: PipelineConfig, env_config: TrackingConfig | None = None):
        self.cfg, self.env_config = cfg, env_config or cfg.env_config()
        self.out = Path(cfg.out)
        # the episodes' settings as changes from the defaults: what the stages are keyed with, and what
        # every training stage's TrainConfig carries
        self.env_changes = changes(TrackingConfig, {f.name: getattr(self.env_config, f.name)
                                                    for f in dataclasses.fields(TrackingConfig)
                                                    if f.name not in ENV_CODE_ONLY},
                                   "env_config", drop=ENV_CODE_ONLY)
        self.reward_changes = changes(RewardConfig, dataclasses.asdict(self.env_config.reward), "env_config.reward")

    def _stage(self, folder: Path, settings: dict, fn, *, label: str) -> dict:
        """:func:`run_stage` with the episodes' ``env`` and ``reward`` changes among the settings when
        there are any (stages run with the defaults keep their settings as before, and a stage is never
        reused across other episodes)."""
        if self.env_changes:
            settings = {**settings, "env": self.env_changes}
        if self.reward_changes:
            settings = {**settings, "reward": self.reward_changes}
        if self.cfg.backend != SimConfig().backend:      # other physics: never the default backend's stage
            settings = {**settings, "sim_backend": self.cfg.backend}
        return run_stage(folder, settings, fn, label=label, log=self.log)

    def log(self, msg: str) -> None:
        print(msg, flush=True)

    # -- shared --------------------------------------------------------------------------------
    def dataset(self) -> ReferenceDataset:
        from adadex.data.build import dataset_at

        path = dataset_at(self.cfg.dataset or self.out / "data",
                          preset=None if self.cfg.dataset else self.cfg.dataset_preset, setting="dataset",
                          seed=self.cfg.dataset_seed, planned_grasp=self.cfg.dataset_planned_grasp,
                          progress=self.cfg.progress, log=lambda m: self.log(f"[run ] {m}"),
                          hint="leave dataset unset to build one")
        ds = ReferenceDataset(path)
        if not self.cfg.dataset:       # built here: by these settings, or refused like any other stage
            want = {"preset": self.cfg.dataset_preset, "seed": self.cfg.dataset_seed,
                    "planned_grasp": self.cfg.dataset_planned_grasp}
            have = {k: ds.info.get(k, False if k == "planned_grasp" else None) for k in want}
            if have != want:
                raise ConfigError(f"{path}: this dataset was built with other settings ({have}, asked for {want}); "
                                  f"use a new out")
        return ds

    def _train_config(self, out: Path, seed: int, ppo: PPOConfig, policy: PolicyConfig, group_size: int | None = None,
                      **kw) -> TrainConfig:
        """A training stage's run: its stage's ``ppo`` and ``policy``, the chain's collector (with the
        stage's own ``group_size`` where given), physics, episodes and randomization."""
        c = self.cfg
        collector = dataclasses.replace(c.collector, **({} if group_size is None else {"group_size": group_size}))
        return TrainConfig(dataset=str(self.ds.path), out=str(out), seed=seed, resume=True,
                           ppo=dataclasses.replace(ppo), collector=collector,
                           policy=dataclasses.replace(policy), env=dict(self.env_changes),
                           reward=dict(self.reward_changes), randomization=dict(c.randomization), wandb=c.wandb,
                           sim=dataclasses.replace(c.sim), progress=c.progress, **kw)

    def _ppo(self, tc: TrainConfig, label: str, teacher=None) -> dict:
        from adadex.train.ppo import PPOTrainer

        settings = {k: v for k, v in tc.to_dict().items() if k not in ("resume", "wandb", "progress", "out")}
        if not settings["env"]:
            del settings["env"]            # default episodes: the settings of stages run before env was one
        settings["ppo"] = {k: v for k, v in settings["ppo"].items() if k != "update_threads"}   # speed, not result
        if settings["policy"]["anchor_lookahead"] == 1:
            del settings["policy"]["anchor_lookahead"]   # its default: the settings of stages run before it existed
        if settings.get("modulator") and settings["modulator"].get("core") is None:
            for k in ("core", "core_size"):              # the same: no recurrent core, as every stage before it
                settings["modulator"].pop(k, None)
        if settings.get("modulator") and settings["modulator"].get("decide_every") == 1:
            del settings["modulator"]["decide_every"]    # the same: a decision every step, as every stage before it
        if settings.get("modulator") and settings["modulator"].get("prior_reach") == 0.0:
            del settings["modulator"]["prior_reach"]     # the same: a prior that reaches everywhere, or none
        if teacher is not None:
            settings["teacher"] = teacher[0]

        def fit():
            table = None
            if teacher is not None:
                from adadex.train.rollouts import load_rollouts, teacher_action_table

                table = teacher_action_table(load_rollouts(teacher[0]), len(self.ds), self.env_config.window)
            r = PPOTrainer(tc, env_config=self.env_config, run_name=label, teacher=table).train()
            return {"policy": str(r["policy"]), "frames": r["frames"], "eval": r["eval"]}

        return self._stage(Path(tc.out), settings, fit, label=label)

    # -- per seed ------------------------------------------------------------------------------
    def specialists(self, seed: int, root: Path) -> dict[str, list[int]]:
        teachers = {}
        s = self.cfg.specialist
        blocks = specialist_blocks(self.ds, s.count, self.env_config.window)
        for k, refs in enumerate(blocks):
            out = root / "specialists" / f"spec_{k}"
            tc = self._train_config(out, seed + 101 * k, s.ppo, s.policy, split=None, references=refs)
            r = self._ppo(tc, f"seed {seed} specialist {k + 1}/{len(blocks)} ({len(refs)} references)")
            teachers[r["policy"]] = refs
        return teachers

    def rollouts(self, seed: int, root: Path, teachers: dict) -> str:
        from adadex.train.rollouts import teacher_rollouts

        out = root / "rollouts"
        c = self.cfg
        # chunk k rolls out on env seed env_seed + k: 1,000 apart per pipeline seed, so that two seeds'
        # teacher rollouts never share Table 3 draws (10_000 + seed made seed 0's chunk 1 seed 1's chunk 0)
        env_seed = 10_000 + 1_000 * seed
        settings = {"teachers": teachers, "episodes": c.rollouts.episodes, "criterion": c.rollouts.criterion,
                    "seed": seed, "env_seed": env_seed, "worlds": c.collector.worlds,
                    **({"randomization": c.randomization} if c.randomization else {})}

        def fit():
            info = teacher_rollouts(teachers, self.ds, out / "data", episodes_per_reference=c.rollouts.episodes,
                                    seed=env_seed, max_worlds=c.collector.worlds, criterion=c.rollouts.criterion,
                                    randomize=c.randomization_config(),
                                    config=self.env_config, nthread=c.collector.env_threads, progress=c.progress,
                                    backend=c.backend)
            return {k: info[k] for k in ("episodes_tried", "episodes_kept", "success_pct", "frames")}

        self._stage(out, settings, fit, label=f"seed {seed} teacher rollouts")
        return str(out / "data")

    def distill(self, seed: int, out: Path, rollouts: str, fraction: float = 1.0) -> str:
        from adadex.train.distill import DistillConfig, distill

        c = self.cfg
        dc = DistillConfig(rollouts=rollouts, out=str(out), steps=c.distill.steps, batch_size=c.distill.batch_size,
                           seed=seed, resume=True, fraction=fraction, wandb=c.wandb, progress=c.progress,
                           checkpoint_every=max(1, c.distill.steps // 5), hidden=tuple(c.specialist.policy.hidden))
        settings = {k: v for k, v in dataclasses.asdict(dc).items()
                    if k not in ("resume", "wandb", "progress", "out", "threads")}
        label = f"seed {seed} distill" + (f" ({fraction:g} of the references)" if fraction < 1 else "")
        r = self._stage(out, settings, lambda: {"tracker": str(distill(dc, run_name=label)["tracker"])},
                        label=label)
        return r["tracker"]

    def modulators(self, seed: int, root: Path, tracker: str) -> dict[str, str]:
        out = {}
        stage = self.cfg.modulator
        for row in MODULATOR_ROWS:
            channels = stage.row_channels(row)
            m = ModulatorSettings(tracker=tracker, channels=channels, modulation=dict(stage.modulation),
                                  **stage.settings(row))
            # the run's policy settings are the specialists' (a modulator run trains no tracker)
            tc = self._train_config(root / "modulators" / row, seed, stage.ppo, self.cfg.specialist.policy,
                                    modulator=m, group_size=self.cfg.group_size("modulator"))
            out[row] = self._ppo(tc, f"seed {seed} modulator {channels}")["policy"]
        return out

    def baselines(self, seed: int, root: Path, rollouts: str) -> dict[str, str]:
        b = self.cfg.baseline
        ppo = self._train_config(root / "baselines" / "ppo", seed, b.ppo, b.policy)
        il = self._train_config(root / "baselines" / "il_rl", seed,
                                dataclasses.replace(b.ppo, imitation_coef=b.imitation_coef), b.policy)
        return {"ppo": self._ppo(ppo, f"seed {seed} vanilla PPO")["policy"],
                "il_rl": self._ppo(il, f"seed {seed} IL+RL", teacher=(rollouts,))["policy"]}

    # -- evaluation ----------------------------------------------------------------------------
    def policy(self, row: str, paths: dict):
        """(policy graph, its primer) for a table row."""
        from adadex.envs.replay import replay_policy
        from adadex.modules.channels import ModulationConfig
        from adadex.modules.modulator import Modulator
        from adadex.modules.tracker import Tracker
        from adadex.transforms.policy import make_policy

        if row == "replay":
            g = make_policy(replay_policy(), None, channels="none")
        elif row in MODULATOR_ROWS:
            g = make_policy(Tracker.load(paths["tracker"]), Modulator.load(paths[row]), channels=self.cfg.row_channels(row),
                            config=ModulationConfig(**self.cfg.modulator.modulation))
        else:
            g = make_policy(Tracker.load(paths[row]), None, channels="none")
        return g

    def evaluate(self, policy, split: str, condition: str, eval_seed: int, *, references=None,
                 keep_rollouts=False, repeats: int | None = None) -> dict:
        from adadex.eval.evaluate import evaluate

        refs = references or episode_references(self.ds, (split, "test"), self.env_config.window)
        if not refs:
            raise ConfigError(f"{self.ds.path}: the {split} split has no test reference with a "
                              f"{self.env_config.window}-frame window")
        randomized = condition == "randomized"
        c = self.cfg
        return evaluate(policy, self.ds, split=None, references=refs * ((repeats or c.evaluation.repeats) if randomized else 1),
                        max_worlds=c.collector.worlds, env_transform=policy.primer, config=self.env_config,
                        randomize=c.randomization_config() if randomized else None, seed=eval_seed, progress=False,
                        nthread=c.collector.env_threads, keep_rollouts=keep_rollouts, backend=c.backend)

    def evaluations(self, seed: int, root: Path, paths: dict, rows: tuple[str, ...] = EVAL_ROWS) -> dict:
        """Every row of ``rows`` (default all of Table 1's) on both splits, nominal and randomized; the same
        environment seed, references and repeats for every row of a seed (common random numbers: rows
        differ by their policy, not their draws, so their episodes pair up). Returns each row's stored
        result by (split, condition, row): ``summary`` and, for evaluations run since they were kept,
        ``per_episode`` and ``return_completion_spearman`` (a stage stored by an older run has neither)."""
        results = {}
        for split in EVAL_SPLITS:
            for condition in ("nominal", "randomized"):
                for row in rows:
                    folder = root / "eval" / split / condition / row
                    settings = {"policy": paths.get(row, "replay"), "tracker": paths["tracker"],
                                "repeats": self.cfg.evaluation.repeats, "seed": seed}

                    def run(row=row, split=split, condition=condition):
                        r = self.evaluate(self.policy(row, paths), split, condition, 20_000 + seed)
                        return {k: r[k] for k in ("summary", "per_reference", "per_episode",
                                                  "return_completion_spearman")}

                    results[(split, condition, row)] = self._stage(
                        folder, settings, run, label=f"seed {seed} evaluate {row} on {split}, {condition}")
        return results

    def log_tracker_vs_replay(self, seed: int, results: dict) -> None:
        """One line per split and condition: this seed's tracker against kinematic replay in completion
        points, paired per episode on the same draws (95 % bootstrap over references) — the first answer
        the run gives, before the modulators and baselines train."""
        from adadex.eval.paired import paired_bootstrap

        parts = []
        for split in EVAL_SPLITS:
            for condition in ("nominal", "randomized"):
                r = {row: results[(split, condition, row)].get("per_episode") for row in ("tracker", "replay")}
                if not all(r.values()):
                    continue
                a, b = (np.asarray(r[row]["completion"]) * 100 for row in ("tracker", "replay"))
                d = paired_bootstrap(a, b, np.asarray(r["tracker"]["reference"]), seed=seed)
                ci = "" if d["ci95"] is None else f" [{d['ci95'][0]:+.1f}, {d['ci95'][1]:+.1f}]"
                parts.append(f"{split} {condition} {d['estimate']:+.1f}{ci}")
        if parts:
            self.log(f"seed {seed}: tracker − replay, completion points: " + "; ".join(parts))

    def teacher_check(self, seed: int, root: Path, teachers: dict, tracker: str) -> list[dict]:
        """The distilled generalist against each teacher on the teacher's own training references
        (randomized, the same draws for both, so their episodes pair up): one stage per specialist,
        ``{"teacher", "references", "teacher_completion_pct", "generalist_completion_pct",
        "generalist_minus_teacher", "generalist_minus_teacher_ci95"}`` each — how much distillation
        kept of what each specialist learned — with :meth:`teacher_floor`'s fields (the teacher against
        replay on the same draws)."""
        from adadex.eval.paired import paired_bootstrap

        out = []
        for k, (path, refs) in enumerate(teachers.items()):
            folder = root / "eval" / "teachers" / f"spec_{k}"

            def run(path=path, refs=refs):
                r = {row: self.evaluate(self.policy(row, {row: p}), "unseen_trajectory", "randomized", 30_000 + seed,
                                        references=list(refs), repeats=self.cfg.evaluation.check_repeats)
                     for row, p in (("teacher", path), ("tracker", tracker))}
                a, b = (np.asarray(r[row]["per_episode"]["completion"]) * 100 for row in ("tracker", "teacher"))
                d = paired_bootstrap(a, b, np.asarray(r["teacher"]["per_episode"]["reference"]), seed=seed)
                return {"teacher": path, "references": len(refs),
                        "teacher_completion_pct": r["teacher"]["summary"]["completion_pct"],
                        "generalist_completion_pct": r["tracker"]["summary"]["completion_pct"],
                        "generalist_minus_teacher": d["estimate"], "generalist_minus_teacher_ci95": d["ci95"]}

            check = self._stage(folder, {"teacher": path, "tracker": tracker, "repeats": self.cfg.evaluation.check_repeats,
                                         "seed": seed}, run,
                                label=f"seed {seed} generalist against teacher {k + 1} on its references")
            out.append({**check, **self.teacher_floor(seed, root, k, path, refs)})
        return out

    def teacher_floor(self, seed: int, root: Path, k: int, path: str, refs: list[int]) -> dict:
        """Specialist ``k`` against kinematic replay on its own training references, on the teacher
        check's draws (paired): ``{"replay_completion_pct", "teacher_minus_replay",
        "teacher_minus_replay_ci95"}`` and the same for object completion (``replay_object_completion_pct``,
        ``teacher_minus_replay_object``, ``…_ci95``), and the episodes' values (``per_episode``, in points)
        for pooling over specialists (:func:`teachers_note`) — what PPO gained over the floor where it trained,
        which is what distillation has to carry to unseen references. Its own stage
        (``eval/teachers_vs_replay/spec_<k>``), so runs stored before it existed resume."""
        from adadex.eval.paired import paired_bootstrap

        def run():
            r = {row: self.evaluate(self.policy(row, {row: p}), "unseen_trajectory", "randomized", 30_000 + seed,
                                    references=list(refs), repeats=self.cfg.evaluation.check_repeats)
                 for row, p in (("teacher", path), ("replay", None))}
            ids = np.asarray(r["teacher"]["per_episode"]["reference"])
            out = {"per_episode": {"reference": ids.tolist()}}
            for metric, suffix in (("completion", ""), ("object_completion", "_object")):
                a, b = (np.asarray(r[row]["per_episode"][metric]) * 100 for row in ("teacher", "replay"))
                d = paired_bootstrap(a, b, ids, seed=seed)
                out |= {f"replay_{metric}_pct": r["replay"]["summary"][f"{metric}_pct"],
                        f"teacher_minus_replay{suffix}": d["estimate"], f"teacher_minus_replay{suffix}_ci95": d["ci95"]}
                out["per_episode"] |= {f"teacher_{metric}": a.tolist(), f"replay_{metric}": b.tolist()}
            return out

        return self._stage(root / "eval" / "teachers_vs_replay" / f"spec_{k}",
                           {"teacher": path, "repeats": self.cfg.evaluation.check_repeats, "seed": seed}, run,
                           label=f"seed {seed} teacher {k + 1} against replay on its references")

    def scaling(self, seed: int, root: Path, rollouts: str, tracker: str) -> dict:
        """Fig. 6: generalists distilled from fractions of the references, on the unseen-trajectory
        test split under randomization (fraction 1 is the generalist itself)."""
        out = {}
        for f in self.cfg.evaluation.scaling_fractions:
            path = tracker if f == 1.0 else self.distill(seed, root / "scaling" / f"frac_{f:g}", rollouts, f)
            folder = root / "scaling" / f"frac_{f:g}" / "eval"
            settings = {"tracker": path, "repeats": self.cfg.evaluation.check_repeats, "seed": seed}
            out[f] = self._stage(folder, settings, lambda p=path: {"summary": self.evaluate(
                self.policy("tracker", {"tracker": p}), "unseen_trajectory", "randomized", 20_000 + seed,
                repeats=self.cfg.evaluation.check_repeats)["summary"]},
                label=f"seed {seed} evaluate the {f:g}-fraction generalist")["summary"]
        return out

    # -- all of it ------------------------------------------------------------------------------
    def chain(self, seed: int) -> tuple[dict, dict, dict, list]:
        """One training seed, start to end: (policy paths by row, evaluation results by (split,
        condition, row) as :meth:`evaluations` returns them, Fig. 6 summaries by fraction, the
        generalist against its teachers as :meth:`teacher_check` returns it)."""
        root = self.out / f"seed_{seed}"
        teachers = self.specialists(seed, root)
        rollouts = self.rollouts(seed, root, teachers)
        tracker = self.distill(seed, root / "generalist", rollouts)
        # replay and the tracker first: their comparison is in (table_so_far) hours before the other rows
        self.log_tracker_vs_replay(seed, self.evaluations(seed, root, {"tracker": tracker}, rows=("replay", "tracker")))
        paths = {"tracker": tracker, **self.modulators(seed, root, tracker), **self.baselines(seed, root, rollouts)}
        return (paths, self.evaluations(seed, root, paths), self.scaling(seed, root, rollouts, tracker),
                self.teacher_check(seed, root, teachers, tracker))

    def run(self) -> dict:
        from adadex.eval.table1 import aggregate, table_markdown

        t0 = time.perf_counter()
        mark_output_dir(check_pipeline_out(self.out), PIPELINE_RUN)    # someone else's folder: refused
        self.ds = self.dataset()
        seeds = self.cfg.seeds
        workers = min(self.cfg.seed_workers, len(seeds))
        chains = (run_in_processes(_seed_chain, [(self.cfg, self.env_config, s) for s in seeds], workers)
                  if workers > 1 else [self.chain(s) for s in seeds])
        scaling: dict = {}
        paths_by_seed = {}
        distilled = {}             # per seed: the generalist against each of its teachers
        for seed, (paths, _, fractions, checks) in zip(seeds, chains):
            paths_by_seed[seed] = paths
            distilled[str(seed)] = checks
            for f, s in fractions.items():
                scaling.setdefault(f, []).append(s)
        table = aggregate(*collect([evaluations for _, evaluations, _, _ in chains]))
        atomic_write_text(self.out / "table1.json", json.dumps(table, indent=1))
        atomic_write_text(self.out / "table1.md",
                          table_markdown(table) + "\n" + self.cfg.modulator.rows_note() + "\n")
        floors = {seed: [c.pop("per_episode", None) for c in checks] for seed, checks in distilled.items()}
        atomic_write_text(self.out / "generalist_vs_teachers.json", json.dumps(distilled, indent=1))
        for seed, checks in distilled.items():
            self.log(f"seed {seed}: on each teacher's references (completion points), teacher − replay: "
                     + ", ".join(f"{c['teacher_minus_replay']:+.1f}" for c in checks)
                     + "; generalist − teacher: " + ", ".join(f"{c['generalist_minus_teacher']:+.1f}" for c in checks))
        figures = self.figures(table, scaling, paths_by_seed[self.cfg.seeds[0]], self.cfg.seeds[0])
        note = self.o_channel(table)
        teachers = teachers_note(floors)
        atomic_write_text(self.out / "table1.md", table_markdown(table) + "\n" + self.cfg.modulator.rows_note()
                          + "\n\n" + note["text"] + "\n\n" + teachers + "\n")
        self.log(note["text"])
        self.log(teachers)
        wall = time.perf_counter() - t0
        self.log(f"table1: {self.out / 'table1.md'} ({wall:.0f} s)")
        return {"table": table, "figures": figures, "wall_s": wall}

    def o_channel(self, table: dict) -> dict:
        """Whether channel O acts (:func:`adadex.eval.table1.o_channel_note`, with the first seed's
        generalist's latent smoothness from ``figures/smoothness.json``); written below the table."""
        from adadex.eval.table1 import o_channel_note
        from adadex.modules.channels import ModulationConfig

        rho = json.loads((self.out / "figures" / "smoothness.json").read_text(encoding="utf-8"))["tracker"]["mean"]
        m = ModulationConfig(**self.cfg.modulator.modulation)
        return o_channel_note(table, rho, lambda_latent=m.lambda_latent, action_bound=m.action_bound)

    def figures(self, table: dict, scaling: dict, paths: dict, seed: int) -> dict[str, str]:
        """``out/figures/`` (:func:`adadex.train.pipeline_figures.pipeline_figures`)."""
        from adadex.train.pipeline_figures import pipeline_figures

        return pipeline_figures(self, table, scaling, paths, seed, MODULATOR_ROWS)


def teachers_note(floors: Mapping[str, list]) -> str:
    """The specialists against kinematic replay on their own references, pooled over every specialist
    of every seed (paired episodes, bootstrap over references within seeds), as the line written below
    Table 1: what PPO gained where it trained is what distillation has to carry to the tracker row.

    Args:
        floors: per seed, each specialist's :meth:`Pipeline.teacher_floor` ``per_episode`` record
            (None for a stage stored before it kept them: then the line says so).
    """
    from adadex.eval.paired import paired_bootstrap

    kept = [(seed, f) for seed, fs in floors.items() for f in fs if f]
    if not kept or len(kept) < sum(len(fs) for fs in floors.values()):
        return ("**The specialists against replay** on their own references: not pooled here (stages stored "
                "before their episodes were kept); per specialist in `generalist_vs_teachers.json`.")
    ids = np.concatenate([[f"{seed}:{r}" for r in f["reference"]] for seed, f in kept])
    seeds = np.concatenate([[seed] * len(f["reference"]) for seed, f in kept])
    parts = []
    for metric, name in (("completion", "completion"), ("object_completion", "object completion")):
        d = paired_bootstrap(np.concatenate([f[f"teacher_{metric}"] for _, f in kept]),
                             np.concatenate([f[f"replay_{metric}"] for _, f in kept]), ids, seeds)
        parts.append(f"{name} {d['estimate']:+.1f} [{d['ci95'][0]:+.1f}, {d['ci95'][1]:+.1f}]")
    return (f"**The specialists against replay** on their own training references, paired ({len(kept)} specialist{'s' * (len(kept) != 1)}, "
            f"{len(ids):,} episodes, Table 3): " + "; ".join(parts) + " points. What PPO gained where it trained "
            "is what distillation has to carry to unseen references (per specialist, and the generalist "
            "against each, in `generalist_vs_teachers.json`).")


def _seed_chain(args) -> tuple[dict, dict, dict, list]:
    """:meth:`Pipeline.chain` in a worker process (``seed_workers`` > 1); the dataset exists by then."""
    cfg, env_config, seed = args
    p = Pipeline(cfg, env_config)
    p.ds = p.dataset()
    return p.chain(seed)


def check_pipeline_out(out, *, force: bool = False, ignore=()) -> Path:
    """The pipeline's output guard, before any work: ``out`` is absent, empty, or an earlier pipeline's
    (whose stages then resume or are skipped); anything else is refused unless ``force``. Writes nothing."""
    return check_output_dir(out, PIPELINE_RUN, force=force, recognize=earlier_pipeline, option="force=true",
                            ignore=ignore)


def run_pipeline(cfg: PipelineConfig, **kwargs) -> dict:
    """Run every stage (skipping finished ones) and write the table and figures; see the module docstring.

    Args:
        cfg: the pipeline's settings.
        **kwargs: :class:`Pipeline`'s keyword arguments (``env_config``: the episode settings,
            default ``cfg.env_config()``).

    Returns:
        :meth:`Pipeline.run`'s result dict.
    """
    return Pipeline(cfg, **kwargs).run()

