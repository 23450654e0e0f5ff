"""A source first: one library effect on one joint (or with one value on two joints of adjacent links, or a few
such effects) that explains most failing joints' error at once, found before any joint is fitted
(:func:`_source_first`).

A shoulder too weak to hold the arm moves every joint of the robot (torque limit 0.3 on arm_j2 and arm_j3 fails
20 of 22 joints); fitted joint by joint, each failing joint would be given an effect of its own.
:func:`~adadex.sysid.diagnose.diagnose` runs this step when no load was found first and at least
:data:`SOURCE_MIN_FAILING` joints fail; the joints the sources explain are their knock-ons. The method is in
:mod:`adadex.sysid.diagnose`'s docstring, the screen, the fits and the windowed refit of a chaotic source in
:func:`_source_first`'s.
"""

from __future__ import annotations

import dataclasses

import numpy as np
from scipy.optimize import minimize_scalar

from adadex.sim.effects import get_effect, robot_ids
from adadex.sim.patch import ModelPatch
from adadex.sysid.fit import WINDOWED_EFFECTS, CoupledFitter, _compass, grid_points
from adadex.sysid.scoring import (COMPLEXITY_PENALTY, COUPLED_XTOL, Candidate, _heldout_mse, _is_absent,
                                  _most_telling, _own_sequences, _patch_of, _reduction, _scored_by, _Setting,
                                  on_bound)

#: a source found first (:func:`_source_first`) is kept when it explains this fraction of the failing joints'
#: held-out excess error on average (as a load found first, :data:`~adadex.sysid.load_search.LOAD_FIRST_AT`)
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
    two training sequences where each failing joint errs most: Brent to
    :data:`~adadex.sysid.scoring.COUPLED_XTOL` of the bounds and a compass polish
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
