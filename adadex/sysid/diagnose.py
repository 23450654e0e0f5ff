"""Which physical effect is missing? Fit candidates where the model fails, rank them on held-out data.

For every failing joint (see :func:`~adadex.sysid.compare.localize`) the joint's sequences are
split into training and held-out sets (every third sequence is held out). Every candidate effect is
screened on a coarse parameter grid on the training set; the ``refine_top`` most promising are
fitted precisely (:mod:`adadex.sysid.fit`). Each is scored on the held-out set by the
fraction of the *excess* error it removes — the part of the mean squared error above the sensor
noise floor, which no model can remove — averaged over the held-out sequences that have excess
error, so that every regime counts alike:

    reduction = mean over sequences of 1 − (MSE_after − σ²) / (MSE_before − σ²)

Friction is scored on the cost it is fitted on. A free replay of a Coulomb friction is chaotic
(:mod:`adadex.sysid.fit`): the stick–slip timing of a fast, torque-limited sequence diverges even at the
true value, so the free replay's error of a held-out sequence need not fall with the true effect (0.5 N·m
added to arm_j3 by an MjSpec edit, 2 s pre-roll, noise: fitted at 0.4995 N·m, scored 0 %, verdict
unexplained, nothing stored). An effect of :data:`~adadex.sysid.fit.WINDOWED_EFFECTS` is therefore scored
on the windowed cost its fit locates it on — 0.25-s windows restarted from the measured positions, the
worst 10 % of a joint's windows trimmed, each sequence's mean over its kept windows
(:meth:`~adadex.sysid.fit.JointFitter.window_mse_per_sequence`) — against the same windowed cost of the
model without it, in the reduction above; so is every set that holds one: a further effect chosen on the
same joint on top of it, a joint's selected effects scored together, the margin of an effect on such a
joint in the selection rule (below), and the shared effect-and-load pair of such an effect. Every other
effect and set is scored on the free replay, as before. Each hypothesis, selected effect and per-joint
finding says which cost it was scored on (``scored_by``: ``"windowed"`` or ``"replay"``); candidates
scored on either are ranked together. The noise floor σ² is the same: a window restarts from noisy
measured positions, so at the true model its error holds the sensor noise plus what the window keeps of
the restart's noise; measured on friction simulated with the library (noise 2e-4 rad, the default
16-sequence excitation of one joint; 0.5 N·m on arm_j3, 0.2 on arm_j5, 0.05 on rf_pip and on if_dip), the
windowed cost at the truth is 1.02–1.24 × the noise variance (median over sequences; at most 1.71 ×, on
arm_j3) where the free replay's is 1.01 ×, both well under σ² as :func:`~adadex.sysid.compare.noise_floor`
estimates it from those recordings (5.6–22 × the noise variance on a joint that moves); where σ² is the
noise variance itself (a joint mostly holding its pose), a sequence scored at the least excess that counts
(2 σ²) keeps at most 36 % of it at the truth, and one with a large excess next to none.

Candidates are ranked by held-out reduction minus a complexity penalty per parameter. Forward
selection then adds further effects on the same joint while each adds at least
``min_gain`` of held-out reduction. Candidates whose held-out reduction is within ``tie`` of the
best are reported as alternatives of one hypothesis (on a position servo, viscous ``damping`` and
``kd_scale`` are such a pair). The same effect selected on several joints becomes one hypothesis
over those joints.

A joint that no sequence excites (it holds its pose while others move) is judged on every sequence, as
:func:`~adadex.sysid.compare.localize` judges it. A joint none of whose held-out sequences shows its
error above the noise (a knock-on seen in a few sequences) is scored on all of its sequences.

A load first: with several failing joints, one payload on one link (any link at or below a failing
joint, recorded or not) is screened before any joint is fitted — one Gauss–Newton step per link on every
recorded joint's error in units of its noise, the :data:`LOAD_SHORTLIST` best searched when a step
removes :data:`LOAD_SCREEN_AT` of it (:func:`_load_first`) — and kept when it explains most of the
failing joints' held-out error (:data:`LOAD_FIRST_AT`); the joints it explains are its knock-ons, and
only the others are then fitted joint by joint (a 0.6 kg mass on the palm is one ``payload_mass`` on the
palm's link, not a payload on the shoulder, armature on the elbow and 13 finger hypotheses).
A source first, when no load is: with :data:`SOURCE_MIN_FAILING` failing joints or more, one library effect
on one joint, or with one value on two joints of adjacent links, is screened on every recorded joint's
error at once before any joint is fitted (:func:`_source_first`: a few grid points per candidate, one
replay each of the sequence where each failing joint errs most, on the worst joints and on those whose
imposed motion moves the rest), fitted when it halves the failing joints' error on average, a further
source added while it lowers that clearly, and kept when together they explain :data:`SOURCE_FIRST_AT` of
the failing joints' held-out error; the joints they explain are their knock-ons, as a load's (a shoulder
too weak to hold the arm, torque limit 0.3 on arm_j2 and arm_j3, fails 20 of 22 joints: one torque limit on
the two, not an effect on each; ``benchmarks/sysid_diagnosis.py --worst``). Near a limit the arm barely
holds, the free replay is chaotic in the value (1e-4 off the truth, a thousand times the noise): when it
leaves a failing joint unexplained, the sources are refitted and scored on the windowed cost, with the
joints they carry (:attr:`Candidate.chaotic`), and that is kept when it explains more.
With one failing joint the search runs once that joint's own fit has chosen a payload or armature, its
look-alike (:func:`_load_on_one_joint`): the joint-by-joint fit hangs the mass at its own link's centre of
mass, while the load may hang off it or on a link below (a mass 5 cm beyond the upper arm's centre of mass
came out 64 % heavy there; one at a finger's centre of mass, felt only on the shoulder, as armature plus a
payload on the shoulder); the search's load, in mass and place, replaces that selection when it explains
the joint's held-out error as well as a payload chosen on the same link, or clearly better than armature
or a payload on the joint's own link.

A joint with too few sequences to hold any out (fewer than three of its own) is scored on its
training sequences only: the diagnosis lists it in ``train_only_joints``, says so in its findings,
marks its hypotheses ``"scored_on": "train"`` and gives them no held-out figure
(``heldout_error_reduction`` is ``None``).

Coupled joints: the failing joints are fitted worst first (error over noise), and after each joint's
effects are chosen the rest are localized again on the model with those effects; a joint that no
longer fails had only a knock-on error (the joint that moves it was the source) and gets no effect of
its own (re-localization replays only the still-pending joints' sequences). Before a joint is fitted, and
when other failing joints are left, one replay tells whether its failure is a knock-on of theirs whatever
moves them (:func:`_follows`): its own sequences are replayed with those joints moving exactly as measured
(:meth:`~adadex.sysid.replay.Replayer.simulate_imposed`: each a flywheel driven along its measurement, so it
feels their measured motion through the model's coupled dynamics); if it no longer fails, it gets no
effect of its own and is reported as a knock-on of the joints it follows (those that suffice alone), and
of their error when that is unexplained. A drag outside the library on the elbow shakes the holding
shoulder by 2.3 mrad against a 2 mrad failure floor; with no library effect on the elbow re-localization
never cleared it, and a ``kd_scale`` × 2.13 was selected on it (tests/sysid/test_user_model_diagnosis.py);
with the elbow imposed the shoulder's error is 0.8 × its noise floor. The joints a knock-on follows are
not imposed in the checks of those after it (no two joints follow each other), and the effects later
chosen on the joints it follows are fitted to its error too (below) and re-localize it. While failing joints are
still pending, a joint's best candidate is refitted against the errors of those it visibly moves too
(one replay decides which: the candidate changes their path by at least 10 % of their residual; on
their training sequences, each joint in units of its noise floor; Brent to 1e-7 of the bounds and a
compass polish):
a source is fitted to every error it causes, not only its own joint's, which pins a sensitive value —
a shoulder torque limit the arm barely holds at, whose 5th-6th digit decides whether the joints it
shakes match — that its own sequences leave ambiguous. The effects of a source keep that coupled fit
when the selected values are refined jointly. Load-like effects (a payload, or armature, its look-alike)
chosen on several joints of one chain are tried as one payload on one link of the unbranched chain
below them, fitted to all their sequences; it replaces them when it
explains their held-out sequences as well (a mass on the hand is one hypothesis, not a payload on the
shoulder plus armature on the elbow). Softer servos carrying a load (:func:`_shared_effect_and_load`):
when the failing joints of one chain are not yet explained and one effect was chosen on several of
them, that effect on all of them with a load on top replaces the selection if it explains the held-out
error better (kp × 0.3 on six arm joints and 2 kg at the palm, joint by joint kp here, damping, friction
and kd there, are one softness and one payload). The load is a payload screened on one link, or links
heavier than the model's — one ``mass_scale`` shared by every failing joint's links (motors, cables),
which no payload on one link mimics — whichever explains more. The step also runs, and its pair is kept
when it explains as much on each joint's own sequences and more on every held-out sequence, when the
joint-by-joint selection explains each joint's own sequences but not the others' (a softness and a torque
limit on a shoulder that sags only while the elbow carries a load). A candidate fitted at (or within 0.1 % of the bounds of) its
absent value explains nothing
and is dropped; explained fractions are reported clipped at 0. A selected value whose 95 % interval
spans half of its bounds is reported as not identifiable from the recording, with the
``adadex sysid excite`` command whose excitation would pin it down (:data:`EXCITATION_FOR`); one that
reaches a bound is not selected at all (below).

No spurious effect: after the joint refit every selected effect must explain at least
:data:`MIN_EXPLAINED` of its joints' held-out excess error beyond what all the other selected effects
explain (its joint, and the knock-on joints its source explained; weakest dropped first,
:func:`_prune`); an effect at its absent value is dropped; a value on a bound of the library
(:func:`on_bound`: damping at its largest value) is not selected but reported in ``suggestions``, with
the ``adadex sysid excite`` command that would identify it. A hypothesis explaining under
:data:`MIN_EXPLAINED` is not stored.

Verdicts: ``nothing_missing`` (no joint's error is above its noise floor), ``explained`` (every
failing joint's held-out excess error falls by at least ``explained_at``), ``unexplained`` (the
best candidates explain too little; the report says how much). A knock-on of other failing joints
(:func:`_follows`) is judged with them: on what their effects explain of its own error when they are
explained, not at all (its finding says whose unexplained error it is) when they are not.
"""

from __future__ import annotations

import dataclasses
import json
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy.optimize import minimize_scalar

from adadex.errors import AdadexError
from adadex.io import atomic_write_text
from adadex.progress import progress_bar
from adadex.sim.effects import EFFECT_NAMES, get_effect, robot_ids
from adadex.sim.patch import EffectInstance, ModelPatch
from adadex.sysid.compare import FAIL_ABS, FAIL_RATIO, compare, heldout_mask, localize, noise_floor
from adadex.sysid.fit import (WINDOW_S, WINDOWED_EFFECTS, CoupledFitter, JointFitter, _compass, grid_points,
                              window_length, window_mse_per_sequence, window_rows)
from adadex.sysid.replay import Replayer

COMPLEXITY_PENALTY = 0.02
#: Brent's tolerance (fraction of the bounds) when a candidate is fitted to the joints it may move too:
#: a knock-on error can hang on the 6th digit of a torque limit (tests/sysid/test_coupled.py).
COUPLED_XTOL = 1e-7
#: a pending joint enters a source's coupled fit when the source's effect moves it by this fraction
#: of its residual
COUPLING_MIN = 0.1
#: A selected effect must explain at least this fraction of its joints' held-out excess error beyond what
#: the other selected effects explain (see :func:`_prune`); a hypothesis explaining less is not stored.
MIN_EXPLAINED = 0.05


class DiagnosisError(AdadexError, ValueError):
    """A diagnosis file that cannot be read."""


@dataclass(kw_only=True)
class Candidate:
    """One effect fitted on one joint while screening: its value and 95 % interval, how much it
    reduces the error on the training and held-out sequences, its score and look-alike effects."""

    effect: str
    joint: str
    value: float
    ci95: tuple[float, float]
    train_error_reduction: float
    heldout_error_reduction: float
    score: float
    alternatives: list[str] = field(default_factory=list)
    #: the values and 95 % intervals of the effect's further parameters (a payload's offset), when fitted
    extra: tuple[float, ...] = ()
    extra_ci95: tuple[tuple[float, float], ...] = ()
    #: the cost its error reductions were measured on: ``"replay"`` (free replay) or ``"windowed"``
    #: (multiple shooting, for an effect of :data:`~adadex.sysid.fit.WINDOWED_EFFECTS` or a set holding one)
    scored_by: str = "replay"
    #: found first as a source whose free replay is chaotic around its value (a shoulder that barely holds
    #: the arm: 1e-4 of the effort off the truth, the free replay's error is a thousand times the noise);
    #: located and scored on the windowed cost, like an effect of :data:`~adadex.sysid.fit.WINDOWED_EFFECTS`
    chaotic: bool = False

    @property
    def values(self) -> list[float]:
        """The value of every parameter fitted (the first, then ``extra``)."""
        return [self.value, *self.extra]


