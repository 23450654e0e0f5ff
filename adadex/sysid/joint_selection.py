"""Joint by joint: whether a failing joint is a knock-on of others (:func:`_follows`), which effects explain
it (:func:`_forward_selection`), then every selected value refitted with the others in place
(:func:`_refit_jointly`), the selection rule (:func:`_prune`) and each joint scored with all of them
(:func:`_score_jointly`).

Every candidate effect is screened on a coarse grid on the joint's training sequences, the most promising
fitted precisely and each scored on its held-out sequences (:func:`_fit_and_score_candidates`); a source whose
effect moves failing joints still pending is fitted to their errors too. The method is in
:mod:`adadex.sysid.diagnose`'s docstring.
"""

from __future__ import annotations

import numpy as np

from adadex.sim.effects import get_effect
from adadex.sim.patch import ModelPatch
from adadex.sysid.fit import WINDOWED_EFFECTS, CoupledFitter, JointFitter
from adadex.sysid.scoring import (COMPLEXITY_PENALTY, COUPLED_XTOL, EXCITATION_FOR, MIN_EXPLAINED, Candidate,
                                  _fails, _heldout_mse, _is_absent, _own_sequences, _patch_of, _reduction,
                                  _scored_by, _Setting, _windowed, on_bound)

#: a pending joint enters a source's coupled fit when the source's effect moves it by this fraction
#: of its residual
COUPLING_MIN = 0.1


def _follows(setting: _Setting, joint: str, others: list[str], patch: ModelPatch) -> tuple[list[str], float] | None:
    """Whether the failure of ``joint`` is a knock-on of the failing joints ``others``, whatever moves them:
    ``(the joints it follows, its RMS error then, rad)``, or None when it still fails.

    Its own sequences are replayed on ``patch`` with ``others`` moving exactly as measured
    (:meth:`~adadex.sysid.replay.Replayer.simulate_imposed`: every torque on them, a missing effect
    included, is taken from the measurement; ``joint`` feels their measured motion through the model's
    coupled dynamics). If ``joint`` then no longer fails (:func:`~adadex.sysid.scoring._fails`), its error
    came from their motion, not from an effect of its own. One replay; when it follows several, each is
    tried alone too and the joints it follows are those that suffice alone (all of them if none does)."""
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
    ``patch`` (``scored_by`` ``"windowed"``; see :mod:`adadex.sysid.diagnose`'s docstring).

    With failing joints still pending (``moved``), the best candidate is then refitted against the error
    of ``joint`` and of those joints on all their training sequences (a
    :class:`~adadex.sysid.fit.CoupledFitter`: grid, Brent to :data:`~adadex.sysid.scoring.COUPLED_XTOL`, a
    compass polish): an effect on ``joint`` that moves them is fitted to the error it causes there too, which pins a
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
    """The selection rule, applied to the effects chosen (in place): a value at its absent value is dropped;
    a value on a bound (:func:`~adadex.sysid.scoring.on_bound`) becomes a suggestion; then, weakest first,
    an effect is dropped while it explains less than :data:`~adadex.sysid.scoring.MIN_EXPLAINED` of its
    joints' held-out excess error beyond what all the other selected effects explain. Its joints: the joint
    it is on and the failing joints its source explained as knock-ons (``moves``), or, for a single load,
    the joints it carries (``carried``). Returns (suggestions, the removed ``(joint, candidate)`` pairs)."""
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
