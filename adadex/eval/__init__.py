"""Evaluation: the paper's metrics, tables and loops.

The names below are re-exported here (``from adadex.eval import evaluate, summarize``) and imported
on first use.
"""

from typing import TYPE_CHECKING

from adadex._exports import lazy_exports

_EXPORTS = {
    "adadex.eval.evaluate": ("evaluate", "format_summary"),
    "adadex.eval.metrics": ("trajectory_metrics", "summarize", "from_rollout", "with_units"),
    "adadex.eval.paired": ("paired_bootstrap", "bootstrap_mean"),
    "adadex.eval.table1": ("aggregate", "table_markdown"),
    "adadex.eval.tables": ("results_table", "plot_results"),
    "adadex.eval.latent_smoothness": ("latent_smoothness",),
    "adadex.eval.reward_check": ("return_metric_spearman",),
}
__all__, __getattr__, __dir__ = lazy_exports(__name__, _EXPORTS)

if TYPE_CHECKING:      # the same names, for type checkers and IDEs
    from adadex.eval.evaluate import evaluate, format_summary
    from adadex.eval.metrics import trajectory_metrics, summarize, from_rollout, with_units
    from adadex.eval.paired import paired_bootstrap, bootstrap_mean
    from adadex.eval.table1 import aggregate, table_markdown
    from adadex.eval.tables import results_table, plot_results
    from adadex.eval.latent_smoothness import latent_smoothness
    from adadex.eval.reward_check import return_metric_spearman
