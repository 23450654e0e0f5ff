"""TorchRL transforms for the modulation channels — reference (R), its lead (L), its compact form (C),
the object-anchor reach (A), object latent (O), action (T), feedback gain (K) — the tracker-in-the-loop
transform that turns a TrackingEnv into the modulator's env, the modulated policy graph, and the object
point clouds its encoder reads.

The names below are re-exported here (``from adadex.transforms import modulation, make_policy``) and
imported on first use.
"""

from typing import TYPE_CHECKING

from adadex._exports import lazy_exports

_EXPORTS = {
    "adadex.transforms.modulation": ("modulation", "channel_transforms", "ReferenceModulation",
                                     "LatentModulation", "ActionModulation",
                                     "CompactModulation", "AnchorReach", "ReferenceLead", "GainModulation",
                                     "read_ahead", "move_visible_reference", "ChannelTransform",
                                     "TrackerInTheLoop", "FlatModulationAction",
                                     "ModulatorView"),
    "adadex.transforms.policy": ("make_policy", "ModulatedPolicy", "state_primer"),
    "adadex.transforms.object_points": ("ObjectPoints",),
}
__all__, __getattr__, __dir__ = lazy_exports(__name__, _EXPORTS)

if TYPE_CHECKING:      # the same names, for type checkers and IDEs
    from adadex.transforms.modulation import (
        modulation, channel_transforms, ReferenceModulation, LatentModulation, ActionModulation,
        CompactModulation, AnchorReach, ReferenceLead, GainModulation, read_ahead, move_visible_reference,
        ChannelTransform, TrackerInTheLoop, FlatModulationAction, ModulatorView
    )
    from adadex.transforms.policy import make_policy, ModulatedPolicy, state_primer
    from adadex.transforms.object_points import ObjectPoints