@dataclass(kw_only=True)
class Diagnosis:
    """What :func:`diagnose` found: the verdict, the baseline error, the hypotheses tried, the effects
    selected (:meth:`patch` turns them into a :class:`~adadex.sim.patch.ModelPatch`), the fraction of
    the error they explain and the findings in words; :meth:`to_dict` is what ``diagnosis.json`` holds.

    :meth:`save` writes ``diagnosis.json`` into a folder and :meth:`load` reads it back
    (:class:`DiagnosisError` for a missing or unreadable file).

    Attributes:
        verdict: ``"nothing_missing"``, ``"explained"`` or ``"unexplained"`` (see the module docstring).
        baseline_error: the nominal model's error, rad: ``overall_rms_rad``, and ``per_joint_rms_rad``
            and ``noise_floor_rad`` by joint name.
        hypotheses: every first-round candidate that explains at least :data:`MIN_EXPLAINED` of its
            joint's excess error, best score first, each a dict with ``effect``, ``joints`` (one),
            ``params`` and ``ci95`` (by parameter name: a value, and a ``[lo, hi]`` 95 % interval, per
            joint), ``train_error_reduction`` and ``heldout_error_reduction`` (fractions of the excess
            error; the held-out one ``None`` when scored on training sequences), ``score``,
            ``alternatives`` (look-alike effects), ``scored_on`` (``"heldout"`` or ``"train"``) and
            ``scored_by``: the cost the reductions were measured on, ``"windowed"`` (an effect of
            :data:`~adadex.sysid.fit.WINDOWED_EFFECTS`, Coulomb friction, or one chosen on top of it:
            0.25-s windows restarted from the measured positions, see the module docstring) or
            ``"replay"`` (a free replay; every other effect). Absent in a file written before it.
        selected: the effects chosen, one dict per effect over all the joints it was chosen on:
            ``effect``, ``joints``, ``params`` and ``ci95`` (by parameter name, one entry per joint),
            ``heldout_error_reduction``, ``identifiable``, ``scored_on`` and ``scored_by`` (one per joint;
            ``scored_by`` as a hypothesis', for the joint's selected effects scored together),
            ``alternatives`` and ``unit`` (the first parameter's).
        explained_fraction: by failing joint, the fraction of its held-out excess error the selected
            effects remove, in [0, 1] (empty when nothing is missing); on the windowed cost for a joint whose
            selected effects hold a windowed one (its ``selected`` entry's ``scored_by`` and its finding
            say so), on the free replay otherwise.
        findings: the findings in sentences: the localization's, then what the diagnosis found (a load,
            knock-on joints, suggestions), ending with one per failing joint (and, when unexplained,
            one naming the joints left unexplained).
        wall_time_s: the diagnosis' wall time, s.
        train_only_joints: the failing joints with too few sequences to hold any out, scored on their
            training sequences only (default ``[]``).
        model: the id of the model the diagnosis replayed on (default ``"builtin"``).
        stage_times_s: wall time per stage, s (``localize``, ``load``, ``source``, ``knock_on_check``, ``fit``,
            ``relocalize``, ``joint_refit_and_scoring``; default ``{}``).
        suggestions: effects the data point to but cannot pin down (their value sits on a bound), each
            a dict like a selected effect's with the ``excite`` command that would identify it and its
            ``finding``; never selected (default ``[]``).
        stage_cpu_s: the same stages' process CPU time, s (every thread of the process, the replay
            pool's included; default ``{}``).

    >>> d = Diagnosis(verdict="explained", baseline_error={}, hypotheses=[], explained_fraction={"arm_j3": 0.9},
    ...               findings=[], wall_time_s=0.0, selected=[{"effect": "damping", "joints": ["arm_j3"],
    ...               "params": {"damping": [2.0]}, "ci95": {"damping": [[1.8, 2.2]]}}])
    >>> d.patch().describe()
    'damping(damping) arm_j3: 2'
    """

    verdict: str
    baseline_error: dict
    hypotheses: list[dict]
    selected: list[dict]
    explained_fraction: dict
    findings: list[str]
    wall_time_s: float
    train_only_joints: list[str] = field(default_factory=list)   # scored on training sequences only
    model: str = "builtin"      # the model id the diagnosis replayed on
    stage_times_s: dict = field(default_factory=dict)   # wall time per stage (localize, fit, relocalize, …)
    #: effects the data point to but cannot pin down (their value sits on a bound), each with the
    #: ``adadex sysid excite`` command that would identify it; never selected
    suggestions: list[dict] = field(default_factory=list)
    #: process CPU time per stage, s (the stages of ``stage_times_s``; every thread of the process, the
    #: replay pool's included; default ``{}``)
    stage_cpu_s: dict = field(default_factory=dict)

    def patch(self, robot=None) -> ModelPatch:
        """The selected effects as a model patch (of ``robot``'s model; default the built-in)."""
        p = ModelPatch(robot=robot)
        for h in self.selected:
            names = [n for n in get_effect(h["effect"]).param_names if n in h["params"]]   # leading ones
            values = np.stack([np.asarray(h["params"][n], dtype=float) for n in names], axis=1)
            cis = [h.get("ci95", {}).get(n) for n in names]
            ci = np.stack([np.asarray(c, dtype=float) for c in cis], axis=1) if all(cis) else None
            effect = EffectInstance(effect=h["effect"], joints=tuple(h["joints"]), values=values, ci95=ci, robot=robot)
            p = p + ModelPatch(effects=(effect,), robot=robot)
        return p

    def to_dict(self) -> dict:
        return {"verdict": self.verdict, "baseline_error": self.baseline_error, "hypotheses": self.hypotheses,
                "selected": self.selected, "explained_fraction": self.explained_fraction,
                "findings": self.findings, "wall_time_s": self.wall_time_s,
                "train_only_joints": self.train_only_joints, "model": self.model,
                "stage_times_s": self.stage_times_s, "suggestions": self.suggestions, "stage_cpu_s": self.stage_cpu_s}

    def save(self, directory) -> Path:
        return atomic_write_text(Path(directory) / "diagnosis.json", json.dumps(self.to_dict(), indent=2))

    @classmethod
    def load(cls, directory_or_file) -> "Diagnosis":
        p = Path(directory_or_file)
        p = p / "diagnosis.json" if p.is_dir() else p
        try:
            fields = json.loads(p.read_text(encoding="utf-8"))
            if (isinstance(fields, dict) and fields.get("verdict") == "nothing_missing"
                    and isinstance(fields.get("train_only_joints"), str) and isinstance(fields.get("model"), dict)):
                # an earlier adadex built a nothing-missing Diagnosis positionally: the model id landed in
                # train_only_joints and the stage times in model (read such a file as it was meant)
                fields = {**fields, "train_only_joints": [], "model": fields["train_only_joints"],
                          "stage_times_s": fields["model"]}
            d = cls(**fields)
        except FileNotFoundError:
            raise DiagnosisError(f"{p}: no such diagnosis (write one with `adadex sysid diagnose … --out DIR`)") from None
        except (OSError, ValueError, TypeError) as e:   # bad UTF-8 or JSON, missing or unknown fields
            raise DiagnosisError(f"{p}: not a readable diagnosis ({type(e).__name__}: {e})") from None
        if not (isinstance(d.verdict, str) and isinstance(d.selected, list) and isinstance(d.hypotheses, list)
                and isinstance(d.model, str) and isinstance(d.train_only_joints, list)
                and isinstance(d.suggestions, list)):
            raise DiagnosisError(f"{p}: not a readable diagnosis (verdict, selected, hypotheses, model, "
                                 "train_only_joints or suggestions of the wrong type)")
        return d


