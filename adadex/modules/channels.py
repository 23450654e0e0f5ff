"""Modulation channels: which are on, how large each may act, and where each lives in the modulator's action.

The modulator (:class:`adadex.modules.modulator.Modulator`) outputs one flat vector in [−1, 1]^D so
that any TorchRL loss can train it; :class:`ModulationLayout` says which slice belongs to which
channel, and the transforms (:mod:`adadex.transforms.modulation`) read their slice as a structured
entry under ``"modulation"``:

=====  ==============================  ==============  =====================================================
chan.  entry                           shape           meaning (after scaling by :class:`ModulationConfig`)
=====  ==============================  ==============  =====================================================
R      ``("modulation", "ref_hand")``    (…, 4, 22)    joint residual of the reference at t+1, t+2, t+4, t+12
R      ``("modulation", "ref_object")``  (…, 4, 6)     object residual there: position (3) + rotation vector (3)
O      ``("modulation", "latent")``      (…, 64)       residual of the object latent (f̃ = f + λ·a)
T      ``("modulation", "action")``      (…, 22)       residual added to the tracker's action
=====  ==============================  ==============  =====================================================

Channels are chosen by a string — ``"R+O+T"``, ``"R+T"``, ``"O"``, ``"none"`` … — so that an
ablation is a config value, never an edit of code.

Example
-------
>>> layout = ModulationLayout("R+T")
>>> layout.dim, layout.channels
(134, ('R', 'T'))
>>> [k for k, _, _ in layout.segments]
[('modulation', 'ref_hand'), ('modulation', 'ref_object'), ('modulation', 'action')]
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from adadex.envs.observation import LATENT_DIM, REF_OFFSETS
from adadex.errors import check_numbers
from adadex.sim.robot import NUM_JOINTS

CHANNELS = ("R", "O", "T")
FUTURE = len(REF_OFFSETS) - 1          # future offsets the R channel edits: t+1, t+2, t+4, t+12
HORIZON = max(REF_OFFSETS) + 1         # frames t … t+12 covered by the persistent reference edit

MOD = "modulation"
REF_HAND = (MOD, "ref_hand")
REF_OBJECT = (MOD, "ref_object")
LATENT = (MOD, "latent")
ACTION_RESIDUAL = (MOD, "action")
#: Persistent reference edit (state carried from step to step): joints, and object position + rotation vector,
#: for frames t … t+12.
HAND_EDIT = (MOD, "hand_edit")
OBJECT_EDIT = (MOD, "object_edit")
EDIT_SHAPES = {HAND_EDIT: (HORIZON, NUM_JOINTS), OBJECT_EDIT: (HORIZON, 6)}

_SHAPES = {REF_HAND: (FUTURE, NUM_JOINTS), REF_OBJECT: (FUTURE, 6), LATENT: (LATENT_DIM,),
           ACTION_RESIDUAL: (NUM_JOINTS,)}
_KEYS = {"R": (REF_HAND, REF_OBJECT), "O": (LATENT,), "T": (ACTION_RESIDUAL,)}


def parse_channels(channels: str | tuple | list) -> tuple[str, ...]:
    """``"R+O+T"`` / ``"T+R"`` / ``"none"`` / ``""`` / ``("R", "T")`` → channels in canonical order (R, O, T)."""
    if isinstance(channels, str):
        text = channels.strip()
        parts = [] if text.lower() in ("", "none") else [p.strip().upper() for p in text.replace(",", "+").split("+")]
    else:
        parts = [str(p).strip().upper() for p in channels]
    unknown = [p for p in parts if p not in CHANNELS]
    if unknown:
        raise ValueError(f"unknown modulation channel(s) {unknown} in {channels!r}; "
                         f"use a '+'-joined subset of {'/'.join(CHANNELS)} or 'none'")
    if len(set(parts)) != len(parts):
        raise ValueError(f"modulation channel repeated in {channels!r}")
    return tuple(c for c in CHANNELS if c in parts)


class ModulationLayout:
    """Where each active channel's entries sit in the modulator's flat action (see module docstring)."""

    def __init__(self, channels="R+O+T"):
        self.channels = parse_channels(channels)
        self.segments: list[tuple[tuple[str, str], slice, tuple[int, ...]]] = []
        start = 0
        for c in self.channels:
            for key in _KEYS[c]:
                shape = _SHAPES[key]
                size = math.prod(shape)
                self.segments.append((key, slice(start, start + size), shape))
                start += size
        self.dim = start

    @property
    def channel_sizes(self) -> list[int]:
        """Entries per active channel, in order (the modulator's head sizes)."""
        return [sum(math.prod(_SHAPES[k]) for k in _KEYS[c]) for c in self.channels]

    @property
    def name(self) -> str:
        return "+".join(self.channels) or "none"

    def __contains__(self, channel: str) -> bool:
        return channel in self.channels

    def split(self, flat):
        """``(…, D)`` tensor → {entry key: (…, *shape) tensor} for the active channels."""
        if flat.shape[-1] != self.dim:
            raise ValueError(f"modulation action for channels {self.name} must have {self.dim} entries, "
                             f"got shape {tuple(flat.shape)}")
        lead = flat.shape[:-1]
        return {key: flat[..., sl].reshape(*lead, *shape) for key, sl, shape in self.segments}

    def __repr__(self) -> str:
        return f"ModulationLayout({self.name!r}, dim={self.dim})"


def entry_shape(key) -> tuple[int, ...]:
    """Shape (without batch dims) of a modulation entry."""
    return _SHAPES[key]


@dataclass(frozen=True)
class ModulationConfig:
    """How far each channel may move things (rad, m). The modulator's outputs are in [−1, 1] and
    are clamped there before scaling, so these are hard bounds per step.

    * ``lambda_hand`` — λ_hand, joint reference residual per step (rad);
    * ``lambda_object_pos`` / ``lambda_object_rot`` — λ_object, object reference residual per step (m, rad);
    * ``persistent`` — the R edits stay in the future reference as the episode moves on (PAPER.md
      decision); ``False`` edits the reference for the current step only;
    * ``lambda_latent`` — λ_latent: f̃ = clip(f + λ·a, −1, 1) (the latent is tanh-bounded). The
      shipped encoder's latents differ between objects by about 0.2 per entry (RMS), so 0.25 lets
      the modulator move the latent about one object's width per step;
    * ``action_bound`` — the T residual added to the tracker's action is in [−bound, bound] (rad).
    """

    lambda_hand: float = 0.05
    lambda_object_pos: float = 0.02
    lambda_object_rot: float = 0.1
    persistent: bool = True
    lambda_latent: float = 0.25
    action_bound: float = 0.05

    def __post_init__(self):
        check_numbers("ModulationConfig", self,
                      ("lambda_hand", "lambda_object_pos", "lambda_object_rot", "lambda_latent", "action_bound"))
