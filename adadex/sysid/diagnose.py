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
recorded joint's error in units of its noise, the :data:`~adadex.sysid.load_search.LOAD_SHORTLIST` best
searched when a step removes :data:`~adadex.sysid.load_search.LOAD_SCREEN_AT` of it
(:func:`~adadex.sysid.load_search._load_first`) — and kept when it explains most of the failing joints'
held-out error (:data:`~adadex.sysid.load_search.LOAD_FIRST_AT`); the joints it explains are its knock-ons, and
only the others are then fitted joint by joint (a 0.6 kg mass on the palm is one ``payload_mass`` on the
palm's link, not a payload on the shoulder, armature on the elbow and 13 finger hypotheses).
A source first, when no load is: with :data:`~adadex.sysid.source_first.SOURCE_MIN_FAILING` failing joints or
more, one library effect on one joint, or with one value on two joints of adjacent links, is screened on every
recorded joint's error at once before any joint is fitted (:func:`~adadex.sysid.source_first._source_first`: a
few grid points per candidate, one replay each of the sequence where each failing joint errs most, on the worst
joints and on those whose imposed motion moves the rest), fitted when it halves the failing joints' error on
average, a further source added while it lowers that clearly, and kept when together they explain
:data:`~adadex.sysid.source_first.SOURCE_FIRST_AT` of the failing joints' held-out error; the joints they
explain are their knock-ons, as a load's (a shoulder too weak to hold the arm, torque limit 0.3 on arm_j2 and
arm_j3, fails 20 of 22 joints: one torque limit on the two, not an effect on each;
``benchmarks/sysid_diagnosis.py --worst``). Near a limit the arm barely holds, the free replay is chaotic in the
value (1e-4 off the truth, a thousand times the noise): when it leaves a failing joint unexplained, the sources
are refitted and scored on the windowed cost, with the joints they carry (:attr:`Candidate.chaotic`), and that
is kept when it explains more.
With one failing joint the search runs once that joint's own fit has chosen a payload or armature, its
look-alike (:func:`~adadex.sysid.load_search._load_on_one_joint`): the joint-by-joint fit hangs the mass at its
own link's centre of mass, while the load may hang off it or on a link below (a mass 5 cm beyond the upper arm's
centre of mass came out 64 % heavy there; one at a finger's centre of mass, felt only on the shoulder, as
armature plus a payload on the shoulder); the search's load, in mass and place, replaces that selection when it
explains the joint's held-out error as well as a payload chosen on the same link, or clearly better than
armature or a payload on the joint's own link.

A joint with too few sequences to hold any out (fewer than three of its own) is scored on its
training sequences only: the diagnosis lists it in ``train_only_joints``, says so in its findings,
marks its hypotheses ``"scored_on": "train"`` and gives them no held-out figure
(``heldout_error_reduction`` is ``None``).