def _split(seqs: np.ndarray, mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    held, train = seqs[mask[seqs]], seqs[~mask[seqs]]
    if held.size == 0:  # too few sequences: score on the training set (marked as such, see the docstring)
        held = seqs
    return train, held


def _reduction(before, after, noise2: float) -> float:
    """Fraction of the excess error removed, averaged over sequences that have excess error.

    Per-sequence averaging weighs every regime alike: an effect that only matches the fast, large
    sequences (where errors are largest) does not pass for one that explains the slow ones too.
    """
    before, after = np.atleast_1d(before), np.atleast_1d(after)
    excess = before - noise2
    keep = excess > 2.0 * noise2
    if not keep.any():
        return 0.0
    red = 1.0 - np.maximum(after[keep] - noise2, 0.0) / excess[keep]
    return float(np.mean(np.clip(red, -1.0, 1.0)))


def _windowed(effects) -> bool:
    """Whether a set of effects (names or candidates) is scored on the windowed cost: it holds an effect of
    :data:`~adadex.sysid.fit.WINDOWED_EFFECTS` (see the module docstring)."""
    return any((e if isinstance(e, str) else e.effect) in WINDOWED_EFFECTS or getattr(e, "chaotic", False)
               for e in effects)


def _scored_by(windowed: bool) -> str:
    return "windowed" if windowed else "replay"


def _patch_of(selected_per_joint: dict, base: ModelPatch) -> ModelPatch:
    p = base
    for joint, chosen in selected_per_joint.items():
        for c in chosen:
            p = p.with_effect(c.effect, [joint], [c.values])
    return p


@dataclass(frozen=True, kw_only=True)
class _Setting:
    """What every step of a diagnosis reads: the replayer, the starting patch, the noise floors and
    which sequences train and which score each joint."""

    replayer: Replayer
    base_patch: ModelPatch
    joint_names: list[str]
    noise: np.ndarray
    seq_meta: list[dict]
    holdout: np.ndarray
    #: (S, J) each sequence's MSE on the starting patch (None: every held-out sequence scores)
    base_mse: np.ndarray | None = None

    def sequences(self, joint: str) -> tuple[np.ndarray, np.ndarray]:
        """(training, held-out) indices of the sequences that excite ``joint``: all, if unlabelled or if
        none excites it (a joint that only holds its pose is judged on every sequence, as
        :func:`~adadex.sysid.compare.localize` judges it)."""
        own = np.array([i for i, s in enumerate(self.seq_meta) if s.get("joint", joint) == joint], dtype=np.int64)
        if own.size == 0:
            own = np.arange(len(self.seq_meta), dtype=np.int64)
        return _split(own, self.holdout)

    def scored(self, joint: str) -> np.ndarray:
        """The sequences ``joint`` is scored on: its held-out ones, or all of its own when none of the
        held-out ones shows its error above the noise (a knock-on seen in a few sequences only, none of
        them held out: scored on the sequences that show it rather than given a meaningless 0 %)."""
        train, held = self.sequences(joint)
        if self.base_mse is None:
            return held
        col, n2 = self.joint_names.index(joint), self.noise2(joint)
        if np.any(self.base_mse[held, col] - n2 > 2.0 * n2):
            return held
        return np.unique(np.concatenate([train, held])).astype(np.int64)

    def train_only(self, joint: str) -> bool:
        """True if ``joint`` has too few sequences to hold any out (then it is scored on its training set)."""
        train, held = self.sequences(joint)
        return np.array_equal(train, held)

    def noise2(self, joint: str) -> float:
        """The squared noise floor of ``joint``, rad²."""
        return float(self.noise[self.joint_names.index(joint)] ** 2)


def diagnose(recording, *, base_patch: ModelPatch | None = None, candidates=EFFECT_NAMES,
             joints=None, max_effects_per_joint: int = 2, min_gain: float = 0.1, tie: float = 0.03,
             explained_at: float = 0.8, refine_top: int = 4, refine_passes: int = 1, nthread: int = 2,
             progress: bool = True) -> Diagnosis:
    """Diagnose ``recording``; see the module docstring. ``joints`` overrides the failing-joint search.

    Args:
        recording: the :class:`~adadex.data.recording.Recording` to explain. Its ``meta["sequences"]``
            (as :func:`~adadex.sysid.excite.design_excitation` writes them) say which joint each
            sequence moves; without them every sequence counts for every joint.
        base_patch: the model to start from, a :class:`~adadex.sim.patch.ModelPatch` the candidates are
            fitted on top of (not part of the selection); None (default): the nominal model.
        candidates: the names of the effects to screen (default :data:`~adadex.sim.effects.EFFECT_NAMES`,
            all of them); the load steps need ``"payload_mass"`` among them.
        joints: the recorded joints to fit (a name or a list), instead of those that fail; each is
            fitted on its own (no load first, no re-localization, coupled fit or shared load). None
            (default): the failing joints. A name not recorded raises before any work.
        max_effects_per_joint: at most this many effects are selected on one joint (default 2).
        min_gain: a further effect on a joint is added only when its score (the held-out excess error
            it removes beyond the effects already chosen, minus the complexity penalty) reaches this
            fraction (default 0.1); the first needs a score of at least 0.
        tie: candidates whose held-out reduction is within this fraction of the best's (3 × this for
            its known look-alikes) are reported as its alternatives (default 0.03); it is also the
            margin the shared-effect-and-load step must win by.
        explained_at: the verdict is ``"explained"`` when every failing joint's held-out excess error
            falls by at least this fraction (default 0.8); a load found first carries the failing
            joints it explains this well.
        refine_top: how many candidates per joint, the best on the coarse grid, are refined precisely;
            the others keep their best grid value (default 4).
        refine_passes: passes of the joint refit of all selected values together, when more than one
            effect is selected (default 1).
        nthread: threads of the :class:`~adadex.sysid.replay.Replayer`'s rollout pool (default 2).
        progress: show a progress bar, one step per candidate fit (default True).

    Returns:
        the :class:`Diagnosis`.
    """
    if joints is not None:             # before any work: recorded joints, the first that is not named
        joints = [recording.joint_names[j] for j in recording._select_joints(joints)]
    t0 = time.perf_counter()
    rep = Replayer(recording, nthread=nthread)
    base_patch = base_patch if base_patch is not None else ModelPatch(robot=rep.robot)
    noise = noise_floor(recording.joint_pos)
    times = {"localize": 0.0, "load": 0.0, "source": 0.0, "knock_on_check": 0.0, "fit": 0.0, "relocalize": 0.0,
             "joint_refit_and_scoring": 0.0}
    cpu = dict.fromkeys(times, 0.0)
    tick, cpu_tick = time.perf_counter(), time.process_time()

    def lap(stage: str) -> None:
        nonlocal tick, cpu_tick
        now, cpu_now = time.perf_counter(), time.process_time()
        times[stage] += now - tick
        cpu[stage] += cpu_now - cpu_tick
        tick, cpu_tick = now, cpu_now

    baseline, failing, findings, base_mse = _localize_failing_joints(recording, base_patch, rep, noise)
    lap("localize")
    if joints is not None:
        failing = list(joints)
    if not failing:
        return Diagnosis(verdict="nothing_missing", baseline_error=baseline, hypotheses=[], selected=[],
                         explained_fraction={}, findings=findings, wall_time_s=time.perf_counter() - t0,
                         train_only_joints=[], model=rep.robot.model_id,
                         stage_times_s={k: round(v, 3) for k, v in times.items()},
                         stage_cpu_s={k: round(v, 3) for k, v in cpu.items()})

    seq_meta = list(recording.meta.get("sequences") or [{} for _ in range(recording.num_sequences)])
    setting = _Setting(replayer=rep, base_patch=base_patch, joint_names=list(recording.joint_names), noise=noise,
                       seq_meta=seq_meta, holdout=heldout_mask(recording), base_mse=base_mse)
    first_rounds: dict[str, list[Candidate]] = {}
    selected_per_joint: dict[str, list[Candidate]] = {}
    explained: dict[str, float] = {}
    bar = progress_bar(total=len(failing) * len(candidates), desc="diagnosing", unit="fit", disable=not progress)
    # Sources first: the worst joint (relative to its noise) is fitted first, then what is left is
    # localized again on the model with its effects, so a joint that only failed because another
    # one moved it differently is not given an explanation of its own.
    pending, knock_on = list(failing), []
    moves: dict[str, list[str]] = {}   # a source joint -> the knock-on joints that stopped failing with its effects
    carried: dict[str, list[str]] = {}   # a single load's joint -> the failing joints it explains
    load_gone: list[str] = []            # failing joints that no longer fail with a load found first
    # A load first: one payload where it hangs, felt on several joints of its chain, is one source.
    load = (_load_first(setting, failing, explained_at) if joints is None and len(failing) >= 2
            and "payload_mass" in candidates else None)
    lap("load")
    if load is not None:
        cand, reds = load
        selected_per_joint[cand.joint] = [cand]
        first_rounds[cand.joint] = [cand]
        carried[cand.joint], load_gone = _carried_by_load(setting, failing, cand, reds, explained_at)
        lap("relocalize")
        knock_on = [j for j in carried[cand.joint] if j != cand.joint]
        explained.update({j: reds[j] for j in carried[cand.joint]})
        pending = [j for j in failing if j not in carried[cand.joint]]
        bar.update(len(carried[cand.joint]) * len(candidates))
        findings.append(_carried_text(setting, carried[cand.joint], cand, load_gone))
    # A source first: one effect (or a few) felt on most failing joints (a shoulder that cannot hold the arm)
    source = (_source_first(setting, failing, explained_at, candidates)
              if joints is None and load is None and len(failing) >= SOURCE_MIN_FAILING else None)
    lap("source")
    if source is not None:
        cands, reds = source
        srcs = [c.joint for c in cands]
        still = _still_failing(setting, failing, _patch_of({c.joint: [c] for c in cands}, base_patch))
        load_gone = [j for j in failing if j not in still and j not in srcs]
        explained_by = [j for j in failing if j not in still or reds[j] >= explained_at or j in srcs]
        lap("relocalize")
        for c in cands:
            selected_per_joint[c.joint] = [c]
            first_rounds[c.joint] = [c]
            carried[c.joint] = explained_by
        knock_on = [j for j in explained_by if j not in srcs]
        explained.update({j: reds[j] for j in explained_by})
        pending = [j for j in failing if j not in explained_by]
        bar.update(len(explained_by) * len(candidates))
        findings.append(_source_text(cands, explained_by, load_gone))
    follows: dict[str, tuple[list[str], float]] = {}   # a joint -> (the joints it follows, its error then, rad)
    while pending:
        joint = pending.pop(0)
        # a knock-on of another failing joint whatever moves that one: with the other failing joints moving
        # exactly as measured the model reproduces it; it gets no effect of its own
        leaders = ([j for j in failing if j != joint and j not in follows and j not in knock_on]
                   if joints is None else [])
        led = _follows(setting, joint, leaders, _patch_of(selected_per_joint, base_patch)) if leaders else None
        lap("knock_on_check")
        if led is not None:
            follows[joint] = led
            bar.update(len(candidates))
            continue
        followers = [j for j, (lead, _) in follows.items() if joint in lead]
        tried, chosen = _forward_selection(
            setting, joint, candidates, max_effects=max_effects_per_joint, min_gain=min_gain, tie=tie,
            refine_top=refine_top, bar=bar, patch=_patch_of(selected_per_joint, base_patch),
            moved=pending + followers if joints is None else ())
        first_rounds[joint] = first_rounds.get(joint, []) + tried
        selected_per_joint[joint] = selected_per_joint.get(joint, []) + chosen
        explained[joint] = chosen[-1].heldout_error_reduction if chosen else 0.0
        lap("fit")
        if chosen and (pending or followers) and joints is None:
            still = _still_failing(setting, pending + followers, _patch_of(selected_per_joint, base_patch))
            lap("relocalize")
            gone = [j for j in pending + followers if j not in still]
            knock_on += gone
            moves[joint] = gone
            bar.update(len([j for j in gone if j in pending]) * len(candidates))
            pending = [j for j in pending if j in still]
            for j in gone:
                follows.pop(j, None)
    bar.close()
    for joint in follows:
        selected_per_joint[joint] = []
    for joint in knock_on:
        if joint not in carried:
            selected_per_joint[joint] = []
    # one failing joint whose own fit chose a payload (or armature): where does a load hang, in mass and place?
    load = (_load_on_one_joint(setting, failing, selected_per_joint, explained, explained_at, tie)
            if joints is None and len(failing) == 1 and "payload_mass" in candidates else None)
    lap("load")
    if load is not None:
        cand, reds, gone = load
        selected_per_joint = {**{j: [] for j in selected_per_joint}, cand.joint: [cand]}
        first_rounds.setdefault(cand.joint, []).insert(0, cand)
        carried[cand.joint], load_gone = list(failing), gone
        knock_on = [j for j in failing if j != cand.joint]
        moves, follows = {}, {}
        explained.update({j: reds[j] for j in failing})
        findings.append(_carried_text(setting, failing, cand, load_gone))
    load = (_single_load_alternative(setting, selected_per_joint, explained, tie, candidates)
            if joints is None and not carried else None)
    if load is not None:
        cand, affected = load
        for j in affected:
            selected_per_joint[j] = []
        selected_per_joint[cand.joint] = [cand]
        carried[cand.joint] = affected
        first_rounds.setdefault(cand.joint, []).insert(0, cand)
        knock_on += [j for j in affected if j != cand.joint]
        findings.append(f"{', '.join(affected)}: one {cand.effect} on the link of {cand.joint} "
                        f"({cand.value:.4g} {get_effect(cand.effect).params[0].unit}) explains their errors as well "
                        f"as separate effects on each (it moves with all of them).")

    if sum(len(c) for c in selected_per_joint.values()) > 1:
        _refit_jointly(setting, selected_per_joint, refine_passes, skip=set(carried), moves=moves)
    suggestions, removed = _prune(setting, selected_per_joint, carried, moves, failing)
    for joint, c in removed:
        if not selected_per_joint[joint]:     # a source left with nothing: the joints it explained count again
            freed = carried.pop(joint, []) + moves.pop(joint, [])
            knock_on = [j for j in knock_on if j not in freed]
    if sum(len(c) for c in selected_per_joint.values()) > 1 or knock_on or removed or follows:
        explained.update(_score_jointly(setting, selected_per_joint, carried))
    explained = {j: max(0.0, v) for j, v in explained.items() if j in failing}
    shared = (_shared_effect_and_load(setting, failing, selected_per_joint, explained, explained_at, tie, candidates)
              if joints is None and not carried and ({"payload_mass", "mass_scale"} & set(candidates)) else None)
    if shared is not None:
        effect, cands, load, reds, (before_mean, before_every, after_every) = shared
        selected_per_joint = {j: [cands[j]] for j in failing}
        for c in load:
            selected_per_joint.setdefault(c.joint, []).append(c)
        for c in [*cands.values(), *load]:
            first_rounds.setdefault(c.joint, []).insert(0, c)
        explained, knock_on, suggestions, follows = dict(reds), [], [], {}
        mean = float(np.mean(list(reds.values())))
        load_text = (f"one payload_mass on the link of {load[0].joint} ({_link_names(setting, load[0].joint)}; "
                     f"{_load_text(load[0])})" if load[0].effect == "payload_mass" else
                     f"their links {load[0].value:.3g} × as heavy as the model's (one mass_scale on all of them, "
                     f"95 % interval {load[0].ci95[0]:.3g}–{load[0].ci95[1]:.3g})")
        findings.append(f"{', '.join(failing)}: {effect} on every one of them "
                        f"({min(c.value for c in cands.values()):.3g}–{max(c.value for c in cands.values()):.3g}) "
                        f"and {load_text} explain their held-out errors better than the effects chosen joint by "
                        f"joint ({mean:.0%} against {before_mean:.0%} on average on each joint's own sequences, "
                        f"{after_every:.0%} against {before_every:.0%} on every held-out sequence): softer servos "
                        f"that carry a load.")
    loaded: dict[str, list[Candidate]] = {}     # a carried joint -> the effects of every source that carries it
    for k, aff in carried.items():
        for j in aff:
            if j not in load_gone:
                loaded[j] = loaded.get(j, []) + list(selected_per_joint[k])
    own_knock_on = [j for j in knock_on if j not in loaded]
    if own_knock_on:
        findings.append(f"{', '.join(own_knock_on)}: no effect of their own; their error follows from the effects "
                        "found on the joints that move them (it falls below the failure threshold once those are "
                        "in the model).")
    # a joint that follows another: judged with it (its finding names what explains the joints it follows)
    # when those are explained, else a knock-on of their unexplained error (it needs no effect of its own)
    followed = {j: [c for k in lead for c in selected_per_joint.get(k, [])] for j, (lead, _) in follows.items()
                if all(explained.get(k, 0.0) >= explained_at for k in lead)}
    for j, (lead, rms) in follows.items():
        unexplained_lead = [k for k in lead if explained.get(k, 0.0) < explained_at]
        findings.append(_follower_text(setting, j, lead, rms, unexplained_lead))
    lap("joint_refit_and_scoring")

    hypotheses = _hypotheses(first_rounds, selected_per_joint, setting.train_only, rep.robot)
    selected = _merge_over_joints(selected_per_joint, rep.robot)
    train_only = [j for j in failing if setting.train_only(j)]
    _mark_train_only(hypotheses, selected, train_only)
    verdict, sentences = _verdict({j: v for j, v in explained.items()
                                   if (j not in knock_on or j in loaded) and (j not in follows or j in followed)},
                                  {**selected_per_joint, **loaded, **followed},
                                  explained_at, rep.robot, train_only)
    if train_only:
        sentences.insert(0, f"Too few sequences to hold any out on {', '.join(train_only)} (at least 3 of a "
                            f"joint's own are needed): scored on the training sequences only, no held-out figure.")
    findings += [s["finding"] for s in suggestions]      # before the per-joint lines, which end the findings
    return Diagnosis(verdict=verdict, baseline_error=baseline, hypotheses=hypotheses, selected=selected,
                     explained_fraction=explained, findings=findings + sentences,
                     wall_time_s=time.perf_counter() - t0, train_only_joints=train_only, model=rep.robot.model_id,
                     stage_times_s={k: round(v, 3) for k, v in times.items()},
                     stage_cpu_s={k: round(v, 3) for k, v in cpu.items()}, suggestions=suggestions)


def _follower_text(setting: _Setting, joint: str, lead: list[str], rms: float, unexplained: list[str]) -> str:
    """The finding of a joint whose failure is a knock-on of the failing joints ``lead`` (:func:`_follows`)."""
    ratio = rms / max(float(setting.noise[setting.joint_names.index(joint)]), 1e-6)
    text = (f"{joint}: a knock-on of {', '.join(lead)}, no effect of its own: with {', '.join(lead)} moving exactly "
            f"as measured the model reproduces it (RMS error {np.degrees(rms):.2g}° = {ratio:.1f}× its noise floor "
            f"on its own sequences, under the failure threshold)")
    if unexplained:
        return text + f"; its error is {', '.join(unexplained)}'s, which is unexplained."
    return text + "."


def _mark_train_only(hypotheses: list[dict], selected: list[dict], train_only: list[str]) -> None:
    """Mark what was scored on held-out or training sequences; train-only scores lose their held-out field."""
    for h in hypotheses:
        h["scored_on"] = "train" if h["joints"][0] in train_only else "heldout"
        if h["scored_on"] == "train":
            h["heldout_error_reduction"] = None
    for h in selected:
        h["scored_on"] = ["train" if j in train_only else "heldout" for j in h["joints"]]
        h["heldout_error_reduction"] = [None if j in train_only else v
                                        for j, v in zip(h["joints"], h["heldout_error_reduction"])]


def _localize_failing_joints(recording, base_patch: ModelPatch, rep: Replayer, noise: np.ndarray):
    """Replay on ``base_patch``: the baseline errors, the failing joints, the localization's sentences and
    each sequence's MSE per joint, (S, J)."""
    cmp = compare(recording, base_patch, replayer=rep)
    loc = localize(cmp)
    names = list(recording.joint_names)
    baseline = {"overall_rms_rad": float(cmp.rms()),
                "per_joint_rms_rad": dict(zip(names, map(float, cmp.rms_per_joint()))),
                "noise_floor_rad": dict(zip(names, map(float, noise)))}
    return baseline, loc.failing_joints, list(loc.sentences), np.mean(cmp.error ** 2, axis=1)


def _fails(setting: _Setting, joint: str, rms: float) -> bool:
    """:func:`~adadex.sysid.compare.localize`'s test: an RMS error (rad) above :data:`FAIL_RATIO` × the
    joint's noise floor and above :data:`FAIL_ABS`."""
    col = setting.joint_names.index(joint)
    return rms / max(float(setting.noise[col]), 1e-6) > FAIL_RATIO and rms > FAIL_ABS


def _own_sequences(setting: _Setting, joint: str) -> np.ndarray:
    """The sequences ``joint`` is localized on: its own, or all when none excites it (as localize)."""
    own = np.unique(np.concatenate(setting.sequences(joint))).astype(np.int64)
    return own if own.size else np.arange(len(setting.seq_meta), dtype=np.int64)


def _follows(setting: _Setting, joint: str, others: list[str], patch: ModelPatch) -> tuple[list[str], float] | None:
    """Whether the failure of ``joint`` is a knock-on of the failing joints ``others``, whatever moves them:
    ``(the joints it follows, its RMS error then, rad)``, or None when it still fails.

    Its own sequences are replayed on ``patch`` with ``others`` moving exactly as measured
    (:meth:`~adadex.sysid.replay.Replayer.simulate_imposed`: every torque on them, a missing effect
    included, is taken from the measurement; ``joint`` feels their measured motion through the model's
    coupled dynamics). If ``joint`` then no longer fails (:func:`_fails`), its error came from their motion,
    not from an effect of its own. One replay; when it follows several, each is tried alone too and the
    joints it follows are those that suffice alone (all of them if none does)."""
    seqs = _own_sequences(setting, joint)
    col, measured = setting.joint_names.index(joint), setting.replayer.rec.joint_pos[seqs]

    def rms_with(imposed: list[str]) -> float:
        sim = setting.replayer.simulate_imposed(patch, imposed=imposed, sequences=seqs)
        return float(np.sqrt(np.mean((sim[..., col] - measured[..., col]) ** 2)))

    rms = rms_with(others)
    if _fails(setting, joint, rms):
        return None
    if len(others) > 1:
        alone = {o: rms_with([o]) for o in others}
        enough = [o for o, r in alone.items() if not _fails(setting, joint, r)]
        if enough:
            return enough, min(alone[o] for o in enough)
    return list(others), rms


def _still_failing(setting: _Setting, joints: list[str], patch: ModelPatch) -> list[str]:
    """Which of ``joints`` still fail on ``patch``: :func:`~adadex.sysid.compare.localize`'s test (RMS error
    on a joint's own sequences against its noise floor over the whole recording), replaying only those
    joints' sequences rather than the whole recording."""
    own = {j: _own_sequences(setting, j) for j in joints}
    seqs = np.unique(np.concatenate(list(own.values())))
    sim = setting.replayer.simulate(patch, sequences=seqs)
    measured = setting.replayer.rec.joint_pos[seqs]
    out = []
    for j in joints:
        col, rows = setting.joint_names.index(j), np.searchsorted(seqs, own[j])
        rms = float(np.sqrt(np.mean((sim[rows, :, col] - measured[rows, :, col]) ** 2)))
        if _fails(setting, j, rms):
            out.append(j)
    return out


def _forward_selection(setting: _Setting, joint: str, candidates, *, max_effects: int, min_gain: float,
                       tie: float, refine_top: int, bar, patch: ModelPatch | None = None, moved=(),
                       ) -> tuple[list[Candidate], list[Candidate]]:
    """Add effects on ``joint`` one at a time, each the best-scoring on held-out sequences, while each
    adds ``min_gain`` (the first only needs a positive score). Returns the first round's candidates,
    ranked, and the chosen effects in order. ``moved``: the failing joints still pending, whose errors
    the refined candidates are fitted to as well (see :func:`_fit_and_score_candidates`)."""
    train, held = setting.sequences(joint)[0], setting.scored(joint)
    n2 = setting.noise2(joint)
    chosen: list[Candidate] = []
    patch = setting.base_patch if patch is None else patch
    held_before = JointFitter(setting.replayer, joint, held, patch).mse_per_sequence(patch)
    start = patch
    first_round: list[Candidate] = []
    for round_ in range(max_effects):
        names_left = [n for n in candidates if not any(c.effect == n for c in chosen)]
        cands = _fit_and_score_candidates(setting, joint, names_left, patch, train, held, held_before, n2,
                                          refine_top=refine_top, bar=bar if round_ == 0 else None, moved=moved,
                                          start=start, windowed=_windowed(chosen))
        if round_ == 0:
            first_round = cands
        if not cands or cands[0].score < (min_gain if chosen else 0.0):
            break
        best = cands[0]
        best.alternatives = _lookalikes(best, cands[1:], tie)
        chosen.append(best)      # the same object as its hypothesis: the joint refit refines both
        patch = patch.with_effect(best.effect, [joint], [[best.value]])
        if best.heldout_error_reduction >= 0.98:
            break
    return first_round, chosen


def _fit_and_score_candidates(setting: _Setting, joint: str, names: list[str], patch: ModelPatch, train, held,
                              held_before, n2: float, *, refine_top: int, bar, moved=(),
                              start: ModelPatch | None = None, windowed: bool = False) -> list[Candidate]:
    """Fit each of ``names`` on top of ``patch`` on the training sequences and score it on the held-out
    ones; ranked best first. ``bar`` (if given) advances once per candidate.

    Scoring: ``held_before`` is the free-replay MSE of each held-out sequence on ``start`` (the patch the
    joint's forward selection started from; default ``patch``). An effect of
    :data:`~adadex.sysid.fit.WINDOWED_EFFECTS`, and every candidate when ``windowed`` (an effect chosen
    on the joint already is one), is scored on the windowed cost instead — its training and held-out
    reductions and its gain over ``patch`` all measured against the windowed cost of ``start`` and
    ``patch`` (``scored_by`` ``"windowed"``; see the module docstring).

    With failing joints still pending (``moved``), the best candidate is then refitted against the error
    of ``joint`` and of those joints on all their training sequences (a
    :class:`~adadex.sysid.fit.CoupledFitter`: grid, Brent to :data:`COUPLED_XTOL`, a compass polish): an
    effect on ``joint`` that moves them is fitted to the error it causes there too, which pins a
    sensitive value (a torque limit the arm barely holds at) far better than ``joint``'s own sequences.
    It keeps the value with the lower coupled error (its own fit's or the coupled fit's) and is scored on
    ``joint``'s own held-out sequences as before."""
    fitter = JointFitter(setting.replayer, joint, train, patch)
    held_fitter = JointFitter(setting.replayer, joint, held, patch)
    cur_held = held_fitter.mse_per_sequence(patch)
    train_before = fitter.mse(patch)
    start = patch if start is None else start
    windowed_before: dict[str, np.ndarray] = {}    # the windowed costs of start and patch, when first needed

    def scored(name: str, value: float, ci, after: float) -> Candidate:
        with_it = fitter.patch_with(name, value)
        by_windows = windowed or name in WINDOWED_EFFECTS
        if by_windows:
            if not windowed_before:
                windowed_before.update(held=held_fitter.window_mse_per_sequence(start),
                                       cur=held_fitter.window_mse_per_sequence(patch),
                                       train=fitter.window_mse_per_sequence(patch))
            h_before, h_cur, t_before = windowed_before["held"], windowed_before["cur"], windowed_before["train"]
            held_after, after = held_fitter.window_mse_per_sequence(with_it), fitter.window_mse_per_sequence(with_it)
        else:
            h_before, h_cur, t_before = held_before, cur_held, train_before
            held_after = held_fitter.mse_per_sequence(with_it)
        red_tr = _reduction(t_before, after, n2)
        red_ho = _reduction(h_before, held_after, n2)
        gain = red_ho - _reduction(h_before, h_cur, n2)
        return Candidate(effect=name, joint=joint, value=value, ci95=ci, train_error_reduction=red_tr,
                         heldout_error_reduction=red_ho,
                         score=gain - COMPLEXITY_PENALTY * len(get_effect(name).params),
                         scored_by=_scored_by(by_windows))

    cands = []
    grids, ranked = _screen_on_grid(fitter, names)
    for k, name in enumerate(ranked):
        if k < refine_top:
            value, ci, after = _refine(fitter, name, grids[name], train_before)
        else:
            value, ci, after = _best_on_grid(name, grids[name], joint, setting.replayer.robot)
        if not _is_absent(name, value, joint, setting.replayer.robot):   # "not there" explains nothing
            cands.append(scored(name, value, ci, after))
        if bar is not None:
            bar.update(1)
    cands.sort(key=lambda c: -c.score)
    shaken = _moved_by(setting, joint, cands[0], train, moved, patch) if cands and len(moved) else []
    if shaken:
        best = cands[0]
        cols = [joint] + shaken
        seqs = np.unique(np.concatenate([train] + [setting.sequences(j)[0] for j in shaken])).astype(np.int64)
        coupled = CoupledFitter(setting.replayer, joint, cols, seqs,
                                [setting.noise[setting.joint_names.index(j)] for j in cols], patch)
        r = coupled.fit(best.effect, xtol_frac=COUPLED_XTOL, maxiter=100)   # from its own (coupled) grid
        if (r.mse_after < coupled.mse(coupled.patch_with(best.effect, best.value))
                and not _is_absent(best.effect, r.value, joint, setting.replayer.robot)):
            cands[0] = scored(best.effect, r.value, r.ci95, fitter.mse(fitter.patch_with(best.effect, r.value)))
            cands.sort(key=lambda c: -c.score)
    return cands


def _moved_by(setting: _Setting, joint: str, cand: Candidate, train, moved, patch: ModelPatch) -> list[str]:
    """The pending joints in ``moved`` that ``cand`` (an effect on ``joint``, at its own fit) visibly moves:
    on the training sequences of ``joint`` and of those joints, the change the effect makes to a joint's
    simulated path is at least :data:`COUPLING_MIN` of that joint's residual (RMS). One replay decides
    which joints a coupled fit has to look at; a joint with an effect of its own that ``cand`` barely
    touches (22 independent faults) is left out, which keeps the coupled fit from replaying the whole
    recording for every source."""
    others = [j for j in moved if j != joint]
    if not others:
        return []
    seqs = np.unique(np.concatenate([train] + [setting.sequences(j)[0] for j in others])).astype(np.int64)
    names = setting.joint_names
    cols = [names.index(j) for j in others]
    rep = setting.replayer
    before = rep.simulate(patch, sequences=seqs)[..., cols]
    after = rep.simulate(patch.with_effect(cand.effect, [joint], [[cand.value]]), sequences=seqs)[..., cols]
    residual = rep.rec.joint_pos[seqs][..., cols] - before
    change = np.sqrt(np.mean((after - before) ** 2, axis=(0, 1)))
    rms = np.sqrt(np.mean(residual ** 2, axis=(0, 1)))
    return [j for j, c, r in zip(others, change, rms) if c >= COUPLING_MIN * r]


def _is_absent(name: str, value: float, joint: str, robot) -> bool:
    """Whether ``value`` is (within 0.1 % of the bounds' width of) the effect's absent value."""
    eff = get_effect(name)
    lo, hi = (float(b[0, 0]) for b in eff.bounds([joint], robot))
    return abs(value - float(eff.absent_values()[0])) <= 1e-3 * (hi - lo)


def _screen_on_grid(fitter: JointFitter, names: list[str]) -> tuple[dict, list[str]]:
    """Every candidate's costs on a coarse grid, and the names ranked by their best grid cost: only the
    most promising are then refined."""
    grids = {n: fitter.grid(n) for n in names}
    return grids, sorted(names, key=lambda n: grids[n][1].min())


def _refine(fitter: JointFitter, name: str, grid, train_before: float) -> tuple[float, tuple, float]:
    """(value, 95 % interval, training MSE) of a precise fit of ``name``, started from its grid."""
    r = fitter.fit(name, grid=grid, mse_before=train_before)
    return r.value, r.ci95, r.mse_after


def _best_on_grid(name: str, grid, joint: str, robot=None) -> tuple[float, tuple, float]:
    """(value, the effect's bounds as the interval, training MSE) of the best grid point of ``name``."""
    i = int(np.argmin(grid[1]))
    ci = tuple(float(b[0, 0]) for b in get_effect(name).bounds([joint], robot))
    return float(grid[0][i]), ci, float(grid[1][i])


def _lookalikes(best: Candidate, others: list[Candidate], tie: float) -> list[str]:
    """The effects that explain the held-out data about as well as ``best``: within ``tie``, or within
    ``3 · tie`` for the effects ``best`` is known to look like."""
    return [c.effect for c in others if best.heldout_error_reduction - c.heldout_error_reduction < tie
            or c.effect in get_effect(best.effect).lookalikes and
            best.heldout_error_reduction - c.heldout_error_reduction < 3 * tie]


#: a single load found before any joint is fitted (:func:`_load_first`) is kept when it explains this
#: fraction of the failing joints' held-out excess error on average
LOAD_FIRST_AT = 0.6
#: how many links, ranked by their Gauss–Newton step, are searched for the load's mass
LOAD_SHORTLIST = 4
#: the search starts only if the best link's Gauss–Newton step removes this fraction of the error: a true
#: load's step removes about 0.8 (0.6 kg at the palm, 1 kg on the forearm), a delay on the shoulder and
#: friction on a finger 0.36 (with a mass on the shoulder's own link)
LOAD_SCREEN_AT = 0.5

#: a source found first (:func:`_source_first`) is kept when it explains this fraction of the failing joints'
#: held-out excess error on average (as a load found first, :data:`LOAD_FIRST_AT`)
SOURCE_FIRST_AT = 0.6
#: the screen's candidate must halve the failing joints' error on average (each joint counted alike: the mean
#: of its MSE ratio) before any source is fitted; a further source must lower that mean by this much more
SOURCE_SCREEN_AT = 0.5
SOURCE_NEXT_AT = 0.1
#: the joints screened as sources: this many worst by error over noise, and the joints of this many joints or
#: pairs of joints of adjacent links whose measured motion, imposed, lowers the other failing joints' error most
SOURCE_JOINTS = 3
#: nothing is screened unless imposing some joint's measured motion (or two adjacent joints') leaves the other
#: failing joints at most this fraction of their error on average (mean MSE ratio): a torque-limited shoulder
#: 0.38–0.58 (its joint or pair), 22 independent faults 0.89 at best (benchmarks/sysid_diagnosis.py)
SOURCE_IMPOSED_AT = 0.75
#: at most this many sources found first, and the candidates fitted per source
MAX_SOURCES = 3
SOURCE_SHORTLIST = 2
#: points of the scan between the best screened point's neighbours, and the half-width (fraction of the
#: bounds) of the scan (2 × SOURCE_SCAN − 1 points) that starts the sources' joint refit
SOURCE_SCAN = 9
SOURCE_REFIT_SPAN = 0.02
#: rounds of the windowed refit of several sources found first (each with the others in place; two limits on
#: the two shoulder joints trade one against the other)
SOURCE_WINDOWED_PASSES = 3
#: the least number of failing joints for a source to be looked for first
SOURCE_MIN_FAILING = 3


def _source_first(setting: _Setting, failing: list[str], explained_at: float, candidates):
    """One source — a library effect on one joint, or a few such effects found one after another — that
    explains most failing joints' error at once, before any joint is fitted: ``(candidates, held-out
    reduction per failing joint)`` or None.

    A shoulder that cannot hold the arm (a torque limit) moves every joint of the robot: 20 of 22 joints
    fail, and fitted joint by joint each is given an effect of its own. Here every candidate effect on a
    few candidate source joints is screened on the residual of every recorded joint in units of its noise
    (the likelihood), on the training sequence where each failing joint errs most (one replay per grid
    point: four interior points of the fit's coarse grid, as a saturation — a torque limit — has no slope
    at its absent value for a finite-difference step to see). First, one replay per failing joint
    and per pair of failing joints of adjacent links with their measured motion imposed
    (:meth:`~adadex.sysid.replay.Replayer.simulate_imposed`): unless one leaves the other failing joints at
    most :data:`SOURCE_IMPOSED_AT` of their error on average (mean MSE ratio), no joint's motion explains
    the others' and nothing more is done (22 independent faults: 0.89 at best, 3 s). The candidate source
    joints: the :data:`SOURCE_JOINTS` failing joints with the largest error over noise, and those of the
    :data:`SOURCE_JOINTS` best imposed joints or pairs. A candidate is scored by the mean over the failing
    joints of its MSE ratio to the starting patch's (each joint counts alike: a source explains many
    joints, not the largest error); nothing is fitted unless the best halves it
    (:data:`SOURCE_SCREEN_AT`). The :data:`SOURCE_SHORTLIST` best are fitted on that residual (Brent
    between the best grid point's neighbours), the best kept; a further source is screened on top of it
    and kept while it lowers the mean ratio by :data:`SOURCE_NEXT_AT` (two limited shoulder joints are two
    torque limits). The sources' values are then refitted together, each with the others in place, on the
    two training sequences where each failing joint errs most: Brent to :data:`COUPLED_XTOL` of the bounds and a compass polish
    (a knock-on error hangs on a sensitive value), once from a scan of ± :data:`SOURCE_REFIT_SPAN` of the
    bounds around the value and once from the fit's grid over the whole bounds, the better kept. They are
    kept if together they explain :data:`SOURCE_FIRST_AT` of the failing joints' held-out excess error on
    average and no value sits on a bound or at its absent value."""
    rep, robot, names = setting.replayer, setting.replayer.robot, setting.joint_names
    effects = [n for n in candidates if n != "payload_mass" and n not in WINDOWED_EFFECTS
               and len(get_effect(n).params) == 1]
    if not effects:
        return None
    base = setting.base_patch
    few = np.unique(np.concatenate([_most_telling(setting, j, 1) for j in failing])).astype(np.int64)
    fcols = [names.index(j) for j in failing]
    measured = rep.rec.joint_pos[few]
    scale = 1.0 / np.maximum(setting.noise, 1e-9)

    def per_joint(sim: np.ndarray) -> np.ndarray:
        return np.mean(((sim - measured) * scale) ** 2, axis=(0, 1))

    b0 = per_joint(rep.simulate(base, sequences=few))
    fb = np.maximum(b0[fcols], 1e-12)

    def ratio(patch: ModelPatch) -> float:
        """Mean over the failing joints of the MSE ratio to the starting patch's (capped at 2)."""
        return float(np.mean(np.minimum(per_joint(rep.simulate(patch, sequences=few))[fcols] / fb, 2.0)))

    # whose measured motion, imposed, reproduces the others' error: a joint (or two of adjacent links) that moves them
    pairs = [[j, k] for i, j in enumerate(failing) for k in failing[i + 1:] if _adjacent(setting, j, k)]
    moving = []
    for js in [[j] for j in failing] + pairs:
        rest = [names.index(k) for k in failing if k not in js]
        if rest:
            e = per_joint(rep.simulate_imposed(base, imposed=js, sequences=few))
            moving.append((float(np.mean(np.minimum(e[rest] / np.maximum(b0[rest], 1e-12), 2.0))), js))
    moving.sort(key=lambda t: t[0])
    if not moving or moving[0][0] > SOURCE_IMPOSED_AT:
        return None        # no joint's motion explains the others': each fails for a reason of its own
    own = np.array([np.sqrt(np.mean(setting.base_mse[_own_sequences(setting, j), names.index(j)]))
                    / max(float(setting.noise[names.index(j)]), 1e-9) for j in failing]) \
        if setting.base_mse is not None else np.zeros(len(failing))
    worst = [failing[i] for i in np.argsort(-own)[:SOURCE_JOINTS]]
    joints = list(dict.fromkeys(worst + [j for r, js in moving[:SOURCE_JOINTS] if r <= SOURCE_IMPOSED_AT
                                         for j in js]))

    # each candidate effect on one of those joints, or on two of them that move adjacent links with one value
    # (a shoulder whose two joints are both too weak to hold the arm: either alone leaves the other failing)
    groups = [[j] for j in joints] + [[j, k] for i, j in enumerate(joints) for k in joints[i + 1:]
                                      if _adjacent(setting, j, k)]
    sources: list[Candidate] = []
    patch, current = base, 1.0
    for _ in range(MAX_SOURCES):
        if current <= SOURCE_NEXT_AT:
            break          # what is left is too little for a further source to lower it by SOURCE_NEXT_AT
        screened = []
        for e in effects:
            for js in groups:
                if any(c.joint in js for c in sources) or not _same_bounds(e, js, robot):
                    continue
                xs = grid_points(e, js[0], robot, absent=False)
                pts = xs[1::2] if xs.size >= 8 else xs
                rs = [ratio(patch.with_effect(e, js, [[float(x)]] * len(js))) for x in pts]
                i = int(np.argmin(rs))
                screened.append((rs[i], e, js, float(pts[i])))
        screened.sort(key=lambda t: t[0])
        need = 1.0 - SOURCE_SCREEN_AT if not sources else current - SOURCE_NEXT_AT
        if not screened or screened[0][0] > need:
            break
        best = None
        for r0, e, js, x0 in screened[:SOURCE_SHORTLIST]:
            xs = grid_points(e, js[0], robot, absent=False)
            k = int(np.argmin(np.abs(xs - x0)))
            a, b = float(xs[max(k - 1, 0)]), float(xs[min(k + 1, xs.size - 1)])
            lo, hi = (float(v[0, 0]) for v in get_effect(e).bounds([js[0]], robot))

            def cost(x: float) -> float:
                return ratio(patch.with_effect(e, js, [[float(x)]] * len(js)))

            # a scan, then Brent between the best point's neighbours: the cost of a limit the arm barely holds
            # at is a narrow well beside a cliff (0.3: 0.001; 0.295: 0.03; 0.305: 0.34), which Brent over
            # the grid's bracket alone steps over
            ys = np.linspace(a, b, SOURCE_SCAN)
            cs = [cost(y) for y in ys]
            i = int(np.argmin(cs))
            x, r = float(ys[i]), float(cs[i])
            res = minimize_scalar(cost, bounds=(float(ys[max(i - 1, 0)]), float(ys[min(i + 1, ys.size - 1)])),
                                  method="bounded", options={"xatol": 1e-4 * (hi - lo), "maxiter": 25})
            if res.fun < r:
                x, r = float(res.x), float(res.fun)
            # a compass search from there, down to Brent's tolerance: it steps into the well Brent stops beside
            x, r = _compass(cost, x, r, float(ys[max(i - 1, 0)]), float(ys[min(i + 1, ys.size - 1)]),
                            0.5 * float(ys[1] - ys[0]), 1e-4 * (hi - lo))
            if r0 < r:
                x, r = x0, r0
            if best is None or r < best[0]:
                best = (r, e, js, x)
        r, e, js, x = best
        if r > need:
            break
        sources += [Candidate(effect=e, joint=j, value=x, ci95=(x, x), train_error_reduction=1.0 - r,
                              heldout_error_reduction=0.0, score=0.0) for j in js]
        patch, current = patch.with_effect(e, js, [[x]] * len(js)), r
    if not sources:
        return None
    # the values together, each with the others in place, on the two sequences where each failing joint errs most
    seqs = np.unique(np.concatenate([_most_telling(setting, j, 2) for j in failing])).astype(np.int64)
    for c in sources:
        fitter, lo, hi = _source_fitter(setting, sources, c, failing, seqs, base)
        # a scan around the value first (the true limit's well sits beside a cliff: Brent from a bracket
        # centred off it steps over it), then Brent between the best point's neighbours and a compass polish
        steps = np.linspace(-1.0, 1.0, 2 * SOURCE_SCAN - 1)
        xs = np.unique(np.clip(c.value + SOURCE_REFIT_SPAN * (hi - lo) * steps, lo, hi))
        grid = (xs, np.array([fitter.mse(fitter.patch_with(c.effect, float(x))) for x in xs]))
        # and from the fit's own grid over the whole bounds, as a joint's refit against its knock-ons: which of
        # the two brackets holds the well depends on where the cliff is (a 0.35 limit on arm_j2 alone: the
        # whole bounds' bracket; 0.3 on both shoulder joints: the scan's)
        r = min(fitter.fit(c.effect, xtol_frac=COUPLED_XTOL, maxiter=100, grid=grid),
                fitter.fit(c.effect, xtol_frac=COUPLED_XTOL, maxiter=100), key=lambda f: f.mse_after)
        c.value, c.ci95 = r.value, r.ci95
    full = _patch_of({c.joint: [c] for c in sources}, base) if len({c.joint for c in sources}) == len(sources) \
        else None
    if full is None or any(on_bound(c.effect, c.joint, c.value, c.ci95, robot)
                           or _is_absent(c.effect, c.value, c.joint, robot) for c in sources):
        return None
    before = _heldout_mse(setting, base, failing)
    after = _heldout_mse(setting, full, failing)
    reds = {j: _reduction(before[j], after[j], setting.noise2(j)) for j in failing}
    red = float(np.mean(list(reds.values())))
    if red < SOURCE_FIRST_AT or min(reds.values()) < explained_at:
        # a free replay that misses may be chaotic around the value, not wrong: located and scored on the
        # windowed cost instead, which is smooth there (a 0.3 limit on both shoulder joints, every joint
        # recorded: the free replay's cost 0.65 at 0.3, 1074 at 0.2999, 1290 at 0.3001; the windowed 3.99,
        # 4.80, 4.15, its minimum within 2e-4 of the truth); kept when it explains more
        windowed = [dataclasses.replace(c) for c in sources]
        _refit_windowed(setting, windowed, failing, seqs, base)
        if not any(on_bound(c.effect, c.joint, c.value, c.ci95, robot) or _is_absent(c.effect, c.value, c.joint, robot)
                   for c in windowed):
            before = _heldout_mse(setting, base, failing, windowed=True)
            after = _heldout_mse(setting, _patch_of({c.joint: [c] for c in windowed}, base), failing, windowed=True)
            wreds = {j: _reduction(before[j], after[j], setting.noise2(j)) for j in failing}
            wred = float(np.mean(list(wreds.values())))
            if wred > red:
                sources, reds, red = windowed, wreds, wred
                for c in sources:
                    c.chaotic, c.scored_by = True, _scored_by(True)
        if red < SOURCE_FIRST_AT:
            return None
    for c in sources:
        c.heldout_error_reduction, c.score = red, red - COMPLEXITY_PENALTY
    return sources, reds


def _source_fitter(setting: _Setting, sources: list[Candidate], c: Candidate, failing: list[str], seqs,
                   base: ModelPatch):
    """``(fitter, lo, hi)``: a :class:`~adadex.sysid.fit.CoupledFitter` of source ``c`` against every failing
    joint on ``seqs``, the other sources in place, and the bounds of its effect on its joint."""
    others = base
    for o in sources:
        if o is not c:
            others = others.with_effect(o.effect, [o.joint], [[o.value]])
    lo, hi = (float(v[0, 0]) for v in get_effect(c.effect).bounds([c.joint], setting.replayer.robot))
    noise = [setting.noise[setting.joint_names.index(j)] for j in failing]
    return CoupledFitter(setting.replayer, c.joint, failing, seqs, noise, others), lo, hi


def _refit_windowed(setting: _Setting, sources: list[Candidate], failing: list[str], seqs, base: ModelPatch) -> None:
    """The sources' values (updated in place) on the windowed cost of every failing joint on ``seqs``, each
    with the others in place (:data:`SOURCE_WINDOWED_PASSES` rounds of coordinate descent when there are
    several): Brent over ± :data:`SOURCE_REFIT_SPAN` of the bounds around its value, to 1e-5 of them, and the
    windowed Gauss–Newton interval."""
    for c in [c for _ in range(SOURCE_WINDOWED_PASSES if len(sources) > 1 else 1) for c in sources]:
        fitter, lo, hi = _source_fitter(setting, sources, c, failing, seqs, base)
        a, b = max(lo, c.value - SOURCE_REFIT_SPAN * (hi - lo)), min(hi, c.value + SOURCE_REFIT_SPAN * (hi - lo))
        res = minimize_scalar(lambda x: fitter.window_mse(fitter.patch_with(c.effect, float(x))), bounds=(a, b),
                              method="bounded", options={"xatol": 1e-5 * (hi - lo), "maxiter": 40})
        c.value = float(res.x)
        c.ci95 = fitter._ci95(c.effect, c.value, lo, hi, windowed=True)


def _shared_effect_and_load(setting: _Setting, failing: list[str], selected_per_joint: dict, explained: dict,
                            explained_at: float, tie: float, candidates=EFFECT_NAMES):
    """One effect on every failing joint of a chain and one load, instead of a different effect on each:
    ``(effect, {joint: candidate}, [load candidates], held-out reduction per joint, (the selection's mean
    reduction, the selection's and the pair's on every held-out sequence))`` or None.

    Softer servos on an arm that carries a load look, joint by joint, like the softness where gravity
    does not load the joint (a yaw, a roll) and like damping, friction, a stiffer derivative or a
    softness of another size where it does (the pitch joints sag as well as lag), and the load screen
    finds no load while the softness dominates. So when the failing joints, all on one chain, are not
    yet explained to within ``tie`` — on their own held-out sequences, or on every held-out sequence
    (:func:`_every_heldout_reduction`) — and one effect was chosen on at least two of them, that effect is
    tried on every failing joint — at its value on the joint it explains best alone (where the load does
    not weigh: the yaw, a wrist), else the median of its values — with a load on top: links heavier than the
    model's (:func:`_heavier_links`) and, with ``payload_mass`` among the ``candidates``, a payload
    screened on one link (:func:`_load_first` on that model) — the step runs when either load effect is a
    candidate (``mass_scale`` is not among the default candidates, which fit it joint by joint, but a
    load shared by a chain's links is one hypothesis, not one per joint); then the effect is refitted on each joint with the
    rest in place. The better pair replaces the selection when the load explains most of what the effect
    alone leaves (the load steps' own test), the pair explains the failing joints' held-out error by
    ``tie`` more on average than the selection (or as well, and by ``tie`` more on every held-out
    sequence; :func:`_pair_with_load`), the load explains :data:`MIN_EXPLAINED` of some joint's
    error beyond the refitted effect (it is not spurious there), and no value sits on a bound."""
    counts: dict[str, list[float]] = {}
    for j in failing:
        for c in selected_per_joint.get(j, []):
            counts.setdefault(c.effect, []).append(c.value)
    if not counts:
        return None
    effect, values = max(counts.items(), key=lambda kv: len(kv[1]))
    current = float(np.mean([explained.get(j, 0.0) for j in failing]))
    if (len(values) < 2 or effect in ("payload_mass", "mass_scale") or len(get_effect(effect).params) != 1
            or not _chain_below(setting, failing)):
        return None
    chosen = _patch_of({j: selected_per_joint.get(j, []) for j in failing}, setting.base_patch)
    crossed = float(np.mean(list(_every_heldout_reduction(setting, chosen, failing).values())))
    if current > 1.0 - tie and crossed > 1.0 - tie:
        return None
    alone = [j for j in failing if [c.effect for c in selected_per_joint.get(j, [])] == [effect]]
    best = max(alone, key=lambda j: explained.get(j, 0.0)) if alone else None
    v = selected_per_joint[best][0].value if best is not None else float(np.median(values))
    base = setting.base_patch.with_effect(effect, failing, [v] * len(failing))
    on_base = dataclasses.replace(setting, base_patch=base)
    loads = []
    heavier = _heavier_links(on_base, failing, explained_at)
    if heavier is not None:
        loads.append(heavier[0])
    found = _load_first(on_base, failing, explained_at) if "payload_mass" in candidates else None
    if found is not None:
        loads.append([found[0]])
    pairs = [p for p in (_pair_with_load(setting, failing, effect, v, load, tie, current, crossed) for load in loads)
             if p is not None]
    if not pairs:
        return None
    cands, load, reds, every = max(pairs, key=lambda p: float(np.mean(list(p[2].values()))))
    return effect, cands, load, reds, (current, crossed, every)


def _with_load(patch: ModelPatch, load: list[Candidate]) -> ModelPatch:
    """``patch`` with a load: one payload (its mass and offset), or one ``mass_scale`` on several joints."""
    if load[0].effect == "payload_mass":
        return patch.with_effect("payload_mass", [load[0].joint], [[load[0].value, *load[0].extra]])
    return patch.with_effect(load[0].effect, [c.joint for c in load], [[c.value] for c in load])


def _pair_with_load(setting: _Setting, failing: list[str], effect: str, v: float, load: list[Candidate], tie: float,
                    current: float, crossed: float):
    """The effect refitted on each failing joint with ``load`` and the others in place, scored on the
    held-out sequences: ``({joint: candidate}, load, reductions)``, or None when a value sits on a bound,
    the load is felt nowhere beyond the effect, or the pair beats neither the selection's ``current``
    (its mean reduction on each joint's own held-out sequences) by ``tie`` nor, while within ``tie`` of
    it there, the selection's ``crossed`` (on every held-out sequence) by ``tie``."""
    robot = setting.replayer.robot

    def model(values: dict, with_load: bool = True, skip: str | None = None) -> ModelPatch:
        js = [j for j in failing if j != skip]
        p = setting.base_patch.with_effect(effect, js, [values[j] for j in js]) if js else setting.base_patch
        return _with_load(p, load) if with_load else p

    values = {j: v for j in failing}
    fits = {}
    for j in failing:                       # each joint's value with the load and the others in place
        train, _ = setting.sequences(j)
        fits[j] = JointFitter(setting.replayer, j, train, model(values, skip=j)).fit(effect)
        values[j] = fits[j].value
    if any(on_bound(effect, j, f.value, f.ci95, robot) or _is_absent(effect, f.value, j, robot) for j, f in fits.items()):
        return None
    windowed = effect in WINDOWED_EFFECTS           # a set holding a windowed effect is scored on windows
    before = _heldout_mse(setting, setting.base_patch, failing, windowed=windowed)
    after = _heldout_mse(setting, model(values), failing, windowed=windowed)
    no_load = _heldout_mse(setting, model(values, with_load=False), failing, windowed=windowed)
    reds = {j: _reduction(before[j], after[j], setting.noise2(j)) for j in failing}
    felt = [j for j in failing if reds[j] - _reduction(before[j], no_load[j], setting.noise2(j)) >= MIN_EXPLAINED]
    mean = float(np.mean(list(reds.values())))
    every = float(np.mean(list(_every_heldout_reduction(setting, model(values), failing).values())))
    better = mean >= current + tie or (mean >= current - tie and every >= crossed + tie)
    if not better or not felt:
        return None
    cands = {j: Candidate(effect=effect, joint=j, value=f.value, ci95=f.ci95,
                          train_error_reduction=1.0 - f.mse_after / max(f.mse_before, 1e-30),
                          heldout_error_reduction=reds[j], score=reds[j] - COMPLEXITY_PENALTY,
                          scored_by=_scored_by(windowed))
             for j, f in fits.items()}
    load = [dataclasses.replace(c, heldout_error_reduction=mean, scored_by=_scored_by(windowed)) for c in load]
    return cands, load, reds, every


def _every_heldout_reduction(setting: _Setting, patch: ModelPatch, joints: list[str]) -> dict[str, float]:
    """Per joint, the fraction of its excess error ``patch`` removes on every held-out sequence, the other
    joints' too: a joint explained on its own sequences may still err when the joints it carries move (a
    load on the forearm the per-joint fits gave a softness and a torque limit: the shoulder 0.67° off while
    the elbow moves, 0.01° with the load)."""
    held = np.flatnonzero(setting.holdout).astype(np.int64)
    if held.size == 0:
        return dict.fromkeys(joints, 1.0)
    base = setting.replayer.simulate(setting.base_patch, sequences=held)
    sim = setting.replayer.simulate(patch, sequences=held)
    measured = setting.replayer.rec.joint_pos[held]
    out = {}
    for j in joints:
        col = setting.joint_names.index(j)
        out[j] = _reduction(np.mean((base[:, :, col] - measured[:, :, col]) ** 2, axis=1),
                            np.mean((sim[:, :, col] - measured[:, :, col]) ** 2, axis=1), setting.noise2(j))
    return out


def _heavier_links(setting: _Setting, failing: list[str], explained_at: float):
    """Links heavier than the model's: one ``mass_scale`` shared by the links of every failing joint
    (motors, cables and brackets the model leaves out are spread over the arm, which a payload on one
    link does not mimic), fitted to the failing joints' training sequences (bounded Brent; each joint's
    error in units of its noise) with a Gauss–Newton interval: ``([one candidate per failing joint],
    held-out reduction per failing joint)``, or None when the scale sits on a bound or at 1, or explains
    less than :data:`LOAD_FIRST_AT` of the failing joints' held-out excess error on average."""
    rep, robot, base = setting.replayer, setting.replayer.robot, setting.base_patch
    lo, hi = (float(np.max(b)) if k == 0 else float(np.min(b))
              for k, b in enumerate(get_effect("mass_scale").bounds(failing, robot)))
    if not lo < 1.0 < hi:
        return None
    train = {j: setting.sequences(j)[0] for j in failing}
    seqs = np.unique(np.concatenate(list(train.values()))).astype(np.int64)
    rows = {j: np.searchsorted(seqs, t) for j, t in train.items()}
    cols = {j: setting.joint_names.index(j) for j in failing}
    measured = rep.rec.joint_pos[seqs]

    def model(x: float) -> ModelPatch:
        return base.with_effect("mass_scale", failing, [[float(x)]] * len(failing))

    def residual(x: float) -> np.ndarray:
        sim = rep.simulate(model(x), sequences=seqs)
        return np.concatenate([(sim[rows[j], :, cols[j]] - measured[rows[j], :, cols[j]]).ravel()
                               / np.sqrt(setting.noise2(j)) for j in failing])

    r1 = residual(1.0)
    res = minimize_scalar(lambda x: float(np.sum(residual(x) ** 2)), bounds=(lo, hi), method="bounded",
                          options={"xatol": 1e-4, "maxiter": 40})
    x = float(res.x)
    r = residual(x)
    c, c1 = float(r @ r), float(r1 @ r1)
    h = 1e-3 * (hi - lo)
    J = (residual(min(x + h, hi)) - residual(max(x - h, lo))) / (min(x + h, hi) - max(x - h, lo))
    sd = float(np.sqrt(c / max(r.size - 1, 1) / max(float(J @ J), 1e-30)))
    ci = (max(lo, x - 1.96 * sd), min(hi, x + 1.96 * sd))
    if (c >= c1 or any(on_bound("mass_scale", j, x, ci, robot) or _is_absent("mass_scale", x, j, robot)
                       for j in failing)):
        return None
    before = _heldout_mse(setting, base, failing)
    after = _heldout_mse(setting, model(x), failing)
    reds = {j: _reduction(before[j], after[j], setting.noise2(j)) for j in failing}
    red = float(np.mean(list(reds.values())))
    if red < LOAD_FIRST_AT:
        return None
    return [Candidate(effect="mass_scale", joint=j, value=x, ci95=ci, train_error_reduction=1.0 - c / c1,
                      heldout_error_reduction=red, score=red - COMPLEXITY_PENALTY) for j in failing], reds


def _load_first(setting: _Setting, failing: list[str], explained_at: float):
    """One payload on one link that explains the failing joints together, before any joint is fitted:
    ``(candidate, held-out reduction per failing joint)`` or None.

    A mass hung on a link is felt on every joint that carries it (a sag under gravity, more inertia) and,
    as knock-ons, on the joints it moves; fitted joint by joint it becomes a payload here, armature there.
    Every link at or below a failing joint can carry it. Each is screened by one Gauss–Newton step
    (one replay at a small mass gives the residual's sensitivity to the mass, hence a first guess of the
    mass and of the error left) on the errors of every recorded joint, each in units of its noise floor
    (the likelihood): the joints that carry the load weigh by how clearly they feel it, and a joint that
    does not fail tells where the load is not (a mass on the forearm's far link would move the wrist,
    which matches). The screen and the search replay only the two training sequences where each recorded
    joint errs most (a load shows in every sequence: 22 failing joints replay 44 sequences per step, not
    the whole recording). Unless the best step removes :data:`LOAD_SCREEN_AT` of the error, no load is
    searched; else the :data:`LOAD_SHORTLIST` most promising links are (bounded Brent up from the step's
    guess: the response is far from linear in the mass), the best scored on the held-out sequences. It
    is kept if it explains at least :data:`LOAD_FIRST_AT`
    of the failing joints' held-out excess error on average and its value is not on a bound."""
    rep, robot = setting.replayer, setting.replayer.robot
    links = _links_below(setting, failing)
    if not links:
        return None
    base = setting.base_patch

    def objective(train: dict):
        """The residual function on ``train`` (joint -> its sequences), every recorded joint in units of
        its noise, scaled so that the starting patch's squared norm is 1; and that starting residual."""
        seqs = np.unique(np.concatenate(list(train.values()))).astype(np.int64)
        rows = {j: np.searchsorted(seqs, t) for j, t in train.items()}
        cols = {j: setting.joint_names.index(j) for j in train}
        measured = rep.rec.joint_pos[seqs]

        def parts(patch: ModelPatch) -> list[np.ndarray]:
            sim = rep.simulate(patch, sequences=seqs)
            return [(sim[rows[j], :, cols[j]] - measured[rows[j], :, cols[j]]).ravel() for j in train]

        p0 = parts(base)
        w = [1.0 / np.sqrt(p.size * setting.noise2(j)) for j, p in zip(train, p0)]      # in units of its noise
        total = float(np.sqrt(sum(float((p * wi) @ (p * wi)) for p, wi in zip(p0, w))))
        w = [wi / total for wi in w]
        return (lambda patch: np.concatenate([p * wi for p, wi in zip(parts(patch), w)]),
                np.concatenate([p * wi for p, wi in zip(p0, w)]))

    # every recorded joint counts: a load where it does not hang moves joints that do not fail. The
    # screen replays the two training sequences where each joint errs most (every joint on all of them)
    few = np.unique(np.concatenate([_most_telling(setting, j, 2) for j in setting.joint_names])).astype(np.int64)
    residual, r0 = objective({j: few for j in setting.joint_names})
    eff = get_effect("payload_mass")
    screened = []
    for k in links:
        hi = float(eff.bounds([k], robot)[1][0, 0])
        delta = 0.1 * hi
        J = (residual(base.with_effect("payload_mass", [k], [[delta]])) - r0) / delta
        jj = float(J @ J)
        if jj <= 0:
            continue
        mass = float(np.clip(-(J @ r0) / jj, 0.0, hi))
        screened.append((float(np.sum((r0 + mass * J) ** 2)), k, mass, hi))
    screened.sort()
    if not screened or screened[0][0] > 1.0 - LOAD_SCREEN_AT:
        return None        # no link's step explains enough for a load to be worth a search
    residual, _ = objective({j: setting.sequences(j)[0] for j in setting.joint_names})   # the search: all
    found: dict[str, tuple[float, float]] = {}     # link -> (best cost, its mass) of every evaluation

    def cost_at(k: str):
        def cost(x: float) -> float:
            r = residual(base.with_effect("payload_mass", [k], [[float(x)]]))
            c = float(r @ r)
            if c < found.get(k, (np.inf, 0.0))[0]:
                found[k] = (c, float(x))
            return c
        return cost

    his = {}
    for _, k, guess, hi in screened[:LOAD_SHORTLIST]:
        if guess > 1e-3 * hi:     # a wide bracket up from the step's guess, then a narrow one around the best
            his[k] = hi
            minimize_scalar(cost_at(k), bounds=(0.5 * guess, min(hi, 4.0 * guess)), method="bounded",
                            options={"xatol": 0.01 * guess, "maxiter": 10})
    if not found:
        return None
    # where it hangs: mass and offset together on the links searched (a load centimetres from the link's
    # centre of mass has another lever arm; the mass alone takes it for another load, or another link)
    placed = _place_loads(setting, base, {k: found[k][1] for k in sorted(found, key=lambda k: found[k][0])}, robot)
    k = min(placed, key=lambda k: placed[k][0])
    _, x, s, ci, sci = placed[k]
    r = residual(base.with_effect("payload_mass", [k], [[x, s]]))
    c = float(r @ r)
    if c >= 1.0 or on_bound("payload_mass", k, x, ci, robot) or _is_absent("payload_mass", x, k, robot):
        return None
    before = _heldout_mse(setting, base, failing)
    after = _heldout_mse(setting, base.with_effect("payload_mass", [k], [[x, s]]), failing)
    reds = {j: _reduction(before[j], after[j], setting.noise2(j)) for j in failing}
    red = float(np.mean(list(reds.values())))
    if red < LOAD_FIRST_AT:
        return None
    return Candidate(effect="payload_mass", joint=k, value=x, ci95=ci, train_error_reduction=1.0 - c,
                     heldout_error_reduction=red, score=red - COMPLEXITY_PENALTY * len(eff.params),
                     extra=(s,), extra_ci95=(sci,)), reds


def _carried_by_load(setting: _Setting, failing: list[str], cand: Candidate, reds: dict,
                     explained_at: float) -> tuple[list[str], list[str]]:
    """The failing joints a load found on its own carries, and those of them that no longer fail with it.
    Those that no longer fail are its knock-ons (no effect of their own, not scored), those it explains
    to ``explained_at`` (``reds``: held-out reduction per failing joint) are scored on it; the others are
    fitted on top of it. One replay of the failing joints' own sequences."""
    still = _still_failing(setting, failing, _patch_of({cand.joint: [cand]}, setting.base_patch))
    gone = [j for j in failing if j not in still and j != cand.joint]
    return [j for j in failing if j not in still or reds[j] >= explained_at or j == cand.joint], gone


def _carried_text(setting: _Setting, carried: list[str], cand: Candidate, gone: list[str]) -> str:
    """The finding of a load that explains the errors of ``carried`` (``gone``: those that no longer fail)."""
    return (f"{', '.join(carried)}: one {cand.effect} on the link of {cand.joint} "
            f"({_link_names(setting, cand.joint)}; {_load_text(cand)}) explains their errors: it moves with all of them"
            + (f"; {', '.join(gone)} no longer fail with it (knock-ons)." if gone else "."))


def _same_bounds(effect: str, joints: list[str], robot) -> bool:
    """Whether ``effect`` has the same bounds on every joint of ``joints`` (one value can be shared)."""
    b = [tuple(float(v[0, 0]) for v in get_effect(effect).bounds([j], robot)) for j in joints]
    return all(x == b[0] for x in b)


def _adjacent(setting: _Setting, a: str, b: str) -> bool:
    """Whether joints ``a`` and ``b`` move the same link or a link and its parent."""
    m = setting.replayer.model_for(setting.base_patch)[0]
    robot = setting.replayer.robot
    jnt = robot_ids(m, [list(robot.names).index(a), list(robot.names).index(b)])[0]
    ba, bb = (int(m.jnt_bodyid[i]) for i in jnt)
    return ba == bb or int(m.body_parentid[ba]) == bb or int(m.body_parentid[bb]) == ba


def _source_text(cands: list[Candidate], carried: list[str], gone: list[str]) -> str:
    """The finding of sources found first (:func:`_source_first`) that explain the errors of ``carried``."""
    what = " and ".join(f"{c.effect} on {c.joint} ({get_effect(c.effect).param_names[0]} = {c.value:.4g} "
                        f"{get_effect(c.effect).params[0].unit})".replace(" )", ")") for c in cands)
    tail = (f"; {', '.join(gone)} no longer fail{'s' if len(gone) == 1 else ''} with it (knock-ons)."
            if gone else ".")
    return (f"{', '.join(carried)}: {what} explain{'s' if len(cands) == 1 else ''} their errors, found first: "
            f"one source felt on all of them{tail}")


def _load_on_one_joint(setting: _Setting, failing: list[str], selected_per_joint: dict, explained: dict,
                       explained_at: float, tie: float):
    """The load search (:func:`_load_first`) for the one failing joint whose own fit chose a payload or its
    look-alike (armature): ``(candidate, held-out reduction per failing joint, the failing joints that no
    longer fail with it)``, or None.

    The joint-by-joint fit puts a payload's mass at the joint's own link's centre of mass. A load off it
    (5 cm beyond the upper arm's) or on a link below (a finger's, its own joint too lightly loaded to fail)
    needs another mass there, or passes for armature; the search fits mass and place on every link at or
    below the joint against every recorded joint (a joint that does not fail tells where the load is
    not). Its load replaces the joint's selection when every failing joint is carried by it
    (:func:`_carried_by_load`) and it explains the joint's held-out error as well (to ``tie``) as the
    payload chosen there, when it hangs on the same link (the same hypothesis, placed); else by ``tie``
    better: a joint's own armature is not taken for a load that merely matches it, nor a payload on its
    own link moved to a link below that fits the joint's error no better (with the joint alone recorded,
    a load anywhere below it can)."""
    joint = failing[0]
    chosen = [c.effect for c in selected_per_joint.get(joint, [])]
    if not any(e == "payload_mass" or "payload_mass" in get_effect(e).lookalikes for e in chosen):
        return None
    found = _load_first(setting, failing, explained_at)
    if found is None:
        return None
    cand, reds = found
    margin = -tie if "payload_mass" in chosen and cand.joint == joint else tie
    if reds[joint] < explained.get(joint, 0.0) + margin:
        return None
    carried, gone = _carried_by_load(setting, failing, cand, reds, explained_at)
    return (cand, reds, gone) if set(failing) <= set(carried) else None


#: the steps, in the load's mass and in its offset's nominal size, at which each training sequence's error
#: is probed for smoothness before mass and offset are fitted together (:func:`_place_loads`)
LOAD_PROBE = (0.005, 0.25)
#: function evaluations of the least-squares fit of mass and offset per link (each takes 3 replays)
LOAD_FIT_STEPS = 10


def _place_loads(setting: _Setting, base: ModelPatch, masses: dict, robot) -> dict:
    """Mass and offset of ``payload_mass`` fitted together on each link of ``masses`` (joint -> the mass the
    search found at offset 0, best first): ``{joint: (cost, mass, offset, mass ci95, offset ci95)}``.

    A bounded least squares from the searched mass at offset 0, on the search's residual (every recorded
    joint on its training sequences, in units of its noise, the starting patch's cost 1) restricted to the
    sequences whose error is a smooth function of the load: at the two best links, each sequence's error
    is probed at five points along the mass and five along the offset (:data:`LOAD_PROBE`), and one that
    departs from a parabola by more than a tenth of its range (and ranges over more than half the median
    sequence's error) is left out, for every link alike — a shoulder swung fast with the fingertips
    brushing the table, whose error jumps by orders of magnitude for a gram. A Gaussian prior on the
    offset, of the parameter's nominal size, weighs as one joint's sample: nothing where the data tell the
    offset, it holds the offset at 0 where they cannot. Intervals from the Gauss–Newton curvature."""
    from scipy.optimize import least_squares

    rep, eff = setting.replayer, get_effect("payload_mass")
    train = {j: setting.sequences(j)[0] for j in setting.joint_names}
    seqs = np.unique(np.concatenate(list(train.values()))).astype(np.int64)
    T = rep.rec.joint_pos.shape[1]
    w = np.zeros((len(seqs), len(setting.joint_names)))
    for i, j in enumerate(setting.joint_names):
        rows = np.searchsorted(seqs, train[j])
        w[rows, i] = 1.0 / np.sqrt(len(rows) * T * setting.noise2(j))
    measured = rep.rec.joint_pos[seqs]

    def blocks(k, m, o, keep=slice(None)):
        sim = rep.simulate(base.with_effect("payload_mass", [k], [[m, o]]), sequences=seqs[keep])
        return (sim - measured[keep]) * w[keep, None, :]

    total = float(np.sum(((rep.simulate(base, sequences=seqs) - measured) * w[:, None, :]) ** 2))
    w /= np.sqrt(total)
    chaotic = np.zeros(len(seqs), bool)
    steps = np.array([-2.0, -1.0, 0.0, 1.0, 2.0])
    A = np.stack([np.ones(5), steps, steps ** 2], axis=1)
    for k in list(masses)[:2]:
        m0, sigma = masses[k], float(eff.nominal_values([k], robot)[0, 1])
        (mlo, slo), (mhi, shi) = (b[0] for b in eff.bounds([k], robot))
        # the probes stay inside the bounds (a mass searched up to its bound is probed below it)
        dm, do = LOAD_PROBE[0] * m0, min(LOAD_PROBE[1] * sigma, shi / 2.0, -slo / 2.0)
        m0 = float(min(max(m0, mlo + 2.0 * dm), mhi - 2.0 * dm))
        c0 = np.sum(blocks(k, m0, 0.0) ** 2, axis=(1, 2))
        for dm, do in ((dm, 0.0), (0.0, do)):
            Y = np.stack([c0 if i == 0 else np.sum(blocks(k, m0 + i * dm, i * do) ** 2, axis=(1, 2)) for i in steps])
            bent = np.abs(Y - A @ np.linalg.lstsq(A, Y, rcond=None)[0]).max(axis=0)
            span = Y.max(axis=0) - Y.min(axis=0)
            chaotic |= (bent > 0.1 * span + 0.1 * np.median(c0)) & (span > 0.5 * np.median(c0))
    keep = np.flatnonzero(~chaotic)
    prior = np.sqrt(keep.size * T * total)     # one joint's sample, in the cost's units

    out = {}
    for k, m0 in masses.items():
        (mlo, slo), (mhi, shi) = (b[0] for b in eff.bounds([k], robot))
        sigma = float(eff.nominal_values([k], robot)[0, 1])
        scale = np.array([max(m0, 1e-3 * mhi), sigma])

        def fun(y):
            m, o = (float(v) for v in np.asarray(y) * scale)
            return np.append(blocks(k, m, o, keep).ravel(), o / sigma / prior)

        y0 = np.array([min(max(m0, mlo), mhi) / scale[0], 0.0])
        res = least_squares(fun, y0, bounds=(np.array([mlo, slo]) / scale, np.array([mhi, shi]) / scale),
                            diff_step=1e-3, xtol=1e-4, ftol=1e-6, max_nfev=LOAD_FIT_STEPS)
        m, o = res.x * scale
        var = 2.0 * float(res.cost) / max(res.fun.size - 2, 1) * np.linalg.pinv(res.jac.T @ res.jac).diagonal()
        half = 1.96 * np.sqrt(np.maximum(var, 0.0)) * scale
        out[k] = (2.0 * float(res.cost), float(m), float(o),
                  (float(max(mlo, m - half[0])), float(min(mhi, m + half[0]))),
                  (float(max(slo, o - half[1])), float(min(shi, o + half[1]))))
    return out


def _load_text(c: Candidate) -> str:
    """A load's value in words: its mass, and where it hangs."""
    text = f"{c.value:.4g} kg"
    if c.extra:
        text += f" at {100 * c.extra[0]:+.2f} cm from the link's centre of mass along its distal axis"
    return text


def _most_telling(setting: _Setting, joint: str, n: int) -> np.ndarray:
    """The ``n`` training sequences of ``joint`` with its largest error on the starting patch."""
    train = setting.sequences(joint)[0]
    if setting.base_mse is None or train.size <= n:
        return train
    col = setting.joint_names.index(joint)
    return train[np.argsort(-setting.base_mse[train, col])[:n]]


def _links_below(setting: _Setting, joints: list[str]) -> list[str]:
    """The robot's joints (all of its table, recorded or not) whose link is at or below the link of one
    of ``joints``: where a load felt on ``joints`` can hang."""
    m = setting.replayer.model_for(setting.base_patch)[0]
    robot = setting.replayer.robot
    jnt = robot_ids(m, np.arange(robot.num_joints))[0]
    body = dict(zip(robot.names, (int(b) for b in m.jnt_bodyid[jnt])))
    tops = {body[j] for j in joints}
    out = []
    for name, b in body.items():
        while b not in tops and b > 0:
            b = int(m.body_parentid[b])
        if b in tops:
            out.append(name)
    return out


def _link_names(setting: _Setting, joint: str) -> str:
    """The bodies of the link ``joint`` moves (its own and those welded to it), by name."""
    import mujoco

    from adadex.sim.effects import link_bodies

    m = setting.replayer.model_for(setting.base_patch)[0]
    jnt = robot_ids(m, np.arange(setting.replayer.robot.num_joints))[0]
    i = list(setting.replayer.robot.names).index(joint)
    bodies = link_bodies(m, [jnt[i]])[0]
    return ", ".join(mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_BODY, int(b)) or f"body {b}" for b in bodies)


