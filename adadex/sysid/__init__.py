"""The model-versus-measurement workbench: replay, compare, localize, diagnose, fit, report.

The names below are re-exported here (``from adadex.sysid import diagnose, fit_patch``) and imported
on first use.
"""

from typing import TYPE_CHECKING

from adadex._exports import lazy_exports

_EXPORTS = {
    "adadex.sysid.replay": ("Replayer",),
    "adadex.sysid.excite": ("design_excitation", "simulate_recording", "ExcitationPlan"),
    "adadex.sysid.compare": ("compare", "localize", "Comparison"),
    "adadex.sysid.diagnose": ("diagnose", "Diagnosis"),
    "adadex.sysid.fit": ("fit_patch", "identify_pd"),
    "adadex.sysid.report": ("write_report",),
    "adadex.sysid.demo": ("run_demo",),
}
__all__, __getattr__, __dir__ = lazy_exports(__name__, _EXPORTS)

if TYPE_CHECKING:      # the same names, for type checkers and IDEs
    from adadex.sysid.replay import Replayer
    from adadex.sysid.excite import design_excitation, simulate_recording, ExcitationPlan
    from adadex.sysid.compare import compare, localize, Comparison
    from adadex.sysid.diagnose import diagnose, Diagnosis
    from adadex.sysid.fit import fit_patch, identify_pd
    from adadex.sysid.report import write_report
    from adadex.sysid.demo import run_demo
