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
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import minimize_scalar

from adadex.sim.effects import get_effect
from adadex.sim.patch import EffectInstance, ModelPatch


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

    def residual(self, patch: ModelPatch) -> np.ndarray:
        self.evaluations += 1
        sim = self.rep.simulate(patch, sequences=self.seqs)[..., self.col]
        return (sim - self.measured).ravel()

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
        eff = get_effect(effect)
        lo, hi = (float(b[0, 0]) for b in eff.bounds([self.joint], self.rep.robot))
        absent = float(eff.absent_values()[0])
        ramp = np.linspace(0, 1, points)
        if lo > 0:
            xs = np.geomspace(lo, hi, points)
        elif lo < 0:
            xs = lo + (hi - lo) * ramp
        else:
            xs = lo + (hi - lo) * ramp ** 2
        xs = np.unique(np.concatenate([xs, [absent]]))
        return xs, np.array([self.mse(self.patch_with(effect, float(x))) for x in xs])

    def fit(self, effect: str, *, points: int = 9, xtol_frac: float = 1e-3, grid=None,
            mse_before: float | None = None, maxiter: int = 30, bracket=None) -> FitResult:
        """Grid, then bounded Brent refinement around the best grid point (or over ``bracket``, with no
        grid), then the CI.

        With ``xtol_frac`` below 1e-3 (a sensitive parameter) the Brent result is polished by a
        compass search (steps x ± h, h halving from 100 ``xtol_frac`` of the bounds down to ``xtol_frac``),
        which steps out of the shallow local minima Brent can stop in at that scale."""
        eff = get_effect(effect)
        lo, hi = (float(b[0, 0]) for b in eff.bounds([self.joint], self.rep.robot))
        start = self.evaluations
        before = self.mse(self.base_patch) if mse_before is None else mse_before

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

    def _ci95(self, effect: str, x: float, lo: float, hi: float) -> tuple[float, float]:
        h = 1e-3 * (hi - lo)
        xm, xp = max(lo, x - h), min(hi, x + h)
        if xp <= xm:
            return (x, x)
        r0 = self.residual(self.patch_with(effect, x))
        J = (self.residual(self.patch_with(effect, xp)) - self.residual(self.patch_with(effect, xm))) / (xp - xm)
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

    def residual(self, patch: ModelPatch) -> np.ndarray:
        self.evaluations += 1
        sim = self.rep.simulate(patch, sequences=self.seqs)[..., self.cols]
        return ((sim - self.measured) * self.scale).ravel()


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
