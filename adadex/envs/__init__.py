"""TorchRL environments: the batched tracking environment, its observation layout, reward and
domain randomization, and the chunked rollout loop of evaluation and teacher rollouts; importing
this package registers ``adadex/Tracking-v0`` with gymnasium.

The names below are re-exported here (``from adadex.envs import TrackingEnv, TrackingConfig``) and
imported on first use.
"""

from typing import TYPE_CHECKING

from adadex._exports import lazy_exports

from adadex.envs.registration import register as _register

_register()

_EXPORTS = {
    "adadex.envs.tracking": ("TrackingEnv", "TrackingConfig", "episode_references"),
    "adadex.envs.randomization": ("Randomization", "EffectRange", "ModelRandomizer"),
    "adadex.envs.reward": ("RewardConfig", "tracking_reward"),
    "adadex.envs.replay": ("replay_policy",),
    "adadex.envs.chunked": ("chunked_rollouts", "RolloutChunk", "chunk_seed"),
    "adadex.envs.frame_errors": ("Thresholds", "frame_success", "frame_tests", "object_success"),
    "adadex.envs.observation": ("OBS_DIM", "LATENT_DIM", "flat_observation",
                                "flat_from_tensordict"),
    "adadex.envs.latent": ("EncoderLatents", "encoder_latent", "fixed_object_latent"),
    "adadex.envs.gym": ("TrackingGymEnv",),
    "adadex.envs.registration": ("ENV_ID",),
}
__all__, __getattr__, __dir__ = lazy_exports(__name__, _EXPORTS)

if TYPE_CHECKING:      # the same names, for type checkers and IDEs
    from adadex.envs.tracking import TrackingEnv, TrackingConfig, episode_references
    from adadex.envs.randomization import Randomization, EffectRange, ModelRandomizer
    from adadex.envs.reward import RewardConfig, tracking_reward
    from adadex.envs.replay import replay_policy
    from adadex.envs.chunked import chunked_rollouts, RolloutChunk, chunk_seed
    from adadex.envs.frame_errors import Thresholds, frame_success, frame_tests, object_success
    from adadex.envs.observation import OBS_DIM, LATENT_DIM, flat_observation, flat_from_tensordict
    from adadex.envs.latent import EncoderLatents, encoder_latent, fixed_object_latent
    from adadex.envs.gym import TrackingGymEnv
    from adadex.envs.registration import ENV_ID