def _single_load_alternative(setting: _Setting, selected_per_joint: dict, explained: dict, tie: float,
                             candidates=EFFECT_NAMES):
    """One payload on one link instead of load-like effects on several joints of a chain, if it explains
    their held-out sequences as well (mean reduction within ``tie``): ``(candidate, affected joints)`` or None.

    A mass on the hand shows as extra inertia and sag on every arm joint that carries it; fitted joint by
    joint it becomes a payload on one joint plus armature on another. The load is tried on each link of the
    unbranched chain below the deepest affected joint, fitted to all affected joints' training sequences
    (each joint's error relative to its own baseline, so that every joint counts alike).
    """
    affected = [j for j, chosen in selected_per_joint.items() if chosen and
                any(c.effect == "payload_mass" or "payload_mass" in get_effect(c.effect).lookalikes for c in chosen)]
    if len(affected) < 2 or "payload_mass" not in candidates:
        return None
    chain = _chain_below(setting, affected)
    if not chain:
        return None
    others = _patch_of({j: c for j, c in selected_per_joint.items() if j not in affected}, setting.base_patch)
    fitters = []
    for j in affected:
        train, held = setting.sequences(j)
        f, hf = JointFitter(setting.replayer, j, train, others), JointFitter(setting.replayer, j, held, others)
        fitters.append((j, f, f.mse(others), hf, hf.mse_per_sequence(others)))
    eff = get_effect("payload_mass")

    def cost(k: str, x: float) -> float:
        p = others.with_effect("payload_mass", [k], [[x]])
        return float(np.mean([f.mse(p) / max(b, 1e-12) for _, f, b, _, _ in fitters]))

    best = None
    for k in chain:
        lo, hi = (float(b[0, 0]) for b in eff.bounds([k], setting.replayer.robot))
        xs = lo + (hi - lo) * np.linspace(0, 1, 9) ** 2
        cs = [cost(k, float(x)) for x in xs]
        i = int(np.argmin(cs))
        res = minimize_scalar(lambda x: cost(k, float(x)), bounds=(xs[max(i - 1, 0)], xs[min(i + 1, 8)]),
                              method="bounded", options={"xatol": 1e-3 * (hi - lo), "maxiter": 30})
        x, c = (float(res.x), float(res.fun)) if res.fun < cs[i] else (float(xs[i]), cs[i])
        if best is None or c < best[2]:
            best = (k, x, c)
    k, x, _ = best
    if _is_absent("payload_mass", x, k, setting.replayer.robot):
        return None
    p = others.with_effect("payload_mass", [k], [[x]])
    reds = [_reduction(hb, hf.mse_per_sequence(p), setting.noise2(j)) for j, _, _, hf, hb in fitters]
    if np.mean(reds) < np.mean([explained[j] for j in affected]) - tie:
        return None
    lo, hi = (float(b[0, 0]) for b in eff.bounds([k], setting.replayer.robot))
    ci = _load_ci95(lambda v: cost(k, v), x, lo, hi)
    red = float(np.mean(reds))
    return Candidate(effect="payload_mass", joint=k, value=x, ci95=ci, train_error_reduction=red,
                     heldout_error_reduction=red, score=red - COMPLEXITY_PENALTY), affected


