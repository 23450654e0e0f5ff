"""Modulation channels: ONE registry of what each channel is, which are on, how large each may act,
and where each lives in the modulator's action.

The modulator (:class:`adadex.modules.modulator.Modulator`) outputs one flat vector in [−1, 1]^D so
that any TorchRL loss can train it; :class:`ModulationLayout` says which slice belongs to which
channel, and the transforms (:mod:`adadex.transforms.modulation`) read their slice as a structured
entry under ``"modulation"``:

=====  ==============================  ==============  =====================================================
chan.  entry                           shape           meaning (after scaling by :class:`ModulationConfig`)
=====  ==============================  ==============  =====================================================
R      ``("modulation", "ref_hand")``    (…, 4, 22)    joint residual of the reference at t+1, t+2, t+4, t+12
R      ``("modulation", "ref_object")``  (…, 4, 6)     object residual there: position (3) + rotation vector (3)
L      ``("modulation", "lead")``        (…, 2)        how far ahead in time the visible reference is read (arm, hand)
C      ``("modulation", "palm")``        (…, 3)        palm position offset of the whole visible reference (compact R)
C      ``("modulation", "grip")``        (…, 4)        closure of each finger's flexion joints there (compact R)
A      ``("modulation", "reach")``       (…, 1)        how far the visible reference's palm moves onto the object where it lies
O      ``("modulation", "latent")``      (…, 64)       residual of the object latent (f̃ = f + λ·a)
T      ``("modulation", "action")``      (…, 22)       residual added to the tracker's action
K      ``("modulation", "gain")``        (…, 2)        feedback gain on the joints' tracking error (arm, hand)
=====  ==============================  ==============  =====================================================

The registry
------------
:data:`CHANNELS` maps each channel's name to its :class:`Channel` record: its action entries (keys
and shapes), the state it may carry between steps (keys and shapes), its config fields (λ's and
bounds, with defaults and docs), what it edits (the tracker's observation, so it runs before the
tracker on the inverse path, or the tracker's action, after it) and — bound by
:mod:`adadex.transforms.modulation`, the layer above — its transform class. The records' order is
the channels' order everywhere: in channel strings, in the flat action, in the modulator's heads and
on the inverse path within each side of the tracker. :class:`ModulationLayout`, :func:`parse_channels`,
:class:`ModulationConfig` (built from the records' fields), the modulator's heads,
:func:`adadex.transforms.modulation.modulation` and :func:`adadex.transforms.policy.make_policy` all
loop over it; none of them names a channel.

**Adding a channel touches one place**: one more :class:`Channel` record in :data:`CHANNELS` below
(its position is its place in the order). Its behaviour is then its transform class — a
:class:`adadex.transforms.modulation.ChannelTransform` subclass declared with ``channel="X"``
(beside R, L, C, A, O, T and K in :mod:`adadex.transforms.modulation`), which binds itself to the record.

Channels are chosen by a string — ``"R+O+T"``, ``"R+T"``, ``"O"``, ``"none"`` … — so that an
ablation is a config value, never an edit of code.

Example
-------
>>> layout = ModulationLayout("R+T")
>>> layout.dim, layout.channels
(134, ('R', 'T'))
>>> [k for k, _, _ in layout.segments]
[('modulation', 'ref_hand'), ('modulation', 'ref_object'), ('modulation', 'action')]
>>> CHANNELS["O"].size, CHANNELS["O"].edits, [f.name for f in CHANNELS["O"].fields]
(64, 'observation', ['lambda_latent'])
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping
from dataclasses import dataclass
from types import MappingProxyType

from adadex.envs.observation import LATENT_DIM, REF_OFFSETS
from adadex.errors import ArrayError, ConfigError, UnknownKeyError, check_numbers
from adadex.sim.robot import NUM_JOINTS

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

#: The compact channel C: a palm position offset (3) and one closure per finger (index, middle, ring, thumb)
PALM = (MOD, "palm")
GRIP = (MOD, "grip")
#: The anchor-reach channel A: one number, how far the reference's palm moves onto the object where it lies,
#: and the reach it latched at the episode's first step (weight, latched flag)
REACH = (MOD, "reach")
REACH_STATE = (MOD, "reach_state")
#: The lead channel L: how far ahead the visible reference is read, arm and hand apart, and the lead it
#: latched at the episode's first step (arm, hand, latched flag)
LEAD = (MOD, "lead")
LEAD_STATE = (MOD, "lead_state")
#: The gain channel K: a feedback gain on the joints' tracking error, arm and hand apart, and the gains it
#: latched at the episode's first step (arm, hand, latched flag)
GAIN = (MOD, "gain")
GAIN_STATE = (MOD, "gain_state")
#: per finger of GRIP, the flexion joints it closes
GRIP_JOINTS = (("if_mcp", "if_pip", "if_dip"), ("mf_mcp", "mf_pip", "mf_dip"), ("rf_mcp", "rf_pip", "rf_dip"),
               ("th_mcp", "th_ipl"))

#: What a channel edits: the tracker's observation (before the tracker on the inverse path) or its action (after).
EDITS = ("observation", "action")


@dataclass(frozen=True)
class Field:
    """One config field of a channel (a field of :class:`ModulationConfig`): name, default, meaning.
    Number fields are checked ≥ 0 and finite (below ``below`` where it is set, one of ``choices`` where
    those are set); boolean fields are switches."""

    name: str
    default: float | bool
    doc: str
    below: float | None = None
    choices: tuple | None = None


@dataclass(frozen=True)
class Channel:
    """One modulation channel's record in :data:`CHANNELS` (see the module docstring).

    Its transform class is :attr:`transform`, bound by :mod:`adadex.transforms.modulation`.

    Attributes:
        name: its letter in channel strings (``"R"``).
        title: what it modulates, in words.
        entries: ``((key, shape), …)``: its part of the modulator's action, in flat order, each in [−1, 1].
        fields: its :class:`Field` s of :class:`ModulationConfig`.
        edits: ``"observation"`` (what the tracker reads: runs before the tracker on the inverse
            path) or ``"action"`` (the tracker's output: runs after it); others raise ``ValueError``.
        state: ``((key, shape), …)``: entries it may carry from step to step (zero at reset;
            default none).
        init_scale: the modulator's initial exploration scale (pre-tanh) on this channel's head
            (default 0.5): sampling an untrained modulator must leave the tracker's success intact,
            so each channel's is sized to what its edits cost (``python
            benchmarks/modulator_usage.py --init-check``: around kinematic replay on the
            planned-grasp ``small`` dataset under Table 3, 188 paired episodes, sampling at 0.5 cost
            R 18.0 and T 6.8 completion points, C at 0.1 cost 7.8; R 0.05 (+0.6), T 0.2 (+1.0) and C
            0.03 (+3.6) are within the ±4-point noise of 188 episodes, while R 0.2 (−6.4) and C 0.1
            are not; docs/modulation.md); O keeps 0.5 (around kinematic replay it acts on nothing;
            around the pipeline's generalist it changed nothing measurable at 0.5).
        latch: for a channel whose action is a choice held for the episode (A, L, K): the name of
            its config switch (one of its ``fields``) that latches the choice at the episode's first
            step; ``""`` (default) for a per-step channel.
    """

    name: str
    title: str
    entries: tuple[tuple[tuple[str, str], tuple[int, ...]], ...]
    fields: tuple[Field, ...]
    edits: str
    state: tuple[tuple[tuple[str, str], tuple[int, ...]], ...] = ()
    init_scale: float = 0.5
    latch: str = ""

    def __post_init__(self):
        if self.edits not in EDITS:
            raise ValueError(f"channel {self.name}: edits must be one of {EDITS}, got {self.edits!r}")
        if self.latch and self.latch not in {f.name for f in self.fields}:
            raise ValueError(f"channel {self.name}: its latch switch {self.latch!r} is not one of its fields")

    @property
    def keys(self) -> tuple[tuple[str, str], ...]:
        """Its action entries' keys, in flat order."""
        return tuple(k for k, _ in self.entries)

    @property
    def size(self) -> int:
        """Entries in the flat action (the size of its modulator head)."""
        return sum(math.prod(shape) for _, shape in self.entries)

    @property
    def transform(self) -> type:
        """Its transform class (``cls(config)`` builds it), once :mod:`adadex.transforms.modulation` is imported."""
        cls = _TRANSFORMS.get(self.name)
        if cls is None:
            raise LookupError(f"modulation channel {self.name} has no transform bound; import "
                              "adadex.transforms.modulation (or the module defining its ChannelTransform)")
        return cls


def _registry(*channels: Channel) -> Mapping[str, Channel]:
    names = [c.name for c in channels]
    keys = [k for c in channels for k, _ in (*c.entries, *c.state)]
    fields = [f.name for c in channels for f in c.fields]
    for what, items in (("name", names), ("tensordict key", keys), ("config field", fields)):
        if len(set(items)) != len(items):
            raise ValueError(f"modulation channels: a {what} is used twice in {items}")
    return MappingProxyType({c.name: c for c in channels})


#: THE registry of modulation channels, in their order (see the module docstring). A new channel is one more record.
CHANNELS: Mapping[str, Channel] = _registry(
    Channel("R", "future reference (hand joints, object pose)",
            entries=((REF_HAND, (FUTURE, NUM_JOINTS)), (REF_OBJECT, (FUTURE, 6))),
            state=((HAND_EDIT, (HORIZON, NUM_JOINTS)), (OBJECT_EDIT, (HORIZON, 6))),
            fields=(Field("lambda_hand", 0.05, "λ_hand, joint reference residual per step (rad)"),
                    Field("lambda_object_pos", 0.02, "λ_object, object reference position residual per step (m)"),
                    Field("lambda_object_rot", 0.1, "λ_object, object reference rotation residual per step (rad)"),
                    Field("persistent", True, "the R edits stay in the future reference as the episode moves on "
                                              "(AdaDexTrack's reference modulation: ŝ_{t+k} ← ŝ_{t+k} + λ·a every "
                                              "step); ``False`` edits the reference for the current step only")),
            edits="observation", init_scale=0.05),
    Channel("L", "reference lead: the visible reference read ahead in time, the arm's and the hand's joints apart "
                 "(the feed-forward that takes back a servo's delay or lag)",
            entries=((LEAD, (2,)),),
            state=((LEAD_STATE, (3,)),),
            fields=(Field("max_lead", 2.0, "the visible reference is read up to this many control steps ahead "
                                           "(at 12 Hz one step is 83 ms): lead = max_lead · clip(a, 0, 1), the arm's "
                                           "joints (and the object's reference) by the first entry, the hand's by "
                                           "the second"),
                    Field("lead_latched", True, "the lead chosen at an episode's first step holds for the whole "
                                                "episode (a servo's delay is the robot's, not the moment's); "
                                                "``False`` chooses it anew every step")),
            edits="observation", init_scale=1.0, latch="lead_latched"),
    Channel("C", "compact reference edit: palm position offset (through the arm Jacobian) and grip",
            entries=((PALM, (3,)), (GRIP, (len(GRIP_JOINTS),))),
            fields=(Field("lambda_palm", 0.10, "λ_palm: the palm of the whole visible reference moves by up to "
                                              "this far (m) per axis, the arm joints solved through the palm's "
                                              "Jacobian; Table 3 displaces the object by N(0, 5 cm) per axis"),
                    Field("lambda_grip", 0.3, "λ_grip: each finger's flexion joints (index, middle, ring: mcp, pip, "
                                              "dip; thumb: mcp, ipl) of the visible reference close (+) or open (−) "
                                              "by up to this much (rad)")),
            edits="observation", init_scale=0.03),
    Channel("A", "object-anchor reach: the visible reference's palm moved onto the object where it lies, by a "
                 "chosen fraction of the anchor's shift",
            entries=((REACH, (1,)),),
            state=((REACH_STATE, (2,)),),
            fields=(Field("reach_latched", True, "the reach chosen at an episode's first step holds for the whole "
                                                 "episode (an episode-level decision: reach for the displaced object "
                                                 "or not); ``False`` chooses it anew every step"),
                    Field("reach_smooth", False, "the reach is w = (1 + a) / 2, every action a distinct reach, "
                                                 "instead of w = clip(0.5 + a, 0, 1), flat past |a| = 0.5 (where "
                                                 "a policy that reaches fully samples no smaller reach)"),
                    Field("reach_lookahead", 1, "control steps ahead at which the anchor reads the reference "
                                                "object's travel (its hold and release; one of the observation's "
                                                "frames ahead, 1, 2, 4 or 12): further ahead, the hand starts "
                                                "bringing the object back onto the reference path before the "
                                                "reference moves it, ahead of the servos' lag",
                          choices=REF_OFFSETS[1:])),
            edits="observation", init_scale=1.0, latch="reach_latched"),
    Channel("O", "object latent",
            entries=((LATENT, (LATENT_DIM,)),),
            fields=(Field("lambda_latent", 0.25, "λ_latent: f̃ = clip(f + λ·a, −1, 1) (the latent is tanh-bounded). "
                                                 "The shipped encoder's latents differ between objects by about 0.2 "
                                                 "per entry (RMS), so 0.25 lets the modulator move the latent about "
                                                 "one object's width per step"),),
            edits="observation"),
    Channel("T", "tracker action",
            entries=((ACTION_RESIDUAL, (NUM_JOINTS,)),),
            fields=(Field("action_bound", 0.05, "the T residual added to the tracker's action is in "
                                                "[−bound, bound] (rad)"),),
            edits="action", init_scale=0.2),
    Channel("K", "feedback gain: the tracker's action corrected by a gain times each joint's tracking error, the "
                 "arm's and the hand's joints apart (the stiffness a soft or loaded servo lacks)",
            entries=((GAIN, (2,)),),
            state=((GAIN_STATE, (3,)),),
            fields=(Field("max_gain", 2.0, "the gain is g = max_gain · clip(a, −max_softening / max_gain, 1): the action "
                                           "gains clip(g · (reference − joint position), ±gain_bound) at the current "
                                           "frame"),
                    Field("max_softening", 0.0, "the lowest gain is −max_softening (< 1): a negative gain softens "
                                                "the servo to kp × (1 + g) (a grip softer than the model's knocks "
                                                "the object less, docs/sim2real.md); 0: the gain only stiffens",
                          below=1.0),
                    Field("gain_bound", 0.1, "the gain's correction of each joint's target is within ±this (rad)"),
                    Field("gain_latched", True, "the gains chosen at an episode's first step hold for the whole "
                                                "episode (a servo's softness is the robot's, not the moment's); "
                                                "``False`` chooses them anew every step")),
            edits="action", init_scale=1.0, latch="gain_latched"),
)

_TRANSFORMS: dict[str, type] = {}      # channel name → transform class, filled by bind_transform


def bind_transform(channel: str, cls: type) -> Channel:
    """Bind ``cls`` as the transform of ``channel`` (called by ``ChannelTransform`` subclasses); returns the record."""
    if channel not in CHANNELS:
        raise ValueError(f"{cls.__name__}: no modulation channel {channel!r} in the registry "
                         f"({'/'.join(CHANNELS)}); add its Channel record to adadex.modules.channels.CHANNELS")
    bound = _TRANSFORMS.get(channel)
    if bound is not None and (bound.__module__, bound.__qualname__) != (cls.__module__, cls.__qualname__):
        raise ValueError(f"modulation channel {channel} already has the transform {bound.__qualname__}")
    _TRANSFORMS[channel] = cls
    return CHANNELS[channel]


def parse_channels(channels: str | tuple | list) -> tuple[str, ...]:
    """``"R+O+T"`` / ``"T+R"`` / ``"none"`` / ``""`` / ``("R", "T")`` → channels in canonical order (R, L, C, A, O, T, K).

    Args:
        channels: ``"+"``- (or ``","``-) joined channel letters, case-insensitive, or a sequence of
            them; ``"none"`` or ``""``: no channel. An unknown or repeated channel raises
            :class:`~adadex.errors.ConfigError`.

    Examples:
        >>> parse_channels("t+r"), parse_channels("none")
        (('R', 'T'), ())
    """
    if isinstance(channels, str):
        text = channels.strip()
        parts = [] if text.lower() in ("", "none") else [p.strip().upper() for p in text.replace(",", "+").split("+")]
    else:
        parts = [str(p).strip().upper() for p in channels]
    unknown = [p for p in parts if p not in CHANNELS]
    if unknown:
        raise ConfigError(f"unknown modulation channel(s) {unknown} in {channels!r}; "
                          f"use a '+'-joined subset of {'/'.join(CHANNELS)} or 'none'")
    if len(set(parts)) != len(parts):
        raise ConfigError(f"modulation channel repeated in {channels!r}")
    return tuple(c for c in CHANNELS if c in parts)


class ModulationLayout:
    """Where each active channel's entries sit in the modulator's flat action (see module docstring).

    Args:
        channels: the active channels, as :func:`parse_channels` takes them (default ``"R+O+T"``).

    Examples:
        >>> layout = ModulationLayout("T+R")
        >>> layout, layout.channel_sizes
        (ModulationLayout('R+T', dim=134), [112, 22])
    """

    def __init__(self, channels="R+O+T"):
        self.channels = parse_channels(channels)
        self.segments: list[tuple[tuple[str, str], slice, tuple[int, ...]]] = []
        start = 0
        for channel in self.records:
            for key, shape in channel.entries:
                size = math.prod(shape)
                self.segments.append((key, slice(start, start + size), shape))
                start += size
        self.dim = start

    @property
    def records(self) -> tuple[Channel, ...]:
        """The active channels' :class:`Channel` records, in order."""
        return tuple(CHANNELS[c] for c in self.channels)

    @property
    def channel_sizes(self) -> list[int]:
        """Entries per active channel, in order (the modulator's head sizes)."""
        return [c.size for c in self.records]

    @property
    def name(self) -> str:
        return "+".join(self.channels) or "none"

    def __contains__(self, channel: str) -> bool:
        return channel in self.channels

    def split(self, flat):
        """``(…, D)`` tensor → {entry key: (…, *shape) tensor} for the active channels."""
        if flat.shape[-1] != self.dim:
            raise ArrayError(f"modulation action for channels {self.name} must have {self.dim} entries, "
                             f"got shape {tuple(flat.shape)}")
        lead = flat.shape[:-1]
        return {key: flat[..., sl].reshape(*lead, *shape) for key, sl, shape in self.segments}

    def __repr__(self) -> str:
        return f"ModulationLayout({self.name!r}, dim={self.dim})"


def entry_shape(key) -> tuple[int, ...]:
    """Shape (without batch dims) of a channel's action entry."""
    for channel in CHANNELS.values():
        for k, shape in channel.entries:
            if k == key:
                return shape
    raise UnknownKeyError(f"no modulation channel has the entry {key!r}")


def _config_class(channels: Mapping[str, Channel]) -> type:
    """The frozen dataclass of every channel's fields, in registry order; number fields validated."""
    fields = [f for c in channels.values() for f in c.fields]
    numbers = tuple(f.name for f in fields if not isinstance(f.default, bool))
    below = {f.name: f.below for f in fields if f.below is not None}
    choices = {f.name: f.choices for f in fields if f.choices is not None}

    def __post_init__(self):
        check_numbers("ModulationConfig", self, numbers)
        for name, bound in below.items():
            if not getattr(self, name) < bound:
                raise ConfigError(f"ModulationConfig.{name} must be < {bound:g}, got {getattr(self, name)}")
        for name, allowed in choices.items():
            if getattr(self, name) not in allowed:
                raise ConfigError(f"ModulationConfig.{name} must be one of {allowed}, got {getattr(self, name)!r}")

    cls = dataclasses.make_dataclass(
        "ModulationConfig", [(f.name, type(f.default), dataclasses.field(default=f.default)) for f in fields],
        namespace={"__post_init__": __post_init__}, frozen=True)
    cls.__module__ = __name__
    cls.__doc__ = ("How far each channel may move things (rad, m): the fields of every channel in :data:`CHANNELS`.\n"
                   "The modulator's outputs are in [−1, 1] and are clamped there before scaling, so these are hard\n"
                   "bounds per step.\n\n"
                   + "\n".join(f"* ``{f.name}`` ({c.name}, default ``{f.default}``) — {f.doc};"
                               for c in channels.values() for f in c.fields))
    return cls


#: The channels' λ's, bounds and switches (one frozen dataclass; its fields come from the records in CHANNELS).
ModulationConfig = _config_class(CHANNELS)
