"""Plain data, no torch modules: references, reference datasets, recordings.

The names below are re-exported here (``from adadex.data import ReferenceDataset``) and imported on
first use.
"""

from typing import TYPE_CHECKING

from adadex._exports import lazy_exports

_EXPORTS = {
    "adadex.data.reference": ("ReferenceDataset", "Reference", "save_dataset", "is_dataset"),
    "adadex.data.build": ("build_dataset",),
    "adadex.data.presets": ("PRESETS",),
    "adadex.data.recording": ("Recording", "load_recording"),
    "adadex.data.retarget": ("Retargeter",),
    "adadex.data.synth": ("Synthesizer", "NoiseConfig"),
    "adadex.data.hoi_import": ("import_npz",),
}
__all__, __getattr__, __dir__ = lazy_exports(__name__, _EXPORTS)

if TYPE_CHECKING:      # the same names, for type checkers and IDEs
    from adadex.data.reference import ReferenceDataset, Reference, save_dataset, is_dataset
    from adadex.data.build import build_dataset
    from adadex.data.presets import PRESETS
    from adadex.data.recording import Recording, load_recording
    from adadex.data.retarget import Retargeter
    from adadex.data.synth import Synthesizer, NoiseConfig
    from adadex.data.hoi_import import import_npz