def _load_ci95(cost, x: float, lo: float, hi: float) -> tuple[float, float]:
    """A rough 95 % interval of a load: where the (relative) cost rises by 10 % of its minimum."""
    c0, h = cost(x), 1e-3 * (hi - lo)
    curv = (cost(min(x + h, hi)) - 2 * c0 + cost(max(x - h, lo))) / h ** 2
    half = float(np.sqrt(0.1 * max(c0, 1e-12) / curv)) if curv > 0 else hi - lo
    return max(lo, x - half), min(hi, x + half)


def _chain_below(setting: _Setting, affected: list[str]) -> list[str]:
    """The recording's joints on the unbranched chain of links from the deepest of ``affected`` down
    (that joint included); empty if ``affected`` are not all on one chain."""
    m = setting.replayer.model_for(setting.base_patch)[0]
    names = list(setting.replayer.rec.joint_names)
    jid = np.asarray(setting.replayer.rec.joint_indices)
    body = {n: int(m.jnt_bodyid[robot_ids(m, [jid[names.index(n)]])[0][0]]) for n in names}

    def ancestors(b: int) -> set[int]:
        out = {b}
        while b > 0:
            b = int(m.body_parentid[b])
            out.add(b)
        return out

    deepest = max(affected, key=lambda j: len(ancestors(body[j])))
    if not all(body[j] in ancestors(body[deepest]) for j in affected):
        return []
    chain, b = [], body[deepest]
    while True:
        chain += [n for n in names if body[n] == b]
        children = np.flatnonzero(m.body_parentid == b)
        children = children[children != b]
        if len(children) != 1:
            return chain
        b = int(children[0])


