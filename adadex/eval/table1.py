"""The paper's Table 1 over training seeds: means, 95 % intervals, and the Markdown table.

:func:`aggregate` takes one evaluation summary (:func:`adadex.eval.metrics.summarize`) per seed for
each (split, condition, row) and returns ``{split: {condition: {row: {metric: mean,
metric_ci95: [lo, hi] | None, "seeds": n}}}}`` with the metrics ``T_o``, ``R_o``, ``T_h``, ``R_h``
(cm, rad), ``E_finger`` (rad), ``mean_error_pct`` and ``completion_pct`` (success, %). The interval
is Student's t over the seeds (``None`` with one seed: one run says nothing about the spread).
:func:`table_markdown` writes it as the paper lays it out, one table per split and condition.

>>> s = lambda c: {"T_o": 2.0, "R_o": 0.1, "T_h": 1.0, "R_h": 0.1, "E_finger": 0.05,
...                "success_mean_error_pct": 60.0, "completion_pct": c, "trajectories": 10}
>>> t = aggregate({("unseen_trajectory", "nominal", "tracker"): [s(50.0), s(60.0), s(70.0)]})
>>> row = t["unseen_trajectory"]["nominal"]["tracker"]
>>> row["completion_pct"], [round(v, 1) for v in row["completion_pct_ci95"]], row["seeds"]
(60.0, [35.2, 84.8], 3)
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence

import numpy as np

#: metric in table1.json → key of an evaluation summary
METRICS = {"T_o": "T_o", "R_o": "R_o", "T_h": "T_h", "R_h": "R_h", "E_finger": "E_finger",
           "mean_error_pct": "success_mean_error_pct", "completion_pct": "completion_pct"}
SPLITS = ("unseen_trajectory", "unseen_object")
CONDITIONS = ("nominal", "randomized")
ROWS = ("replay", "ppo", "il_rl", "tracker", "R", "RT", "ROT", "O")
ROW_LABELS = {"replay": "kinematic replay", "ppo": "PPO", "il_rl": "IL+RL (DexTrack-style)", "tracker": "tracker",
              "R": "+R", "RT": "+R+T", "ROT": "+R+O+T", "O": "O only"}


def ci95(values: Sequence[float]) -> list[float] | None:
    """Student-t 95 % interval of the mean of ``values`` (``None`` for fewer than two finite values)."""
    from scipy import stats

    v = np.asarray([x for x in values if math.isfinite(x)], dtype=np.float64)
    if len(v) < 2:
        return None
    half = float(stats.t.ppf(0.975, len(v) - 1) * v.std(ddof=1) / math.sqrt(len(v)))
    m = float(v.mean())
    return [m - half, m + half]


def aggregate(summaries: Mapping[tuple[str, str, str], Sequence[dict]]) -> dict:
    """``{(split, condition, row): [summary per seed]}`` → the table1.json structure (module docstring)."""
    out: dict = {}
    for (split, condition, row), per_seed in summaries.items():
        entry = {"seeds": len(per_seed)}
        for name, key in METRICS.items():
            vals = [float(s[key]) for s in per_seed]
            finite = [v for v in vals if math.isfinite(v)]
            entry[name] = float(np.mean(finite)) if finite else math.nan
            entry[f"{name}_ci95"] = ci95(vals)
        out.setdefault(split, {}).setdefault(condition, {})[row] = entry
    return out


def _cell(entry: dict, name: str, fmt: str) -> str:
    ci = entry.get(f"{name}_ci95")
    text = format(entry[name], fmt)
    return text if ci is None else f"{text} ± {format((ci[1] - ci[0]) / 2, fmt)}"


def table_markdown(table: dict, *, title: str = "Table 1") -> str:
    """The table as Markdown: one block per split and condition, rows in :data:`ROWS` order, each
    cell the mean over seeds ± the half-width of its 95 % interval."""
    lines = [f"# {title}", "",
             "Success (%): mean-error / completion. Errors: T_o, T_h in cm; R_o, R_h, E_finger in rad. "
             "Mean over training seeds ± half-width of the Student-t 95 % interval (none with one seed).", ""]
    for split in SPLITS:
        for condition in CONDITIONS:
            rows = table.get(split, {}).get(condition)
            if not rows:
                continue
            lines += [f"## {split.replace('_', ' ')}, {condition}", "",
                      "| method | seeds | success mean-error % | success completion % | T_o | R_o | T_h | R_h | E_finger |",
                      "|---|---|---|---|---|---|---|---|---|"]
            for row in [r for r in ROWS if r in rows] + [r for r in rows if r not in ROWS]:
                e = rows[row]
                lines.append(f"| {ROW_LABELS.get(row, row)} | {e['seeds']} | {_cell(e, 'mean_error_pct', '.1f')} | "
                             f"{_cell(e, 'completion_pct', '.1f')} | {_cell(e, 'T_o', '.2f')} | "
                             f"{_cell(e, 'R_o', '.3f')} | {_cell(e, 'T_h', '.2f')} | {_cell(e, 'R_h', '.3f')} | "
                             f"{_cell(e, 'E_finger', '.3f')} |")
            lines.append("")
    return "\n".join(lines)
