"""The modulator: actor + critic that read the tracker's observation and output the modulation.

One flat action in [−1, 1]^D (``"action"``), D set by the channels that are on
(:class:`adadex.modules.channels.ModulationLayout`): a shared trunk and one head per active
channel, in the registry's order and sized by its record (:data:`adadex.modules.channels.CHANNELS`)
— R: reference residuals for the future offsets (hand joints 4×22; object pose 4×6, rotation as a
small rotation vector), O: a latent residual (64), T: an action residual (22).
Heads start near zero, so an untrained modulator leaves the tracker almost untouched.

* ``modulator.actor`` — in: ``"observation"``; out: ``"action"`` (D), ``"action_log_prob"``,
  ``("modulator", "loc")``, ``("modulator", "scale")``.
* ``modulator.critic`` — in: ``"observation"``; out: ``"state_value"``.

Use it on ``TransformedEnv(TrackingEnv(…), modulation(channels, tracker))`` with any TorchRL loss,
or with the tracker in one policy graph via :func:`adadex.transforms.policy.make_policy`.

Example
-------
>>> import torch
>>> from tensordict import TensorDict
>>> mod = Modulator("R+T", hidden=(64, 64))
>>> mod.layout.dim
134
>>> mod(TensorDict({"observation": torch.zeros(2, 273)}, batch_size=[2]))["action"].shape
torch.Size([2, 134])
"""

from __future__ import annotations

from collections.abc import Sequence

from adadex.envs.observation import OBS_DIM, OBSERVATION
from adadex.errors import check_number
from adadex.modules.channels import ModulationLayout
from adadex.modules.nets import ActorCritic, make_actor, make_critic


class Modulator(ActorCritic):
    """Actor + critic with one head per active channel (see the module docstring).

    Args:
        channels: ``"R+O+T"``, ``"R+T"``, … (not ``"none"``: no channel, no modulator).
        hidden: widths of the trunk / critic hidden layers.
        init_scale: initial exploration scale (pre-tanh).
        loc_bound: > 0 bounds the pre-tanh mean to ±loc_bound (see :class:`~adadex.modules.tracker.Tracker`).
    """

    kind = "modulator"

    def __init__(self, channels="R+O+T", hidden: Sequence[int] = (512, 256, 128), init_scale: float = 0.5,
                 loc_bound: float = 0.0):
        super().__init__()
        self.layout = ModulationLayout(channels)
        if not self.layout.dim:
            raise ValueError("a Modulator needs at least one channel (R, O or T); for 'none' use the tracker alone")
        check_number("Modulator.loc_bound", loc_bound)
        self.config = {"channels": self.layout.name, "hidden": list(hidden), "init_scale": float(init_scale),
                       "loc_bound": float(loc_bound)}
        self.actor = make_actor(OBSERVATION, OBS_DIM, self.layout.channel_sizes, -1.0, 1.0, hidden,
                                namespace="modulator", init_scale=init_scale, loc_bound=loc_bound)
        self.critic = make_critic(OBSERVATION, OBS_DIM, hidden)

    @property
    def channels(self) -> tuple[str, ...]:
        return self.layout.channels