def _refit_jointly(setting: _Setting, selected_per_joint: dict, passes: int, skip=frozenset(),
                   moves=None) -> None:
    """Refit every selected value with all the other selected effects in place (coordinate descent).

    Effects on one joint change how the others move (a finger that no longer flops changes the load on
    a saturating arm joint), so values fitted joint by joint are refined together. An effect on a joint
    whose effects explained knock-on errors elsewhere (``moves``: joint -> those joints) is refitted, as
    it was chosen, against those joints' errors too (a :class:`~adadex.sysid.fit.CoupledFitter`). Updates
    in place.
    """
    moves = moves or {}
    for _ in range(passes):
        for joint, chosen in selected_per_joint.items():
            for c in ([] if joint in skip else chosen):
                full = _patch_of(selected_per_joint, setting.base_patch)
                others = ModelPatch(effects=tuple(e for e in full.effects
                                                  if not (e.joints == (joint,) and e.effect == c.effect)),
                                    robot=full.robot)   # the model's identity: a user model's joints stay its own
                train, _ = setting.sequences(joint)
                if moves.get(joint):
                    cols = [joint] + list(moves[joint])
                    seqs = np.unique(np.concatenate([setting.sequences(j)[0] for j in cols])).astype(np.int64)
                    r = CoupledFitter(setting.replayer, joint, cols, seqs,
                                      [setting.noise[setting.joint_names.index(j)] for j in cols],
                                      others).fit(c.effect, xtol_frac=COUPLED_XTOL, maxiter=100)
                else:
                    r = JointFitter(setting.replayer, joint, train, others).fit(c.effect)
                c.value, c.ci95 = r.value, r.ci95


