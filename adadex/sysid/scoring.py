"""What every step of a diagnosis (:mod:`adadex.sysid.diagnose`) shares: its setting, its candidates, its scores.

:class:`_Setting` is what every step reads (the replayer, the starting patch, the noise floors, which sequences
train and which score each joint) and :class:`Candidate` one effect fitted on one joint. The scores: the
fraction of a joint's excess error a model removes on its held-out sequences (:func:`_reduction`, of the free
replay's or the windowed cost's MSE, :func:`_heldout_mse`), whether a joint still fails
(:func:`_still_failing`: :func:`~adadex.sysid.compare.localize`'s test), and what a fitted value says: at its
absent value (:func:`_is_absent`), on a bound (:func:`on_bound`), not identifiable (:func:`identifiable`, with
the excitation that would pin it down, :data:`EXCITATION_FOR`). The steps — :mod:`~adadex.sysid.load_search`,
:mod:`~adadex.sysid.source_first` and :mod:`~adadex.sysid.joint_selection` — import from here and not from each
other; :mod:`adadex.sysid.diagnose` runs them and re-exports the public names.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from adadex.sim.effects import get_effect
from adadex.sim.patch import ModelPatch
from adadex.sysid.compare import FAIL_ABS, FAIL_RATIO
from adadex.sysid.fit import WINDOWED_EFFECTS, window_length, window_mse_per_sequence, window_rows
from adadex.sysid.replay import Replayer

COMPLEXITY_PENALTY = 0.02
#: Brent's tolerance (fraction of the bounds) when a candidate is fitted to the joints it may move too:
#: a knock-on error can hang on the 6th digit of a torque limit (tests/sysid/test_coupled.py).
COUPLED_XTOL = 1e-7
#: A selected effect must explain at least this fraction of its joints' held-out excess error beyond what
#: the other selected effects explain (see :func:`~adadex.sysid.joint_selection._prune`); a hypothesis
#: explaining less is not stored.
MIN_EXPLAINED = 0.05


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
    :data:`~adadex.sysid.fit.WINDOWED_EFFECTS` (see :mod:`adadex.sysid.diagnose`'s docstring)."""
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


def _fails(setting: _Setting, joint: str, rms: float) -> bool:
    """:func:`~adadex.sysid.compare.localize`'s test: an RMS error (rad) above :data:`FAIL_RATIO` × the
    joint's noise floor and above :data:`FAIL_ABS`."""
    col = setting.joint_names.index(joint)
    return rms / max(float(setting.noise[col]), 1e-6) > FAIL_RATIO and rms > FAIL_ABS


def _own_sequences(setting: _Setting, joint: str) -> np.ndarray:
    """The sequences ``joint`` is localized on: its own, or all when none excites it (as localize)."""
    own = np.unique(np.concatenate(setting.sequences(joint))).astype(np.int64)
    return own if own.size else np.arange(len(setting.seq_meta), dtype=np.int64)


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


def _most_telling(setting: _Setting, joint: str, n: int) -> np.ndarray:
    """The ``n`` training sequences of ``joint`` with its largest error on the starting patch."""
    train = setting.sequences(joint)[0]
    if setting.base_mse is None or train.size <= n:
        return train
    col = setting.joint_names.index(joint)
    return train[np.argsort(-setting.base_mse[train, col])[:n]]


def _is_absent(name: str, value: float, joint: str, robot) -> bool:
    """Whether ``value`` is (within 0.1 % of the bounds' width of) the effect's absent value."""
    eff = get_effect(name)
    lo, hi = (float(b[0, 0]) for b in eff.bounds([joint], robot))
    return abs(value - float(eff.absent_values()[0])) <= 1e-3 * (hi - lo)


def on_bound(effect: str, joint: str, value: float, ci95, robot=None) -> bool:
    """Whether the value or its 95 % interval reaches a bound of the effect other than its absent value:
    the data want more than the library allows, or cannot say how much (damping pinned at its
    largest value, a mass at its limit)."""
    eff = get_effect(effect)
    lo, hi = (float(b[0, 0]) for b in eff.bounds([joint], robot))
    absent, tol = float(eff.absent_values()[0]), 1e-3 * (hi - lo)
    a, b = min(ci95[0], value), max(ci95[1], value)
    return (b >= hi - tol and absent != hi) or (a <= lo + tol and absent != lo)


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
