"""Policy components as TensorDictModules: the point-cloud encoder (object latent), the tracker
(specialist / generalist actor + critic) and the modulator (R/O/T heads).

The names below are re-exported here (``from adadex.modules import Tracker, Modulator``) and imported
on first use.
"""

from typing import TYPE_CHECKING

from adadex._exports import lazy_exports

_EXPORTS = {
    "adadex.modules.tracker": ("Tracker", "ReplayBounds"),
    "adadex.modules.modulator": ("Modulator",),
    "adadex.modules.encoder": ("PointCloudEncoder", "PointCloudAutoencoder", "EncoderConfig",
                               "load_encoder", "save_encoder", "object_latents",
                               "surface_points", "chamfer_distance"),
    "adadex.modules.channels": ("ModulationLayout", "Channel", "parse_channels"),
    "adadex.modules.anchor": ("ObjectAnchor", "PalmShift"),
    "adadex.modules.nets": ("ActorCritic", "make_actor", "make_critic", "GaussianHeads",
                            "Normalizer", "SamplingPolicy", "fit_normalizers", "make_core",
                            "recurrent_state_shapes"),
}
__all__, __getattr__, __dir__ = lazy_exports(__name__, _EXPORTS)

if TYPE_CHECKING:      # the same names, for type checkers and IDEs
    from adadex.modules.tracker import Tracker, ReplayBounds
    from adadex.modules.modulator import Modulator
    from adadex.modules.encoder import (
        PointCloudEncoder, PointCloudAutoencoder, EncoderConfig, load_encoder, save_encoder, object_latents,
        surface_points, chamfer_distance
    )
    from adadex.modules.channels import ModulationLayout, Channel, parse_channels
    from adadex.modules.anchor import ObjectAnchor, PalmShift
    from adadex.modules.nets import (
        ActorCritic, make_actor, make_critic, GaussianHeads, Normalizer, SamplingPolicy, fit_normalizers, make_core,
        recurrent_state_shapes
    )
