"""Result tables and plots over several evaluations (the paper's Table 1 layout).

:func:`results_table` turns ``{name: summary}`` (summaries from :func:`adadex.eval.evaluate.evaluate`)
into a Markdown table — success (mean-error / completion, %, the paper's), the object-centric object
completion and carried (%, :mod:`adadex.eval.metrics`; "—" for a summary stored without them), T_o
and T_h (cm), R_o and R_h (rad), E_finger (rad) — and :func:`plot_results` draws the success rates
side by side.

Example
-------
>>> row = {"success_mean_error_pct": 50.0, "completion_pct": 60.0, "T_o": 3.0, "R_o": 0.2, "T_h": 2.0,
...        "R_h": 0.1, "E_finger": 0.05, "trajectories": 10, "object_completion_pct": 40.0, "carried_pct": 30.0}
>>> print(results_table({"tracker": row}).splitlines()[2])
| tracker | 10 | 50.0 / 60.0 | 40.0 / 30.0 | 3.00 | 0.200 | 2.00 | 0.100 | 0.050 |
"""

from __future__ import annotations

import math

from adadex.io import atomic_write

_COLUMNS = ("policy", "refs", "success % (mean-err / compl.)", "object % (compl. / carried)", "T_o cm", "R_o rad",
            "T_h cm", "R_h rad", "E_finger rad")


def _pct(s: dict, key: str) -> str:
    v = s.get(key)
    return "—" if v is None or not math.isfinite(v) else f"{v:.1f}"


def results_table(results: dict[str, dict]) -> str:
    """Markdown table, one row per named summary, in the given order.

    Args:
        results: ``{name: summary}``, each a :func:`~adadex.eval.metrics.summarize` result.
    """
    lines = ["| " + " | ".join(_COLUMNS) + " |", "|" + "---|" * len(_COLUMNS)]
    for name, s in results.items():
        lines.append(f"| {name} | {s['trajectories']} | {s['success_mean_error_pct']:.1f} / {s['completion_pct']:.1f} | "
                     f"{_pct(s, 'object_completion_pct')} / {_pct(s, 'carried_pct')} | {s['T_o']:.2f} | "
                     f"{s['R_o']:.3f} | {s['T_h']:.2f} | {s['R_h']:.3f} | {s['E_finger']:.3f} |")
    return "\n".join(lines)


def plot_results(results: dict[str, dict], path, title: str = "") -> None:
    """Grouped bars of both success rates per named summary, saved as a PNG.

    Args:
        results: ``{name: summary}``, each a :func:`~adadex.eval.metrics.summarize` result.
        path: the PNG file to write (atomically).
        title: the plot's title (default none).
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    names = list(results)
    x = np.arange(len(names))
    fig, ax = plt.subplots(figsize=(max(5, 1.2 * len(names) + 2), 3.6))
    for off, key, label in ((-0.2, "success_mean_error_pct", "mean-error"), (0.2, "completion_pct", "completion")):
        vals = [results[n][key] for n in names]
        bars = ax.bar(x + off, vals, width=0.4, label=label)
        ax.bar_label(bars, fmt="%.0f", fontsize=8)
    ax.set_xticks(x, names, rotation=20 if max(map(len, names)) > 12 else 0, ha="right" if max(map(len, names)) > 12 else "center")
    ax.set_ylabel("success %")
    ax.set_ylim(0, 105)
    ax.legend()
    ax.set_title(title)
    fig.tight_layout()
    atomic_write(path, lambda f: fig.savefig(f, format="png", dpi=110))
    plt.close(fig)
