"""Where a load hangs: one payload on one link, in mass and place, felt on the failing joints of its chain,
and the steps of a diagnosis that look for one.

- :func:`_load_first`: with several failing joints, before any joint is fitted (a 0.6 kg mass on the palm is
  one ``payload_mass`` on the palm's link, not a payload on the shoulder, armature on the elbow and 13 finger
  hypotheses); mass and place fitted together by :func:`_place_loads`;
- :func:`_load_on_one_joint`: with one failing joint, once its own fit chose a payload or armature;
- :func:`_single_load_alternative`: one payload instead of load-like effects chosen on several joints of one
  chain;
- :func:`_shared_effect_and_load`: one effect on every failing joint of a chain with a load on top, a payload
  or links heavier than the model's (:func:`_heavier_links`): softer servos that carry a load.

The method is in :mod:`adadex.sysid.diagnose`'s docstring.
"""

from __future__ import annotations

import dataclasses

import numpy as np
from scipy.optimize import minimize_scalar

from adadex.sim.effects import EFFECT_NAMES, get_effect, robot_ids
from adadex.sim.patch import ModelPatch
from adadex.sysid.fit import WINDOWED_EFFECTS, JointFitter
from adadex.sysid.scoring import (COMPLEXITY_PENALTY, MIN_EXPLAINED, Candidate, _heldout_mse, _is_absent,
                                  _most_telling, _patch_of, _reduction, _scored_by, _Setting, _still_failing,
                                  on_bound)

#: a single load found before any joint is fitted (:func:`_load_first`) is kept when it explains this
#: fraction of the failing joints' held-out excess error on average
LOAD_FIRST_AT = 0.6
#: how many links, ranked by their Gauss–Newton step, are searched for the load's mass
LOAD_SHORTLIST = 4
#: the search starts only if the best link's Gauss–Newton step removes this fraction of the error: a true
#: load's step removes about 0.8 (0.6 kg at the palm, 1 kg on the forearm), a delay on the shoulder and
#: friction on a finger 0.36 (with a mass on the shoulder's own link)
LOAD_SCREEN_AT = 0.5


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
    sequence; :func:`_pair_with_load`), the load explains :data:`~adadex.sysid.scoring.MIN_EXPLAINED` of some
    joint's error beyond the refitted effect (it is not spurious there), and no value sits on a bound."""
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
