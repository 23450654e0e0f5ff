"""Which physical effect is missing? Fit candidates where the model fails, rank them on held-out data.

For every failing joint (see :func:`~adadex.sysid.compare.localize`) the joint's sequences are
split into training and held-out sets (every third sequence is held out). Every candidate effect is
screened on a coarse parameter grid on the training set; the ``refine_top`` most promising are
fitted precisely (:mod:`adadex.sysid.fit`). Each is scored on the held-out set by the
fraction of the *excess* error it removes — the part of the mean squared error above the sensor
noise floor, which no model can remove — averaged over the held-out sequences that have excess
error, so that every regime counts alike:

    reduction = mean over sequences of 1 − (MSE_after − σ²) / (MSE_before − σ²)

Candidates are ranked by held-out reduction minus a complexity penalty per parameter. Forward
selection then adds further effects on the same joint while each adds at least
``min_gain`` of held-out reduction. Candidates whose held-out reduction is within ``tie`` of the
best are reported as alternatives of one hypothesis (on a position servo, viscous ``damping`` and
``kd_scale`` are such a pair). The same effect selected on several joints becomes one hypothesis
over those joints.

Verdicts: ``nothing_missing`` (no joint's error is above its noise floor), ``explained`` (every
failing joint's held-out excess error falls by at least ``explained_at``), ``unexplained`` (the
best candidates explain too little; the report says how much).
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from tqdm import tqdm

from adadex.io import atomic_write_text
from adadex.sim.effects import EFFECT_NAMES, get_effect
from adadex.sim.patch import ModelPatch
from adadex.sysid.compare import compare, heldout_mask, localize, noise_floor
from adadex.sysid.fit import JointFitter
from adadex.sysid.replay import Replayer

COMPLEXITY_PENALTY = 0.02


@dataclass
class Candidate:
    effect: str
    joint: str
    value: float
    ci95: tuple[float, float]
    train_error_reduction: float
    heldout_error_reduction: float
    score: float
    alternatives: list[str] = field(default_factory=list)


@dataclass
class Diagnosis:
    verdict: str
    baseline_error: dict
    hypotheses: list[dict]
    selected: list[dict]
    explained_fraction: dict
    findings: list[str]
    wall_time_s: float

    def patch(self) -> ModelPatch:
        """The selected effects as a model patch."""
        p = ModelPatch()
        for h in self.selected:
            p = p.with_effect(h["effect"], h["joints"], np.array(h["params"][get_effect(h["effect"]).param_names[0]])[:, None])
        return p

    def to_dict(self) -> dict:
        return {"verdict": self.verdict, "baseline_error": self.baseline_error, "hypotheses": self.hypotheses,
                "selected": self.selected, "explained_fraction": self.explained_fraction,
                "findings": self.findings, "wall_time_s": self.wall_time_s}

    def save(self, directory) -> Path:
        return atomic_write_text(Path(directory) / "diagnosis.json", json.dumps(self.to_dict(), indent=2))

    @classmethod
    def load(cls, directory_or_file) -> "Diagnosis":
        p = Path(directory_or_file)
        p = p / "diagnosis.json" if p.is_dir() else p
        return cls(**json.loads(p.read_text()))


def _split(seqs: np.ndarray, mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    held, train = seqs[mask[seqs]], seqs[~mask[seqs]]
    if held.size == 0:  # too few sequences: score on the training set
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


def _patch_of(selected_per_joint: dict, base: ModelPatch) -> ModelPatch:
    p = base
    for joint, chosen in selected_per_joint.items():
        for c in chosen:
            p = p.with_effect(c.effect, [joint], [[c.value]])
    return p


def diagnose(recording, *, base_patch: ModelPatch | None = None, candidates=EFFECT_NAMES,
             joints=None, max_effects_per_joint: int = 2, min_gain: float = 0.1, tie: float = 0.03,
             explained_at: float = 0.8, refine_top: int = 4, refine_passes: int = 1, nthread: int = 2,
             progress: bool = True) -> Diagnosis:
    """Diagnose ``recording``; see the module docstring. ``joints`` overrides the failing-joint search."""
    t0 = time.perf_counter()
    base_patch = base_patch if base_patch is not None else ModelPatch()
    rep = Replayer(recording, nthread=nthread)
    cmp = compare(recording, base_patch, replayer=rep)
    loc = localize(cmp)
    names = list(recording.joint_names)
    noise = noise_floor(recording.joint_pos)
    baseline = {"overall_rms_rad": float(cmp.rms()),
                "per_joint_rms_rad": dict(zip(names, map(float, cmp.rms_per_joint()))),
                "noise_floor_rad": dict(zip(names, map(float, noise)))}
    failing = list(joints) if joints is not None else loc.failing_joints
    findings = list(loc.sentences)
    if not failing:
        return Diagnosis("nothing_missing", baseline, [], [], {}, findings, time.perf_counter() - t0)

    seq_meta = list(recording.meta.get("sequences") or [{} for _ in range(recording.num_sequences)])
    holdout = heldout_mask(recording)
    per_joint: dict[str, list[Candidate]] = {}
    selected_per_joint: dict[str, list[Candidate]] = {}
    explained: dict[str, float] = {}
    work = [(j, c) for j in failing for c in candidates]
    bar = tqdm(total=len(work), desc="diagnosing", unit="fit", disable=not progress)
    for joint in failing:
        own = np.array([i for i, s in enumerate(seq_meta) if s.get("joint", joint) == joint])
        train, held = _split(own, holdout)
        n2 = float(noise[names.index(joint)] ** 2)
        chosen: list[Candidate] = []
        patch = base_patch
        held_fitter = JointFitter(rep, joint, held, patch)
        held_before = held_fitter.mse_per_sequence(patch)
        first_round: list[Candidate] = []
        for round_ in range(max_effects_per_joint):
            fitter = JointFitter(rep, joint, train, patch)
            held_fitter = JointFitter(rep, joint, held, patch)
            cur_held = held_fitter.mse_per_sequence(patch)
            cands = []
            names_left = [n for n in candidates if not any(c.effect == n for c in chosen)]
            train_before = fitter.mse(patch)
            # Screen every candidate on a coarse grid; refine only the most promising ones.
            grids = {n: fitter.grid(n) for n in names_left}
            ranked = sorted(names_left, key=lambda n: grids[n][1].min())
            for k, name in enumerate(ranked):
                if k < refine_top:
                    r = fitter.fit(name, grid=grids[name], mse_before=train_before)
                    value, ci, after = r.value, r.ci95, r.mse_after
                else:
                    i = int(np.argmin(grids[name][1]))
                    value, after = float(grids[name][0][i]), float(grids[name][1][i])
                    eff = get_effect(name)
                    ci = tuple(float(b[0, 0]) for b in eff.bounds([joint]))
                held_after = held_fitter.mse_per_sequence(fitter.patch_with(name, value))
                red_tr = _reduction(train_before, after, n2)
                red_ho = _reduction(held_before, held_after, n2)
                gain = red_ho - _reduction(held_before, cur_held, n2)
                cands.append(Candidate(name, joint, value, ci, red_tr, red_ho,
                                       gain - COMPLEXITY_PENALTY * len(get_effect(name).params)))
                if round_ == 0:
                    bar.update(1)
            cands.sort(key=lambda c: -c.score)
            if round_ == 0:
                first_round = cands
            if not cands or cands[0].score < (min_gain if chosen else 0.0):
                break
            best = cands[0]
            best.alternatives = [c.effect for c in cands[1:] if best.heldout_error_reduction - c.heldout_error_reduction < tie
                                 or c.effect in get_effect(best.effect).lookalikes and
                                 best.heldout_error_reduction - c.heldout_error_reduction < 3 * tie]
            chosen.append(best)
            patch = patch.with_effect(best.effect, [joint], [[best.value]])
            if best.heldout_error_reduction >= 0.98:
                break
        per_joint[joint] = first_round
        selected_per_joint[joint] = chosen
        explained[joint] = chosen[-1].heldout_error_reduction if chosen else 0.0
    bar.close()

    # Effects on one joint change how the others move (a finger that no longer flops changes the
    # load on a saturating arm joint), so refit every selected value with all the other selected
    # effects in place — a coordinate-descent pass — and score the joints again.
    if sum(len(c) for c in selected_per_joint.values()) > 1:
        for _ in range(refine_passes):
            for joint, chosen in selected_per_joint.items():
                for k, c in enumerate(chosen):
                    others = ModelPatch(tuple(
                        e for e in _patch_of(selected_per_joint, base_patch).effects
                        if not (e.joints == (joint,) and e.effect == c.effect)))
                    own = np.array([i for i, s in enumerate(seq_meta) if s.get("joint", joint) == joint])
                    train, _ = _split(own, holdout)
                    r = JointFitter(rep, joint, train, others).fit(c.effect)
                    c.value, c.ci95 = r.value, r.ci95
        full = _patch_of(selected_per_joint, base_patch)
        for joint, chosen in selected_per_joint.items():
            own = np.array([i for i, s in enumerate(seq_meta) if s.get("joint", joint) == joint])
            _, held = _split(own, holdout)
            hf = JointFitter(rep, joint, held, base_patch)
            n2 = float(noise[names.index(joint)] ** 2)
            red = _reduction(hf.mse_per_sequence(base_patch), hf.mse_per_sequence(full), n2)
            if chosen:
                chosen[-1].heldout_error_reduction = red
            explained[joint] = red

    hypotheses = []
    for joint, cands in per_joint.items():
        for c in cands:
            hypotheses.append({"effect": c.effect, "joints": [joint],
                               "params": {get_effect(c.effect).param_names[0]: [c.value]},
                               "ci95": {get_effect(c.effect).param_names[0]: [list(c.ci95)]},
                               "train_error_reduction": c.train_error_reduction,
                               "heldout_error_reduction": c.heldout_error_reduction,
                               "score": c.score, "alternatives": []})
    hypotheses.sort(key=lambda h: -h["score"])
    # Best first-round hypothesis per joint carries the look-alike alternatives.
    for joint, chosen in selected_per_joint.items():
        if chosen:
            for h in hypotheses:
                if h["joints"] == [joint] and h["effect"] == chosen[0].effect:
                    h["alternatives"] = chosen[0].alternatives
                    break

    # Selected effects, merged over joints.
    merged: dict[str, dict] = {}
    for joint, chosen in selected_per_joint.items():
        for c in chosen:
            pname = get_effect(c.effect).param_names[0]
            h = merged.setdefault(c.effect, {"effect": c.effect, "joints": [], "params": {pname: []},
                                             "ci95": {pname: []}, "heldout_error_reduction": [],
                                             "alternatives": []})
            h["joints"].append(joint)
            h["params"][pname].append(c.value)
            h["ci95"][pname].append(list(c.ci95))
            h["heldout_error_reduction"].append(c.heldout_error_reduction)
            h["alternatives"] = sorted(set(h["alternatives"]) | set(c.alternatives))
    selected = list(merged.values())
    verdict = "explained" if all(v >= explained_at for v in explained.values()) else "unexplained"
    for joint, v in explained.items():
        chosen = selected_per_joint[joint]
        what = " + ".join(f"{c.effect} ({get_effect(c.effect).param_names[0]} = {c.value:.4g})" for c in chosen) or "nothing"
        findings.append(f"{joint}: {what} explains {100 * v:.0f}% of the held-out error above the noise floor.")
    if verdict == "unexplained":
        weak = [j for j, v in explained.items() if v < explained_at]
        findings.append(f"Unexplained: on {', '.join(weak)} the best candidates explain less than "
                        f"{100 * explained_at:.0f}% of the excess error; an effect outside the library may be at work.")
    return Diagnosis(verdict, baseline, hypotheses, selected, explained, findings, time.perf_counter() - t0)
