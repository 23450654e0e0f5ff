"""The paper's Table 1 over training seeds: means, 95 % intervals, differences to the tracker, and the
Markdown table.

:func:`aggregate` takes one evaluation summary (:func:`adadex.eval.metrics.summarize`) per seed for
each (split, condition, row) and, where the evaluations kept them, each seed's per-episode results
(``per_episode`` of :func:`adadex.eval.evaluate.evaluate`). It returns ``{split: {condition: {row:
{metric: value, metric_ci95: [lo, hi] | None, "seeds": n, "episodes": n, "ci": how, "diff_vs_tracker":
{metric: value}, "diff_vs_tracker_ci95": {metric: [lo, hi] | None}}}}}`` with the metrics ``T_o``,
``R_o``, ``T_h``, ``R_h`` (cm, rad), ``E_finger`` (rad), ``mean_error_pct`` and ``completion_pct``
(the paper's success, %; the headline) and the object-centric ``object_completion_pct`` and
``carried_pct`` (%, :mod:`adadex.eval.metrics`).

*value*  the mean over seeds of each seed's value.
*metric_ci95*  with per-episode results for every seed (``"ci": "bootstrap"``): the 95 % percentile
    bootstrap interval over references, resampled within each seed and pooled across seeds
    (:func:`adadex.eval.paired.bootstrap_mean`, 2000 resamples, seeded); without them (stages
    stored by older runs, ``"ci": "student-t"``): Student's t over the seeds (``None`` with one seed).
*diff_vs_tracker*  (every row but the tracker) the row minus the tracker, paired per episode — the
    rows of a seed are evaluated on the same references and draws — with its bootstrap interval over
    references pooled across seeds (:func:`adadex.eval.paired.paired_bootstrap`); without per-episode
    results, the mean over seeds of the per-seed differences with Student's t over them.

:func:`table_markdown` writes it as the paper lays it out, one table per split and condition, and
below each the differences to the tracker.

>>> s = lambda c: {"T_o": 2.0, "R_o": 0.1, "T_h": 1.0, "R_h": 0.1, "E_finger": 0.05,
...                "success_mean_error_pct": 60.0, "completion_pct": c, "trajectories": 10}
>>> t = aggregate({("unseen_trajectory", "nominal", "tracker"): [s(50.0), s(60.0), s(70.0)]})
>>> row = t["unseen_trajectory"]["nominal"]["tracker"]
>>> row["completion_pct"], [round(v, 1) for v in row["completion_pct_ci95"]], row["seeds"], row["ci"]
(60.0, [35.2, 84.8], 3, 'student-t')
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence

import numpy as np

from adadex.eval.paired import RESAMPLES, bootstrap_mean, pair_episodes, pooled_episodes, paired_bootstrap

#: metric in table1.json → key of an evaluation summary
METRICS = {"T_o": "T_o", "R_o": "R_o", "T_h": "T_h", "R_h": "R_h", "E_finger": "E_finger",
           "mean_error_pct": "success_mean_error_pct", "completion_pct": "completion_pct",
           "object_completion_pct": "object_completion_pct", "carried_pct": "carried_pct"}
#: metric in table1.json → (field of an evaluation's ``per_episode``, scale to the table's unit)
EPISODE_FIELDS = {"T_o": ("T_o", 100.0), "R_o": ("R_o", 1.0), "T_h": ("T_h", 100.0), "R_h": ("R_h", 1.0),
                  "E_finger": ("E_finger", 1.0), "mean_error_pct": ("success_mean_error", 100.0),
                  "completion_pct": ("completion", 100.0), "object_completion_pct": ("object_completion", 100.0),
                  "carried_pct": ("carried", 100.0)}
SPLITS = ("unseen_trajectory", "unseen_object")
CONDITIONS = ("nominal", "randomized")
ROWS = ("replay", "ppo", "il_rl", "tracker", "R", "RT", "ROT", "O")
ROW_LABELS = {"replay": "kinematic replay", "ppo": "PPO", "il_rl": "IL+RL (DexTrack-style)", "tracker": "tracker",
              "R": "+R", "RT": "+R+T", "ROT": "+R+O+T", "O": "O only"}
BASE_ROW = "tracker"


def ci95(values: Sequence[float]) -> list[float] | None:
    """Student-t 95 % interval of the mean of ``values`` (``None`` for fewer than two finite values)."""
    from scipy import stats

    v = np.asarray([x for x in values if math.isfinite(x)], dtype=np.float64)
    if len(v) < 2:
        return None
    half = float(stats.t.ppf(0.975, len(v) - 1) * v.std(ddof=1) / math.sqrt(len(v)))
    m = float(v.mean())
    return [m - half, m + half]


def _value(summary: Mapping, key: str) -> float:
    v = summary.get(key)
    return math.nan if v is None else float(v)


def _has_episodes(per_seed) -> bool:
    return per_seed is not None and len(per_seed) > 0 and all(
        isinstance(e, Mapping) and "reference" in e for e in per_seed)


def _mean(values: Sequence[float]) -> float:
    finite = [v for v in values if math.isfinite(v)]
    return float(np.mean(finite)) if finite else math.nan


def aggregate(summaries: Mapping[tuple[str, str, str], Sequence[dict]],
              episodes: Mapping[tuple[str, str, str], Sequence[dict | None]] | None = None, *,
              resamples: int = RESAMPLES, seed: int = 0) -> dict:
    """``{(split, condition, row): [summary per seed]}`` → the table1.json structure (module docstring).

    Args:
        summaries: ``{(split, condition, row): [summary per seed]}``, each a
            :func:`~adadex.eval.metrics.summarize` result.
        episodes: ``{(split, condition, row): [per_episode per seed]}``, the seeds in the same order as
            in ``summaries`` (``None`` for a seed whose evaluation kept none); a row uses the bootstrap
            only when every one of its seeds has them, a difference only when both rows have them.
        resamples, seed: the bootstrap's resamples and random seed.
    """
    episodes = episodes or {}
    out: dict = {}
    for (split, condition, row), per_seed in summaries.items():
        eps = episodes.get((split, condition, row))
        boot = _has_episodes(eps) and len(eps) == len(per_seed)
        entry = {"seeds": len(per_seed), "ci": "bootstrap" if boot else "student-t"}
        if boot:
            entry["episodes"] = len(pooled_episodes(eps, "completion")[0])
        for name, key in METRICS.items():
            vals = [_value(s, key) for s in per_seed]
            entry[name] = _mean(vals)
            entry[f"{name}_ci95"] = ci95(vals)
            if boot and all(EPISODE_FIELDS[name][0] in e for e in eps):
                field, scale = EPISODE_FIELDS[name]
                b = bootstrap_mean(*pooled_episodes(eps, field, scale=scale), resamples=resamples, seed=seed)
                if b["ci95"] is not None:
                    entry[name], entry[f"{name}_ci95"] = b["estimate"], b["ci95"]
        entry.setdefault("episodes", int(sum(_value(s, "trajectories") for s in per_seed
                                             if math.isfinite(_value(s, "trajectories")))))
        out.setdefault(split, {}).setdefault(condition, {})[row] = entry
    for (split, condition, row), per_seed in summaries.items():
        base = (split, condition, BASE_ROW)
        if row == BASE_ROW or base not in summaries:
            continue
        entry = out[split][condition][row]
        diff, diff_ci = {}, {}
        eps, base_eps = episodes.get((split, condition, row)), episodes.get(base)
        paired = (_has_episodes(eps) and _has_episodes(base_eps) and len(eps) == len(base_eps) == len(per_seed))
        for name, key in METRICS.items():
            field, scale = EPISODE_FIELDS[name]
            if paired and all(field in e for e in (*eps, *base_eps)):
                a, b, refs, seeds = pair_episodes(eps, base_eps, field, scale=scale)
                d = paired_bootstrap(a, b, refs, seeds, resamples=resamples, seed=seed)
                diff[name], diff_ci[name] = d["estimate"], d["ci95"]
            elif len(per_seed) == len(summaries[base]):      # by seed: no pairing of episodes possible
                per_seed_diff = [_value(s, key) - _value(t, key) for s, t in zip(per_seed, summaries[base])]
                diff[name], diff_ci[name] = _mean(per_seed_diff), ci95(per_seed_diff)
        if diff:
            entry["diff_vs_tracker"], entry["diff_vs_tracker_ci95"] = diff, diff_ci
    return out


def _cell(entry: dict, name: str, fmt: str) -> str:
    value = entry.get(name)
    if value is None or not math.isfinite(value):
        return "—"
    ci = entry.get(f"{name}_ci95")
    text = format(value, fmt)
    return text if ci is None else f"{text} ± {format((ci[1] - ci[0]) / 2, fmt)}"


def _diff_cell(entry: dict, name: str, fmt: str) -> str:
    d = entry.get("diff_vs_tracker", {}).get(name)
    if d is None or not math.isfinite(d):
        return "—"
    ci = entry.get("diff_vs_tracker_ci95", {}).get(name)
    text = format(d, "+" + fmt)
    return text if ci is None else f"{text} [{format(ci[0], '+' + fmt)}, {format(ci[1], '+' + fmt)}]"


def _ordered(rows: Mapping) -> list[str]:
    return [r for r in ROWS if r in rows] + [r for r in rows if r not in ROWS]


#: written under each nominal block's heading: what one undrawn episode a reference can and cannot tell
NOMINAL_NOTE = ("Nominal: one episode a reference and nothing drawn, so each row is one sample of outcomes that "
                "any perturbation changes (Table 3's action noise alone moves a row by several points); read a "
                "difference here against the randomized block's.")


def table_markdown(table: dict, *, title: str = "Table 1") -> str:
    """The table as Markdown: one block per split and condition, rows in :data:`ROWS` order, each
    cell the mean over seeds ± the half-width of its 95 % interval; below each block the rows'
    differences to the tracker with their 95 % intervals ([lo, hi]); under each nominal heading
    :data:`NOMINAL_NOTE`.

    Args:
        table: the :func:`aggregate` structure (table1.json).
        title: the page's heading (default ``"Table 1"``).
    """
    lines = [f"# {title}", "",
             "Success (%): mean-error / completion (the paper's metrics), then the object-centric object "
             "completion (frames within the paper's thresholds *and* T_o ≤ 5 cm) and carried (the object follows "
             "the reference through its motion). Errors: T_o, T_h in cm; R_o, R_h, E_finger in rad. "
             "Mean over training seeds ± half-width of the 95 % interval: bootstrap over test references, "
             "resampled within each seed and pooled across seeds (`ci: bootstrap`), or, for evaluations stored "
             "without per-episode results, Student's t over seeds (none with one seed).", ""]
    for split in SPLITS:
        for condition in CONDITIONS:
            rows = table.get(split, {}).get(condition)
            if not rows:
                continue
            lines += [f"## {split.replace('_', ' ')}, {condition}", ""]
            if condition == "nominal":
                lines += [NOMINAL_NOTE, ""]
            lines += ["| method | seeds | episodes | success mean-error % | success completion % | object completion % "
                      "| carried % | T_o | R_o | T_h | R_h | E_finger |",
                      "|---|---|---|---|---|---|---|---|---|---|---|---|"]
            for row in _ordered(rows):
                e = rows[row]
                lines.append(f"| {ROW_LABELS.get(row, row)} | {e['seeds']} | {e.get('episodes', '—')} | "
                             f"{_cell(e, 'mean_error_pct', '.1f')} | {_cell(e, 'completion_pct', '.1f')} | "
                             f"{_cell(e, 'object_completion_pct', '.1f')} | {_cell(e, 'carried_pct', '.1f')} | "
                             f"{_cell(e, 'T_o', '.2f')} | {_cell(e, 'R_o', '.3f')} | {_cell(e, 'T_h', '.2f')} | "
                             f"{_cell(e, 'R_h', '.3f')} | {_cell(e, 'E_finger', '.3f')} |")
            diffs = [r for r in _ordered(rows) if "diff_vs_tracker" in rows[r]]
            if diffs:
                lines += ["", "Difference to the tracker (row − tracker; paired per episode, 95 % bootstrap interval "
                          "over references pooled across seeds; for evaluations stored without per-episode "
                          "results, the per-seed differences with Student's t):", "",
                          "| method | success mean-error % | success completion % | object completion % | carried % "
                          "| T_o cm |",
                          "|---|---|---|---|---|---|"]
                for row in diffs:
                    e = rows[row]
                    lines.append(f"| {ROW_LABELS.get(row, row)} | {_diff_cell(e, 'mean_error_pct', '.1f')} | "
                                 f"{_diff_cell(e, 'completion_pct', '.1f')} | "
                                 f"{_diff_cell(e, 'object_completion_pct', '.1f')} | "
                                 f"{_diff_cell(e, 'carried_pct', '.1f')} | {_diff_cell(e, 'T_o', '.2f')} |")
            lines.append("")
    return "\n".join(lines)


def o_channel_note(table: dict, rho_mean: float, *, lambda_latent: float, latent_dim: int = 64,
                   action_bound: float = 0.05, action_dim: int = 22) -> dict:
    """Whether channel O can act, and why not when it does not: the O-only row against the tracker
    (unseen trajectories, randomized) beside how far O's largest edit can move the tracker's action.

    O edits the object latent the tracker reads, ``f̃ = clip(f + λ·a, −1, 1)`` with ``a ∈ [−1, 1]^64``,
    so its largest edit has norm ``λ·√64``; a tracker whose action moves ``ρ`` per unit of latent
    (the latent smoothness of Fig. 12, :mod:`adadex.eval.latent_smoothness`) moves about ``ρ·λ·√64``
    under it, to set against T's largest edit, ``action_bound·√22``. A row whose difference's interval
    holds zero has no effect resolved.

    Args:
        table: the :func:`aggregate` structure (table1.json).
        rho_mean: the generalist tracker's mean ρ (action norm per unit latent norm).
        lambda_latent: O's step, :attr:`ModulationConfig.lambda_latent`.
        latent_dim: the latent's size (64).
        action_bound: T's bound per joint, :attr:`ModulationConfig.action_bound`.
        action_dim: the action's size (22).

    Returns:
        ``{"diff", "diff_ci95", "resolved", "o_reach", "t_reach", "rho_mean", "text"}`` (``diff`` in
        completion points; ``None`` without the O row or its paired difference).
    """
    row = table.get("unseen_trajectory", {}).get("randomized", {}).get("O", {})
    diff = (row.get("diff_vs_tracker") or {}).get("completion_pct")
    ci = (row.get("diff_vs_tracker_ci95") or {}).get("completion_pct")
    o_reach = float(rho_mean) * lambda_latent * latent_dim ** 0.5
    t_reach = action_bound * action_dim ** 0.5
    resolved = None if ci is None else not (ci[0] <= 0.0 <= ci[1])
    effect = ("no O row with a paired difference" if diff is None else
              f"O alone {diff:+.1f} completion points against the tracker"
              + ("" if ci is None else f" [{ci[0]:+.1f}, {ci[1]:+.1f}]")
              + (", an effect resolved" if resolved else ", no effect resolved" if resolved is False else ""))
    text = (f"**Channel O** (unseen trajectories, randomized): {effect}. The generalist's action moves "
            f"ρ = {rho_mean:.3f} per unit of latent (Fig. 12), so O's largest edit (λ = {lambda_latent:g} on "
            f"{latent_dim} latent entries) moves it about {o_reach:.3f} rad, against {t_reach:.3f} rad for T's "
            f"largest edit: O can act only as far as the tracker reads the latent.")
    return {"diff": diff, "diff_ci95": ci, "resolved": resolved, "o_reach": o_reach, "t_reach": t_reach,
            "rho_mean": float(rho_mean), "text": text}