def _heldout_mse(setting: _Setting, patch: ModelPatch, joints, windowed: bool = False) -> dict[str, np.ndarray]:
    """Per joint of ``joints``, the MSE of each of its held-out sequences under ``patch`` (one replay):
    free-replay, or (``windowed``) the windowed cost of each (a multiple-shooting replay; each joint's
    windows trimmed as :meth:`~adadex.sysid.fit.JointFitter.window_mse_per_sequence` trims them)."""
    held = {j: setting.scored(j).astype(np.int64) for j in joints}
    seqs = np.unique(np.concatenate(list(held.values())))
    L = window_length(setting.replayer.rec.dt)
    sim = (setting.replayer.simulate_windows(patch, length=L, sequences=seqs) if windowed
           else setting.replayer.simulate(patch, sequences=seqs))
    measured = setting.replayer.rec.joint_pos[seqs]
    out = {}
    for j, h in held.items():
        col, rows = setting.joint_names.index(j), np.searchsorted(seqs, h)
        e = sim[rows, :, col] - measured[rows, :, col]
        out[j] = (window_mse_per_sequence(window_rows(e[..., None], L), len(rows)) if windowed
                  else np.mean(e ** 2, axis=1))
    return out


def on_bound(effect: str, joint: str, value: float, ci95, robot=None) -> bool:
    """Whether the value or its 95 % interval reaches a bound of the effect other than its absent value:
    the data want more than the library allows, or cannot say how much (damping pinned at its
    largest value, a mass at its limit)."""
    eff = get_effect(effect)
    lo, hi = (float(b[0, 0]) for b in eff.bounds([joint], robot))
    absent, tol = float(eff.absent_values()[0]), 1e-3 * (hi - lo)
    a, b = min(ci95[0], value), max(ci95[1], value)
    return (b >= hi - tol and absent != hi) or (a <= lo + tol and absent != lo)


