"""The modulator: actor + critic that read what the modulator sees and output the modulation.

One flat action in [−1, 1]^D (``"action"``), D set by the channels that are on
(:class:`adadex.modules.channels.ModulationLayout`): a shared trunk and one head per active
channel, in the registry's order and sized by its record (:data:`adadex.modules.channels.CHANNELS`)
— R: reference residuals for the future offsets (hand joints 4×22; object pose 4×6, rotation as a
small rotation vector), O: a latent residual (64), T: an action residual (22).
Heads start near zero, so an untrained modulator's mean leaves the tracker almost untouched, and
each channel explores with its own initial scale (the record's ``init_scale``), sized so that
*sampling* an untrained modulator leaves the tracker's success intact as well.

What it reads (``inputs``):

* ``"view"`` (the default) — ``("modulator", "view")``, :mod:`adadex.modules.modulator_view`: the
  tracker's observation plus the original reference and the errors against it, its accumulated
  edit, the object's start offset, the servo lag, its last action, the episode phase and the
  ``history`` previous frames. The env must carry the view's state:
  ``modulation(channels, tracker, view=modulator.view)`` for training, or
  :func:`adadex.transforms.policy.make_policy`'s primer.
* ``"observation"`` — the tracker's 273-D observation alone (checkpoints saved before the view).

* ``modulator.actor`` — in: its input; out: ``"action"`` (D), ``"action_log_prob"``,
  ``("modulator", "loc")``, ``("modulator", "scale")``.
* ``modulator.critic`` — in: its input; out: ``"state_value"``.

Use it on ``TransformedEnv(TrackingEnv(…), modulation(channels, tracker, view=modulator.view))`` with
any TorchRL loss, or with the tracker in one policy graph via :func:`adadex.transforms.policy.make_policy`.

Example
-------
>>> import torch
>>> from tensordict import TensorDict
>>> mod = Modulator("R+T", hidden=(64, 64), inputs="observation")
>>> mod.layout.dim
134
>>> mod(TensorDict({"observation": torch.zeros(2, 273)}, batch_size=[2]))["action"].shape
torch.Size([2, 134])
>>> Modulator("R+T", hidden=(64, 64)).obs_key, Modulator("R+T", hidden=(64, 64)).view.dim
(('modulator', 'view'), 871)
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

from adadex.envs.observation import OBS_DIM, OBSERVATION
from adadex.errors import ConfigError, check_number
from adadex.modules.channels import ModulationLayout
from adadex.modules.modulator_view import VIEW, ViewLayout
from adadex.modules.nets import ActorCritic, make_actor, make_critic

#: what a modulator may read (see the module docstring)
INPUTS = ("view", "observation")


def channel_scales(layout: ModulationLayout, init_scale=None) -> dict[str, float]:
    """Each active channel's initial exploration scale: the registry's (``None``), one number for
    all, or ``{channel: scale}`` over the registry's defaults.

    >>> channel_scales(ModulationLayout("R+T"), {"T": 0.2})["T"]
    0.2
    """
    if init_scale is None:
        init_scale = {}
    if isinstance(init_scale, Mapping):
        unknown = sorted(set(init_scale) - set(layout.channels))
        if unknown:
            raise ConfigError(f"Modulator.init_scale: channels {unknown} are not among {layout.name}")
        out = {c.name: float(init_scale.get(c.name, c.init_scale)) for c in layout.records}
    else:
        out = dict.fromkeys(layout.channels, float(init_scale))
    for c, v in out.items():
        check_number(f"Modulator.init_scale[{c}]", v, strict_low=True)
    return out


class Modulator(ActorCritic):
    """Actor + critic with one head per active channel (see the module docstring).

    Args:
        channels: ``"R+O+T"``, ``"R+T"``, … (not ``"none"``: no channel, no modulator).
        hidden: widths of the trunk / critic hidden layers.
        init_scale: initial exploration scale (pre-tanh): ``None`` — each channel's from the registry;
            a number for every channel; or ``{channel: scale}``.
        loc_bound: > 0 bounds the pre-tanh mean to ±loc_bound (see :class:`~adadex.modules.tracker.Tracker`).
        inputs: ``"view"`` or ``"observation"`` (see the module docstring).
        history: previous frames in the view.
    """

    kind = "modulator"

    def __init__(self, channels="R+O+T", hidden: Sequence[int] = (512, 256, 128), init_scale=None,
                 loc_bound: float = 0.0, inputs: str = "view", history: int = 3):
        super().__init__()
        self.layout = ModulationLayout(channels)
        if not self.layout.dim:
            raise ConfigError("a Modulator needs at least one channel (R, O or T); for 'none' use the tracker alone")
        check_number("Modulator.loc_bound", loc_bound)
        if inputs not in INPUTS:
            raise ConfigError(f"Modulator.inputs must be one of {INPUTS}, got {inputs!r}")
        scales = channel_scales(self.layout, init_scale)
        self.view = ViewLayout(self.layout.channels, history) if inputs == "view" else None
        self.obs_key, obs_dim = (VIEW, self.view.dim) if self.view is not None else (OBSERVATION, OBS_DIM)
        self.config = {"channels": self.layout.name, "hidden": list(hidden), "init_scale": scales,
                       "loc_bound": float(loc_bound), "inputs": inputs, "history": int(history)}
        self.actor = make_actor(self.obs_key, obs_dim, self.layout.channel_sizes, -1.0, 1.0, hidden,
                                namespace="modulator", init_scale=[scales[c] for c in self.layout.channels],
                                loc_bound=loc_bound)
        self.critic = make_critic(self.obs_key, obs_dim, hidden)

    @property
    def channels(self) -> tuple[str, ...]:
        return self.layout.channels

    @classmethod
    def upgrade_config(cls, config: dict) -> dict:
        """Checkpoints saved before the view read the tracker's observation alone."""
        config.setdefault("inputs", "observation")
        config.setdefault("history", 3)
        return config