Coupled joints: the failing joints are fitted worst first (error over noise), and after each joint's
effects are chosen the rest are localized again on the model with those effects; a joint that no
longer fails had only a knock-on error (the joint that moves it was the source) and gets no effect of
its own (re-localization replays only the still-pending joints' sequences). Before a joint is fitted, and
when other failing joints are left, one replay tells whether its failure is a knock-on of theirs whatever
moves them (:func:`~adadex.sysid.joint_selection._follows`): its own sequences are replayed with those joints
moving exactly as measured (:meth:`~adadex.sysid.replay.Replayer.simulate_imposed`: each a flywheel driven along
its measurement, so it feels their measured motion through the model's coupled dynamics); if it no longer fails,
it gets no effect of its own and is reported as a knock-on of the joints it follows (those that suffice alone),
and of their error when that is unexplained. A drag outside the library on the elbow shakes the holding
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
shoulder plus armature on the elbow). Softer servos carrying a load
(:func:`~adadex.sysid.load_search._shared_effect_and_load`): when the failing joints of one chain are not
yet explained and one effect was chosen on several of them, that effect on all of them with a load on top
replaces the selection if it explains the held-out error better (kp × 0.3 on six arm joints and 2 kg at the
palm, joint by joint kp here, damping, friction and kd there, are one softness and one payload). The load is
a payload screened on one link, or links heavier than the model's — one ``mass_scale`` shared by every
failing joint's links (motors, cables), which no payload on one link mimics — whichever explains more. The
step also runs, and its pair is kept when it explains as much on each joint's own sequences and more on
every held-out sequence, when the joint-by-joint selection explains each joint's own sequences but not the
others' (a softness and a torque limit on a shoulder that sags only while the elbow carries a load). A
candidate fitted at (or within 0.1 % of the bounds of) its absent value explains nothing and is dropped;
explained fractions are reported clipped at 0. A selected value whose 95 % interval spans half of its bounds
is reported as not identifiable from the recording, with the ``adadex sysid excite`` command whose
excitation would pin it down (:data:`EXCITATION_FOR`); one that reaches a bound is not selected at all
(below).

No spurious effect: after the joint refit every selected effect must explain at least
:data:`MIN_EXPLAINED` of its joints' held-out excess error beyond what all the other selected effects
explain (its joint, and the knock-on joints its source explained; weakest dropped first,
:func:`~adadex.sysid.joint_selection._prune`); an effect at its absent value is dropped; a value on a bound of
the library (:func:`on_bound`: damping at its largest value) is not selected but reported in ``suggestions``, with
the ``adadex sysid excite`` command that would identify it. A hypothesis explaining under
:data:`MIN_EXPLAINED` is not stored.

Verdicts: ``nothing_missing`` (no joint's error is above its noise floor), ``explained`` (every
failing joint's held-out excess error falls by at least ``explained_at``), ``unexplained`` (the
best candidates explain too little; the report says how much). A knock-on of other failing joints
(:func:`~adadex.sysid.joint_selection._follows`) is judged with them: on what their effects explain of its own
error when they are explained, not at all (its finding says whose unexplained error it is) when they are not.

The code: :func:`diagnose` (here) runs the steps and words the result (the hypotheses, the selected effects,
the verdict); the steps are in :mod:`~adadex.sysid.load_search` (a load first, on one joint, shared with an
effect, or instead of load-like effects), :mod:`~adadex.sysid.source_first` (a source first) and
:mod:`~adadex.sysid.joint_selection` (the knock-on check, the forward selection of each joint, the joint refit,
the selection rule and the joint scoring), and what they share — the setting of a run, :class:`Candidate`, the
held-out scores, the bounds and identifiability of a value — in :mod:`~adadex.sysid.scoring`.
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from adadex.errors import AdadexError
from adadex.io import atomic_write_text
from adadex.progress import progress_bar
from adadex.sim.effects import EFFECT_NAMES, get_effect
from adadex.sim.patch import EffectInstance, ModelPatch
from adadex.sysid import source_first
from adadex.sysid.compare import compare, heldout_mask, localize, noise_floor
from adadex.sysid.fit import WINDOW_S
from adadex.sysid.joint_selection import _follows, _forward_selection, _prune, _refit_jointly, _score_jointly
from adadex.sysid.load_search import (_carried_by_load, _carried_text, _link_names, _load_first, _load_on_one_joint,
                                      _load_text, _shared_effect_and_load, _single_load_alternative)
from adadex.sysid.replay import Replayer
from adadex.sysid.scoring import (EXCITATION_FOR, MIN_EXPLAINED, Candidate, _is_absent, _patch_of, _reduction,
                                  _Setting, _still_failing, _windowed, effect_at, identifiable, on_bound)
from adadex.sysid.source_first import _source_first, _source_text

# The diagnosis and its public helpers (defined with the scores in adadex.sysid.scoring), and _reduction,
# the score tests recompute: all imported from here.
__all__ = ["diagnose", "Diagnosis", "DiagnosisError", "Candidate", "MIN_EXPLAINED", "EXCITATION_FOR", "on_bound",
           "identifiable", "effect_at", "_reduction"]


class DiagnosisError(AdadexError, ValueError):
    """A diagnosis file that cannot be read."""


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
    # A source first: one effect (or a few) felt on most failing joints (a shoulder that cannot hold the arm);
    # the threshold is read from its module at each call (a test lowers it there)
    source = (_source_first(setting, failing, explained_at, candidates)
              if joints is None and load is None and len(failing) >= source_first.SOURCE_MIN_FAILING else None)
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
    """The finding of a joint whose failure is a knock-on of the failing joints ``lead``
    (:func:`~adadex.sysid.joint_selection._follows`)."""
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