def _suggestion(c: Candidate, robot) -> dict:
    """A value that sits on a bound, as a suggestion with the excitation that would identify it."""
    eff = get_effect(c.effect)
    model = "" if robot is None or robot.builtin or robot.path is None else f" --model {robot.path}"
    command = f"adadex sysid excite --joints {c.joint} {EXCITATION_FOR.get(c.effect, '')}".rstrip() + model
    unit = eff.params[0].unit
    finding = (f"Suggestion, not selected: {c.effect} on {c.joint} ({eff.param_names[0]} = {c.value:.4g} {unit}) "
               f"sits on a bound of what the library allows (95% interval [{c.ci95[0]:.3g}, {c.ci95[1]:.3g}] "
               f"{unit}); this recording cannot pin it down. To identify it run `{command}`.")
    return {"effect": c.effect, "joints": [c.joint], "params": {eff.param_names[0]: [c.value]},
            "ci95": {eff.param_names[0]: [list(c.ci95)]}, "unit": unit, "excite": command, "finding": finding}


def _prune(setting: _Setting, selected_per_joint: dict, carried: dict, moves: dict, failing) -> tuple[list, list]:
    """The selection rule, applied to the effects chosen (in place): a value at its absent value is
    dropped; a value on a bound (:func:`on_bound`) becomes a suggestion; then, weakest first, an effect
    is dropped while it explains less than :data:`MIN_EXPLAINED` of its joints' held-out excess error
    beyond what all the other selected effects explain. Its joints: the joint it is on and the failing
    joints its source explained as knock-ons (``moves``), or, for a single load, the joints it carries
    (``carried``). Returns (suggestions, the removed ``(joint, candidate)`` pairs)."""
    robot = setting.replayer.robot
    suggestions, removed = [], []
    for joint, chosen in selected_per_joint.items():
        for c in list(chosen):
            if _is_absent(c.effect, c.value, joint, robot):
                chosen.remove(c)
                removed.append((joint, c))
            elif on_bound(c.effect, joint, c.value, c.ci95, robot):
                chosen.remove(c)
                removed.append((joint, c))
                suggestions.append(_suggestion(c, robot))

    def its_joints(joint: str) -> list[str]:
        own = carried.get(joint) or [joint, *moves.get(joint, ())]
        return [j for j in dict.fromkeys(own) if j in failing] or [joint]

    items = [(j, c) for j, chosen in selected_per_joint.items() for c in chosen]
    if not items:
        return suggestions, removed
    scored = sorted({k for j, _ in items for k in its_joints(j)})
    # by cost (False: free replay; True: windowed, for an effect on a joint whose set holds a windowed one)
    before = {False: _heldout_mse(setting, setting.base_patch, scored)}
    while items:
        full_patch = _patch_of(selected_per_joint, setting.base_patch)
        full = {False: _heldout_mse(setting, full_patch, scored)}
        margins = []
        for joint, c in items:
            w = _windowed(selected_per_joint[joint])
            if w and w not in before:
                before[w] = _heldout_mse(setting, setting.base_patch, scored, windowed=True)
            if w and w not in full:
                full[w] = _heldout_mse(setting, full_patch, scored, windowed=True)
            without = {j: [x for x in chosen if x is not c] for j, chosen in selected_per_joint.items()}
            js = its_joints(joint)
            less = _heldout_mse(setting, _patch_of(without, setting.base_patch), js, windowed=w)
            margins.append(float(np.mean([_reduction(before[w][k], full[w][k], setting.noise2(k))
                                          - _reduction(before[w][k], less[k], setting.noise2(k)) for k in js])))
        i = int(np.argmin(margins))
        if margins[i] >= MIN_EXPLAINED:
            break
        joint, c = items.pop(i)
        selected_per_joint[joint].remove(c)
        removed.append((joint, c))
    return suggestions, removed


def _score_jointly(setting: _Setting, selected_per_joint: dict, carried=None) -> dict[str, float]:
    """Each joint's held-out excess-error reduction with all selected effects in place; also stored on
    the joint's last chosen candidate. A load in ``carried`` (joint -> the joints it explains) is scored
    by the mean over the joints it explains."""
    full = _patch_of(selected_per_joint, setting.base_patch)
    explained = {}
    carried = carried or {}
    for joint, chosen in selected_per_joint.items():
        if joint not in setting.joint_names:     # a load on a link whose joint is not recorded
            continue
        held = setting.scored(joint)
        hf = JointFitter(setting.replayer, joint, held, setting.base_patch)
        # a joint carried by a source scored on windows (a chaotic one) is scored on windows too
        windowed = _windowed(chosen) or _windowed([c for k, aff in carried.items() if joint in aff
                                                   for c in selected_per_joint.get(k, [])])
        mse = hf.window_mse_per_sequence if windowed else hf.mse_per_sequence
        explained[joint] = _reduction(mse(setting.base_patch), mse(full), setting.noise2(joint))
        if chosen:
            chosen[-1].heldout_error_reduction = explained[joint]
            chosen[-1].scored_by = _scored_by(windowed)
    for joint, chosen in selected_per_joint.items():     # a load or source: the mean over the joints it carries
        if joint in carried and chosen:
            chosen[-1].heldout_error_reduction = float(np.mean([explained[j] for j in carried[joint]
                                                                if j in explained]))
    return explained


def _hypotheses(first_rounds: dict, selected_per_joint: dict, train_only=lambda joint: False,
                robot=None) -> list[dict]:
    """Every first-round candidate of every joint that explains at least :data:`MIN_EXPLAINED` of its
    held-out excess error (training error, on a joint ``train_only`` says has no held-out sequences) as a
    hypothesis, best score first; each joint's best carries its look-alike alternatives."""
    hypotheses = []
    for joint, cands in first_rounds.items():
        for c in cands:
            if (max(c.heldout_error_reduction, c.train_error_reduction if train_only(joint) else -1.0) < MIN_EXPLAINED
                    or _is_absent(c.effect, c.value, joint, robot)):
                continue      # explains (next to) nothing, or refined to its absent value: not stored
            names = get_effect(c.effect).param_names
            hypotheses.append({"effect": c.effect, "joints": [joint],
                               "params": {n: [v] for n, v in zip(names, c.values)},
                               "ci95": {n: [list(ci)] for n, ci in zip(names, [c.ci95, *c.extra_ci95])},
                               "train_error_reduction": max(0.0, c.train_error_reduction),
                               "heldout_error_reduction": max(0.0, c.heldout_error_reduction),
                               "score": c.score, "alternatives": [], "scored_by": c.scored_by})
    hypotheses.sort(key=lambda h: -h["score"])
    for joint, chosen in selected_per_joint.items():
        if chosen:
            for h in hypotheses:
                if h["joints"] == [joint] and h["effect"] == chosen[0].effect:
                    h["alternatives"] = chosen[0].alternatives
                    break
    return hypotheses


def _merge_over_joints(selected_per_joint: dict, robot=None) -> list[dict]:
    """The selected effects, one entry per effect over all the joints it was selected on, each
    value flagged ``identifiable`` (see :func:`identifiable`) with its unit."""
    merged: dict[str, dict] = {}
    for joint, chosen in selected_per_joint.items():
        for c in chosen:
            names = get_effect(c.effect).param_names
            h = merged.setdefault(c.effect, {"effect": c.effect, "joints": [], "params": {},
                                             "ci95": {}, "heldout_error_reduction": [],
                                             "alternatives": [], "identifiable": [], "scored_by": [],
                                             "unit": get_effect(c.effect).params[0].unit})
            h["identifiable"].append(identifiable(c.effect, joint, c.ci95, robot))
            h["joints"].append(joint)
            absent = get_effect(c.effect).absent_values()
            for i, n in enumerate(names):
                if i < len(c.values) or n in h["params"]:
                    prev = len(h["joints"]) - 1 - len(h["params"].get(n, []))
                    h["params"].setdefault(n, [float(absent[i])] * prev).append(
                        c.values[i] if i < len(c.values) else float(absent[i]))
                    cis = [c.ci95, *c.extra_ci95]
                    h["ci95"].setdefault(n, [[float(absent[i])] * 2] * prev).append(
                        list(cis[i]) if i < len(cis) else [float(absent[i])] * 2)
            h["heldout_error_reduction"].append(max(0.0, c.heldout_error_reduction))
            h["scored_by"].append(c.scored_by)
            h["alternatives"] = sorted(set(h["alternatives"]) | set(c.alternatives))
    return list(merged.values())


#: The excitation that pins each effect down, as ``adadex sysid excite`` options.
EXCITATION_FOR = {
    "coulomb_friction": "--freqs 0.25,0.5 --amps 0.1,0.3", "backlash": "--freqs 0.25,0.5 --amps 0.05,0.2",
    "damping": "--freqs 1,3,5 --amps 0.5,1", "kd_scale": "--freqs 1,3,5 --amps 0.5,1",
    "armature": "--freqs 3,5 --amps 0.5,1 --kinds chirp,multisine",
    "payload_mass": "--freqs 0.5,3 --amps 1 --poses loaded,unloaded",
    "actuator_delay": "--freqs 2,4,6 --kinds sine,chirp", "actuator_lag": "--freqs 0.5,2,5 --kinds sine,chirp",
    "torque_limit": "--freqs 2,4 --amps 1", "kp_scale": "--freqs 0.5,3 --amps 0.3,1 --poses loaded,unloaded",
    "joint_spring": "--freqs 0.25 --amps 0.3,1 --poses loaded,unloaded", "encoder_offset": "--freqs 0.5 --amps 0.3",
}


def identifiable(effect: str, joint: str, ci95, robot=None) -> bool:
    """False when the data cannot pin the parameter down: its 95 % interval reaches a bound or spans
    half of the bounds (a flat error)."""
    lo, hi = (float(b[0, 0]) for b in get_effect(effect).bounds([joint], robot))
    a, b = ci95
    w = hi - lo
    return not (b - a >= 0.5 * w or a <= lo + 1e-3 * w and effect_at(effect, a) or b >= hi - 1e-3 * w)


def effect_at(effect: str, value: float) -> bool:
    """Whether an interval's lower end at ``value`` is informative (not the absent value itself)."""
    return value != float(get_effect(effect).absent_values()[0])


def _describe(c: Candidate, robot) -> str:
    eff = get_effect(c.effect)
    text = f"{c.effect} ({eff.param_names[0]} = {c.value:.4g} {eff.params[0].unit}"
    text += "".join(f", {p.name} = {v:.4g} {p.unit}" for p, v in zip(eff.params[1:], c.extra)) + ")"
    if not identifiable(c.effect, c.joint, c.ci95, robot):
        text = (f"{c.effect} (not identifiable from this recording: its 95% interval "
                f"[{c.ci95[0]:.3g}, {c.ci95[1]:.3g}] {eff.params[0].unit} reaches the bounds; to identify it run "
                f"`adadex sysid excite --joints {c.joint} {EXCITATION_FOR.get(c.effect, '')}`)")
    return text


def _verdict(explained: dict, selected_per_joint: dict, explained_at: float,
             robot=None, train_only=()) -> tuple[str, list[str]]:
    """``explained`` or ``unexplained``, and one finding per joint (plus one naming the unexplained joints)."""
    verdict = "explained" if all(v >= explained_at for v in explained.values()) else "unexplained"
    findings = []
    for joint, v in explained.items():
        chosen = selected_per_joint[joint]
        # an effect that explains (next to) nothing of this joint is not printed as its explanation
        what = (" + ".join(_describe(c, robot) for c in chosen) if v >= MIN_EXPLAINED else "") or "nothing"
        on = "training (no sequence held out)" if joint in train_only else "held-out"
        how = (f" (scored on {WINDOW_S:g}-s windows restarted from the measured positions: a free replay of "
               f"{'friction' if not any(getattr(c, 'chaotic', False) for c in chosen) else chosen[0].effect} "
               "is chaotic)" if _windowed(chosen) else "")
        findings.append(f"{joint}: {what} explains {100 * v:.0f}% of the {on} error above the noise floor{how}.")
    if verdict == "unexplained":
        weak = [j for j, v in explained.items() if v < explained_at]
        findings.append(f"Unexplained: on {', '.join(weak)} the best candidates explain less than "
                        f"{100 * explained_at:.0f}% of the excess error; an effect outside the library may be at work.")
    return verdict, findings
