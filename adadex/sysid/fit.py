"""Fit effect parameters to a recording.

Every effect in the library has one parameter per joint, and the excitation moves one joint per
sequence, so fitting decouples into bounded 1-D problems — one per (effect, joint) — on the
sequences that move that joint. Each is solved robustly: a coarse grid over the parameter's
bounds (which also sidesteps the zero gradient many effects have at their absent value, e.g.
Coulomb friction at 0), then a bounded Brent refinement around the best grid point. The 95 %
confidence interval comes from the Gauss–Newton curvature at the optimum: var(θ) = σ² / JᵀJ with
σ² the residual variance and J = ∂r/∂θ by central differences.

The error measure is the mean squared joint-position error over the fitted joint and sequences,
replayed with :class:`~adadex.sysid.replay.Replayer`.

Friction-like effects (:data:`WINDOWED_EFFECTS`) are located on a multiple-shooting cost instead: the
free replay of a joint with a small Coulomb friction is chaotic in the friction (each stick–slip event
that changes leaves a lasting offset, and a fast, torque-limited arm amplifies it), so its cost is a
staircase of deep, narrow minima that a grid and Brent cannot search. Replayed in windows of
:data:`WINDOW_S`, each restarted from the measured positions
(:meth:`~adadex.sysid.replay.Replayer.simulate_windows`), the error cannot build up and its cost is
nearly a bowl; the value found there is then polished on the free-replay cost in a narrow bracket
around it (:meth:`JointFitter.fit`). The diagnosis scores such an effect on the windowed cost as well
(:meth:`JointFitter.window_mse_per_sequence`): at the true friction a free replay of a fast held-out
sequence can stay far off (:mod:`adadex.sysid.diagnose`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import minimize_scalar

from adadex.sim.effects import get_effect
from adadex.sim.patch import EffectInstance, ModelPatch

#: Effects located on the windowed (multiple-shooting) cost before a polish on the free-replay cost: those
#: whose free-replay cost is not a smooth function of their value. Measured on the 32-sequence
#: excitation of arm_j3 and arm_j5 (noise 2e-4 rad): Coulomb friction of 0.5 N·m on arm_j3 has a
#: free-replay cost whose minimum is 0.005 N·m wide, with local minima 2–12 % away (the grid and Brent
#: stopped at 0.688). ``backlash`` (0.005 rad on arm_j3, 0.002 rad on arm_j5) was fitted to −0.05 % and
#: +0.75 % on the free replay and stays there, though its free-replay cost also jumps on arm_j3.
WINDOWED_EFFECTS = ("coulomb_friction",)
#: Seconds between restarts of the windowed cost. Measured on Coulomb friction hidden on arm_j3 (0.5 N·m
#: at two noise seeds, 2 N·m), arm_j5 (0.2) and arm_j2 (1.0), recorded at 60 Hz: with :data:`WINDOW_TRIM`,
#: windows of 0.15–0.5 s put the windowed minimum within 2.3 % of the truth on all five, 0.25 s within
#: 0.8 % (the smallest worst case). Shorter windows restart (and inject the sensor noise) more often and
#: see less of each stick–slip cycle; in longer ones a fast, torque-limited arm's chaotic motion grows
#: (untrimmed, 0.2, 0.33 and 0.5 s put one case 26–147 % off, 0.25 s 1.3 %).
WINDOW_S = 0.25
#: Fraction of the windows, the worst, left out of the windowed cost. A few windows of a fast,
#: torque-limited arm diverge from a restart even at the true value (1e-4 rad² where the median window is
#: at the noise floor, 5e-8) and make the cost jump; without them the minimum is stable.
WINDOW_TRIM = 0.1
#: The free-replay polish scans this fraction of the windowed value on each side (at least 1e-3 of the
#: bounds), on :data:`POLISH_POINTS` points, then refines with Brent between the best one's neighbours.
POLISH_SPAN = 0.03
POLISH_POINTS = 21


@dataclass(kw_only=True)
class FitResult:
    """One effect fitted on one joint: the value, its 95 % interval, the mean squared error before and
    after, and the number of replays the fit took."""

    effect: str
    joint: str
    value: float
    ci95: tuple[float, float]
    mse_before: float
    mse_after: float
    evaluations: int


class JointFitter:
    """Fits effects on one joint against the recording's sequences ``seqs`` (indices)."""

    def __init__(self, replayer, joint: str, seqs, base_patch: ModelPatch | None = None):
        self.rep = replayer
        self.joint = joint
        self.seqs = np.asarray(seqs, dtype=np.int64)
        self.col = list(replayer.rec.joint_names).index(joint)
        self.measured = replayer.rec.joint_pos[self.seqs][..., self.col]
        self.base_patch = base_patch if base_patch is not None else ModelPatch(robot=replayer.robot)
        self.evaluations = 0

    def _errors(self, sim: np.ndarray) -> np.ndarray:
        """The fitted error of simulated positions ``sim`` (S, T, J): (S, T, 1), the joint's."""
        return (sim[..., self.col] - self.measured)[..., None]

    def residual(self, patch: ModelPatch) -> np.ndarray:
        self.evaluations += 1
        return self._errors(self.rep.simulate(patch, sequences=self.seqs)).ravel()

    def window_errors(self, patch: ModelPatch) -> np.ndarray:
        """The windowed (multiple-shooting) error, one row per window of every sequence: (windows,
        samples), replayed with :meth:`~adadex.sysid.replay.Replayer.simulate_windows` in windows of
        :data:`WINDOW_S`; the first sample (the pre-roll's rest, not predicted by any window) is left out."""
        self.evaluations += 1
        L = window_length(self.rep.rec.dt)
        return window_rows(self._errors(self.rep.simulate_windows(patch, length=L, sequences=self.seqs)), L)

    def window_mse(self, patch: ModelPatch) -> float:
        """The windowed cost: the mean squared error of the windows but the :data:`WINDOW_TRIM` worst."""
        w = np.nanmean(self.window_errors(patch) ** 2, axis=1)
        return float(np.mean(w[_kept_windows(w)]))

    def window_mse_per_sequence(self, patch: ModelPatch) -> np.ndarray:
        """The windowed cost sequence by sequence, (S,): :func:`window_mse_per_sequence` of this joint's
        windowed error (the windows :meth:`window_mse` keeps, each sequence's mean over its own)."""
        return window_mse_per_sequence(self.window_errors(patch), len(self.seqs))

    def mse_per_sequence(self, patch: ModelPatch) -> np.ndarray:
        r = self.residual(patch).reshape(len(self.seqs), -1)
        return np.mean(r * r, axis=1)

    def mse(self, patch: ModelPatch) -> float:
        r = self.residual(patch)
        return float(np.mean(r * r))

    def patch_with(self, effect: str, value: float) -> ModelPatch:
        return self.base_patch.with_effect(effect, [self.joint], [[value]])

    def grid(self, effect: str, points: int = 9) -> tuple[np.ndarray, np.ndarray]:
        """Costs on a coarse grid over the bounds plus the absent value: geometric for scale-like
        parameters (positive lower bound), quadratic (dense near 0) for sizes that start at 0,
        linear for signed ones."""
        xs = self._grid_points(effect, points)
        return xs, np.array([self.mse(self.patch_with(effect, float(x))) for x in xs])

    def _grid_points(self, effect: str, points: int) -> np.ndarray:
        return grid_points(effect, self.joint, self.rep.robot, points)

    def fit(self, effect: str, *, points: int = 9, xtol_frac: float = 1e-3, grid=None,
            mse_before: float | None = None, maxiter: int = 30, bracket=None) -> FitResult:
        """Grid, then bounded Brent refinement around the best grid point (or over ``bracket``, with no
        grid), then the CI.

        With ``xtol_frac`` below 1e-3 (a sensitive parameter) the Brent result is polished by a
        compass search (steps x ± h, h halving from 100 ``xtol_frac`` of the bounds down to ``xtol_frac``),
        which steps out of the shallow local minima Brent can stop in at that scale.

        An effect of :data:`WINDOWED_EFFECTS` (with no ``bracket``) is located on the windowed cost
        instead (:meth:`window_mse`; its own grid — a given ``grid``, the free replay's, is not used —
        and Brent to 1e-4 of the bounds), then polished on the free-replay cost around it
        (:meth:`_polish`); ``mse_after`` is the free replay's, and the 95 % interval comes from the
        Gauss–Newton curvature of the windowed residual (the free replay's has none to speak of there)."""
        eff = get_effect(effect)
        lo, hi = (float(b[0, 0]) for b in eff.bounds([self.joint], self.rep.robot))
        start = self.evaluations
        before = self.mse(self.base_patch) if mse_before is None else mse_before
        if effect in WINDOWED_EFFECTS and bracket is None:
            x = self._locate_windowed(effect, points, lo, hi)
            best_x, best_c = self._polish(effect, x, lo, hi, xtol_frac, maxiter)
            ci = self._ci95(effect, best_x, lo, hi, windowed=True)
            return FitResult(effect=effect, joint=self.joint, value=best_x, ci95=ci, mse_before=before,
                             mse_after=best_c, evaluations=self.evaluations - start)

        def cost(x: float) -> float:
            return self.mse(self.patch_with(effect, float(x)))

        if bracket is None:
            xs, costs = grid if grid is not None else self.grid(effect, points)
            i = int(np.argmin(costs))
            a, b = xs[max(i - 1, 0)], xs[min(i + 1, len(xs) - 1)]
            best_x, best_c = float(xs[i]), float(costs[i])
        else:
            a, b = (float(v) for v in bracket)
            best_x = 0.5 * (a + b)
            best_c = cost(best_x)
        if b > a:
            res = minimize_scalar(cost, bounds=(a, b), method="bounded",
                                  options={"xatol": xtol_frac * (hi - lo), "maxiter": maxiter})
            if res.fun < best_c:
                best_x, best_c = float(res.x), float(res.fun)
            if xtol_frac < 1e-3:
                best_x, best_c = _compass(cost, best_x, best_c, a, b, 100 * xtol_frac * (hi - lo),
                                          xtol_frac * (hi - lo))
        ci = self._ci95(effect, best_x, lo, hi)
        return FitResult(effect=effect, joint=self.joint, value=best_x, ci95=ci, mse_before=before, mse_after=best_c,
                         evaluations=self.evaluations - start)

    def _locate_windowed(self, effect: str, points: int, lo: float, hi: float) -> float:
        """The minimum of the windowed cost: a grid over the bounds, then bounded Brent (to 1e-4 of the
        bounds) between the best grid point's neighbours."""
        def cost(x: float) -> float:
            return self.window_mse(self.patch_with(effect, float(x)))

        xs = self._grid_points(effect, points)
        costs = np.array([cost(x) for x in xs])
        i = int(np.argmin(costs))
        a, b = xs[max(i - 1, 0)], xs[min(i + 1, len(xs) - 1)]
        best_x, best_c = float(xs[i]), float(costs[i])
        if b > a:
            res = minimize_scalar(cost, bounds=(a, b), method="bounded",
                                  options={"xatol": 1e-4 * (hi - lo), "maxiter": 40})
            if res.fun < best_c:
                best_x = float(res.x)
        return best_x

    def _polish(self, effect: str, x: float, lo: float, hi: float, xtol_frac: float,
                maxiter: int) -> tuple[float, float]:
        """(value, free-replay MSE) of the best free-replay cost near ``x``: a scan of
        :data:`POLISH_POINTS` points over ``x`` ± :data:`POLISH_SPAN` · x (at least 1e-3 of the bounds), then
        bounded Brent between the best point's neighbours (and the compass search below 1e-3, as in
        :meth:`fit`). The free-replay minimum around a small friction is a fraction of a percent wide, so
        it is scanned for, not bracketed."""
        def cost(y: float) -> float:
            return self.mse(self.patch_with(effect, float(y)))

        half = max(POLISH_SPAN * abs(x), 1e-3 * (hi - lo))
        ys = np.unique(np.clip(x + np.linspace(-half, half, POLISH_POINTS), lo, hi))
        costs = np.array([cost(y) for y in ys])
        k = int(np.argmin(costs))
        best_x, best_c = float(ys[k]), float(costs[k])
        a, b = float(ys[max(k - 1, 0)]), float(ys[min(k + 1, len(ys) - 1)])
        if b > a:
            tol = min(xtol_frac * (hi - lo), 0.05 * (b - a))
            res = minimize_scalar(cost, bounds=(a, b), method="bounded", options={"xatol": tol, "maxiter": maxiter})
            if res.fun < best_c:
                best_x, best_c = float(res.x), float(res.fun)
            if xtol_frac < 1e-3:
                best_x, best_c = _compass(cost, best_x, best_c, a, b, 100 * xtol_frac * (hi - lo), xtol_frac * (hi - lo))
        return best_x, best_c

    def _ci95(self, effect: str, x: float, lo: float, hi: float, windowed: bool = False) -> tuple[float, float]:
        """Gauss–Newton 95 % interval at ``x``: on the free-replay residual, or (``windowed``) on the
        windowed residual of the windows :meth:`window_mse` keeps at ``x``."""
        h = 1e-3 * (hi - lo)
        xm, xp = max(lo, x - h), min(hi, x + h)
        if xp <= xm:
            return (x, x)
        if windowed:
            rows = self.window_errors(self.patch_with(effect, x))
            keep = _kept_windows(np.nanmean(rows ** 2, axis=1))
            valid = np.isfinite(rows[keep])

            def residual(patch):
                return self.window_errors(patch)[keep][valid]

            r0 = rows[keep][valid]
        else:
            residual = self.residual
            r0 = self.residual(self.patch_with(effect, x))
        J = (residual(self.patch_with(effect, xp)) - residual(self.patch_with(effect, xm))) / (xp - xm)
        dof = max(r0.size - 1, 1)
        sigma2 = float(r0 @ r0) / dof
        jtj = float(J @ J)
        if jtj <= 0:
            return (lo, hi)
        half = 1.96 * np.sqrt(sigma2 / jtj)
        return (float(max(lo, x - half)), float(min(hi, x + half)))


class CoupledFitter(JointFitter):
    """Fits effects on ``joint`` against the error of every joint in ``joints`` (``joint`` and the joints
    it may move) on ``seqs``, each joint's error in units of its noise floor (``noise``, rad, one per
    joint): :meth:`mse` is the mean over those joints of MSE / σ². A source whose error shows on other
    joints (a sagging shoulder shakes the fingers) is fitted to all of it, not to its own joint alone."""

    def __init__(self, replayer, joint: str, joints, seqs, noise, base_patch: ModelPatch | None = None):
        super().__init__(replayer, joint, seqs, base_patch)
        names = list(replayer.rec.joint_names)
        self.cols = [names.index(j) for j in joints]
        self.scale = 1.0 / np.maximum(np.asarray(noise, dtype=float), 1e-9)
        self.measured = replayer.rec.joint_pos[self.seqs][..., self.cols]

    def _errors(self, sim: np.ndarray) -> np.ndarray:
        return (sim[..., self.cols] - self.measured) * self.scale


def grid_points(effect: str, joint: str, robot=None, points: int = 9, absent: bool = True) -> np.ndarray:
    """The coarse grid of ``effect`` on ``joint`` over its bounds: geometric for scale-like parameters
    (positive lower bound), quadratic (dense near 0) for sizes that start at 0, linear for signed ones;
    with the absent value added (``absent``), or with the points next to it left out."""
    eff = get_effect(effect)
    lo, hi = (float(b[0, 0]) for b in eff.bounds([joint], robot))
    none = float(eff.absent_values()[0])
    ramp = np.linspace(0, 1, points)
    if lo > 0:
        xs = np.geomspace(lo, hi, points)
    elif lo < 0:
        xs = lo + (hi - lo) * ramp
    else:
        xs = lo + (hi - lo) * ramp ** 2
    return np.unique(np.concatenate([xs, [none]])) if absent else xs[np.abs(xs - none) > 1e-3 * (hi - lo)]


def window_length(dt: float) -> int:
    """Samples per window of the windowed cost: :data:`WINDOW_S` at the recording period ``dt`` (at least 1)."""
    return max(1, int(round(WINDOW_S / dt)))


def window_rows(e: np.ndarray, L: int) -> np.ndarray:
    """Errors ``e`` (S, T, C) of a windowed replay as one row per window of every sequence, (S · W, L · C),
    sequence by sequence; the first sample (the pre-roll's rest, not predicted by any window) is left out
    and a short last window is padded with NaN."""
    e = e[:, 1:]
    S, T, C = e.shape
    W = -(-T // L)
    pad = np.full((S, W * L, C), np.nan)
    pad[:, :T] = e
    return pad.reshape(S * W, L * C)


def window_mse_per_sequence(rows: np.ndarray, num_sequences: int) -> np.ndarray:
    """Each sequence's windowed cost, (S,), from the window rows of :meth:`JointFitter.window_errors`
    (``num_sequences`` sequences, their windows in order): the mean squared error of the sequence's windows
    among those the windowed cost keeps (all but the :data:`WINDOW_TRIM` worst of all the sequences'
    windows together, as :meth:`JointFitter.window_mse` trims them); a sequence none of whose windows is
    kept gets the mean of all of them. The held-out scoring of a windowed effect reads it
    (:mod:`adadex.sysid.diagnose`): its per-sequence mean excess error, as the free replay's."""
    w = np.nanmean(rows ** 2, axis=1)
    kept = np.zeros(w.size, dtype=bool)
    kept[_kept_windows(w)] = True
    w, kept = w.reshape(num_sequences, -1), kept.reshape(num_sequences, -1)
    n = kept.sum(axis=1)
    trimmed = np.where(kept, w, 0.0).sum(axis=1) / np.maximum(n, 1)
    return np.where(n > 0, trimmed, w.mean(axis=1))


def _kept_windows(mse: np.ndarray) -> np.ndarray:
    """Indices of the windows the windowed cost keeps: all but the :data:`WINDOW_TRIM` worst, best first."""
    return np.argsort(mse)[:max(1, mse.size - int(WINDOW_TRIM * mse.size))]


def _compass(cost, x: float, c: float, lo: float, hi: float, h: float, h_min: float) -> tuple[float, float]:
    """1-D compass search from (x, cost c) within [lo, hi]: try x ± h, move on improvement, else halve h."""
    while h >= h_min:
        for y in (x - h, x + h):
            if lo <= y <= hi:
                cy = cost(y)
                if cy < c:
                    x, c = y, cy
                    break
        else:
            h *= 0.5
    return x, c


def sequences_moving(recording, joint: str) -> np.ndarray:
    """Indices of the sequences that excite ``joint`` (all, when the recording does not say)."""
    seqs = list(recording.meta.get("sequences") or [])
    own = [i for i, s in enumerate(seqs) if s.get("joint") == joint]
    return np.asarray(own if own else range(recording.num_sequences), dtype=np.int64)


def fit_patch(recording, additions, *, base_patch: ModelPatch | None = None, nthread: int = 2) -> ModelPatch:
    """Fit ``additions`` — a list of ``(effect, joints)`` — in order, each on top of the previous ones.

    Every joint's value is fitted on the sequences that move it. Returns the fitted effects only
    (not ``base_patch``), each with its 95 % interval (``ci95``), so
    :meth:`adadex.envs.randomization.Randomization.from_patch` can randomize around the fit.

    Args:
        recording: the :class:`~adadex.data.recording.Recording` to fit; its ``meta["sequences"]`` say
            which sequences move each joint (all of them, where it does not say).
        additions: ``(effect, joints)`` pairs: an effect's name (of
            :data:`~adadex.sim.effects.EFFECT_NAMES`) and the non-empty list of recorded joints to fit it
            on, each joint's value on its own (:meth:`JointFitter.fit`: its first parameter; the others
            keep their absent values). An unknown effect or joint raises
            :class:`~adadex.sim.effects.EffectError`.
        base_patch: the model the additions are fitted on top of (:class:`~adadex.sim.patch.ModelPatch`);
            None (default): the nominal model.
        nthread: threads of the :class:`~adadex.sysid.replay.Replayer`'s rollout pool (default 2).

    Returns:
        a :class:`~adadex.sim.patch.ModelPatch` of one effect per addition, in order, with ``values``
        (joints, parameters) and ``ci95`` (joints, parameters, 2) in the effect's units.
    """
    from adadex.sim.effects import EffectError
    from adadex.sysid.replay import Replayer

    rep = Replayer(recording, nthread=nthread)
    base = base_patch if base_patch is not None else ModelPatch(robot=rep.robot)
    added = ModelPatch(robot=rep.robot)
    for effect, joints in additions:
        get_effect(effect)
        missing = [j for j in joints if j not in recording.joint_names]
        if missing or not joints:
            raise EffectError(f"{effect}: joints {missing or joints} are not in the recording "
                              f"(it has {', '.join(recording.joint_names)})")
        values, intervals = [], []
        for j in joints:
            r = JointFitter(rep, j, sequences_moving(recording, j), base + added).fit(effect)
            values.append([r.value])
            intervals.append([list(r.ci95)])
        fitted = EffectInstance(effect=effect, joints=tuple(joints), values=np.array(values),
                                ci95=np.array(intervals), robot=rep.robot)
        added = added + ModelPatch(effects=(fitted,), robot=rep.robot)
    return added


def identify_pd(replayer, joint: str, seqs, *, method: str = "cma", seed: int = 0,
                base_patch: ModelPatch | None = None, max_evals: int = 150) -> dict:
    """The paper's identification: per-joint servo gains (``kp_scale``, ``kd_scale``) that minimize
    Σ‖q_sim − q_real‖² on ``seqs``, with CMA-ES (``method="cma"``, the paper's choice, seeded) or
    MuJoCo's bounded least squares (``method="lsq"``, the optimizer behind ``mujoco.sysid``).

    The starting model (kp, kd scales 1) is scored as well and kept when the optimizer ends worse
    (``progress`` is then False): the result is never worse than the nominal ``mse_nominal``.

    Args:
        replayer: the :class:`~adadex.sysid.replay.Replayer` of the recording.
        joint: the recorded joint whose kp and kd scales are fitted, on its own error only.
        seqs: the indices of the sequences to fit on (e.g. :func:`sequences_moving`).
        method: ``"cma"`` (default) or ``"lsq"``; another raises ``ValueError``.
        seed: CMA-ES's random seed (default 0); ``"lsq"`` is deterministic.
        base_patch: the model the gains are fitted on top of (:class:`~adadex.sim.patch.ModelPatch`);
            None (default): the nominal model.
        max_evals: CMA-ES's budget of cost evaluations, 8 per generation (default 150); ``"lsq"`` runs
            at most 40 iterations instead.

    Returns:
        a dict: ``joint``, ``method``, ``kp_scale`` and ``kd_scale`` (× nominal, within the effects'
        bounds), ``mse`` and ``mse_nominal`` (the fitted and the nominal model's mean squared error of
        ``joint`` on ``seqs``, rad²), ``progress``, ``evaluations`` (replays of ``seqs``) and
        ``seconds`` (wall time, s).
    """
    import io
    import time

    import cma
    from mujoco import minimize

    fitter = JointFitter(replayer, joint, seqs, base_patch)
    robot = replayer.robot
    lo = np.array([get_effect(n).bounds([joint], robot)[0][0, 0] for n in ("kp_scale", "kd_scale")])
    hi = np.array([get_effect(n).bounds([joint], robot)[1][0, 0] for n in ("kp_scale", "kd_scale")])

    def patch_at(x):
        return (fitter.base_patch.with_effect("kp_scale", [joint], [[float(x[0])]])
                .with_effect("kd_scale", [joint], [[float(x[1])]]))

    t0 = time.perf_counter()
    x0 = np.ones(2)
    start = fitter.mse(patch_at(x0))      # the starting (nominal) model is scored too: never return worse
    if method == "cma":
        span = hi - lo
        es = cma.CMAEvolutionStrategy(((x0 - lo) / span).tolist(), 0.15,
                                      {"bounds": [[0, 0], [1, 1]], "seed": seed + 1, "maxfevals": max_evals,
                                       "verbose": -9, "popsize": 8})
        while not es.stop():
            zs = es.ask()
            es.tell(zs, [fitter.mse(patch_at(lo + np.asarray(z) * span)) for z in zs])
        x = lo + np.asarray(es.result.xbest) * span
    elif method == "lsq":
        def residual(x):
            x = np.asarray(x)
            cols = x if x.ndim == 2 else x[:, None]
            return np.stack([fitter.residual(patch_at(cols[:, i])) for i in range(cols.shape[1])], axis=1) \
                if x.ndim == 2 else fitter.residual(patch_at(x))

        x, _ = minimize.least_squares(x0, residual, bounds=[lo, hi], verbose=0, output=io.StringIO(), max_iter=40)
    else:
        raise ValueError(f"method must be 'cma' or 'lsq', got {method!r}")
    mse = fitter.mse(patch_at(x))
    progress = bool(mse < start)
    if not progress:   # the optimizer found nothing better than where it started: keep the start
        x, mse = x0, start
    return {"joint": joint, "method": method, "kp_scale": float(x[0]), "kd_scale": float(x[1]),
            "mse": mse, "mse_nominal": start, "progress": progress,
            "evaluations": fitter.evaluations, "seconds": time.perf_counter() - t0}
