"""The three modulation channels as TorchRL transforms, and the tracker in the loop.

Each channel is its own :class:`~torchrl.envs.transforms.Transform` (a :class:`ChannelTransform`
bound to its record in the channel registry, :data:`adadex.modules.channels.CHANNELS`), adds its
input to the env's action spec (entries under ``"modulation"``, in [−1, 1]) and acts on the
*inverse* path, i.e. on what goes into the environment:

* :class:`ReferenceModulation` (R): ŝ_{t+k} ← ŝ_{t+k} + λ_x · a_ref for k ∈ {1, 2, 4, 12},
  x ∈ {hand joints, object pose}; the object rotation residual is a rotation vector, composed on
  the left. By default the edit *persists*: the edited future frames stay edited as the episode
  moves on (our design decision, which the paper leaves open; per-step edits are a switch). The
  edit is state carried in the tensordict, ``("modulation", "hand_edit")`` (…, 13, 22) and
  ``("modulation", "object_edit")`` (…, 13, 6), for frames t … t+12, shifted by one frame per step
  and zero after a reset; the observation leaving the env shows the edited reference (structured
  entries and the 273-D vector), the reward still scores the original one. ``persistent=False`` edits the current step only.
* :class:`ReferenceLead` (L): the visible reference read ahead in time, up to ``max_lead`` control
  steps, the arm's and the hand's joints apart (latched for the episode by default).
* :class:`CompactModulation` (C): R in 7 numbers — the visible reference's palm moved by an offset
  (through the arm Jacobian) and each finger's flexion closed or opened; absolute, not carried.
* :class:`LatentModulation` (O): the object latent becomes f̃ = clip(f + λ · a, −1, 1).
* :class:`ActionModulation` (T): action ← action + bound · clip(Δa, −1, 1).
* :class:`GainModulation` (K): action ← action + clip(g · (reference − joint position), ±bound), a
  feedback gain per joint group on the tracking error at the current frame (latched for the episode).
* :class:`TrackerInTheLoop`: runs a frozen tracker (deterministic, no gradient) on the modulated
  observation and writes its action; the env's own 22-D action leaves the outer action spec.
* :class:`FlatModulationAction`: the outer action becomes one flat vector in [−1, 1]^D, split into
  the channels' entries, so a modulator can be trained with any TorchRL loss.
* :class:`ModulatorView`: writes what the modulator sees, ``("modulator", "view")``
  (:mod:`adadex.modules.modulator_view`), and carries its state (last action, steps, history).

R and O edit the tracker's observation, T its action (the records' ``edits``), which places them
on either side of the tracker. R and O edit the structured entries and reassemble
``"observation"`` with the env's one function (:func:`adadex.envs.observation.flat_from_tensordict`)
so the tracker reads the modulated vector.
The tracker's action is clipped by the env to ``max_action`` after T's residual is added.

:func:`modulation` builds the whole chain for a set of channels::

    env = TransformedEnv(TrackingEnv(data, num_worlds=8), modulation("R+O+T", tracker=frozen))
    env.action_spec.shape          # (8, 198): the modulator's action
"""

from __future__ import annotations

import torch
from tensordict import TensorDictBase
from torchrl.data import Bounded, Composite, Unbounded
from torchrl.envs import Compose, Transform
from torchrl.envs.utils import ExplorationType, set_exploration_type

from adadex.envs.observation import JOINT_POS, OBJECT_LATENT, OBJECT_START, OBSERVATION, REF_JOINT_POS, REF_OBJECT_POSE, \
    REF_OBJECT_START, REF_OFFSETS, flat_from_tensordict
from adadex.errors import UnknownKeyError
from adadex.modules.channels import GRIP_JOINTS, HAND_EDIT, MOD, OBJECT_EDIT, PALM, Channel, ModulationConfig, \
    ModulationLayout, bind_transform
from adadex.modules.modulator_view import LAST_ACTION, STEPS, VIEW, ViewLayout, next_view_state, view_features
from adadex.quat import quat_from_rotvec, quat_mul, rotvec_from_quat
from adadex.sim.robot import JOINT_NAMES, NUM_JOINTS

_FUTURE_ROWS = list(REF_OFFSETS[1:])      # rows of the 13-frame edit that the R action moves
_OBS_ROWS = list(REF_OFFSETS)             # rows of the edit seen by the reference entries


def _unit_box(batch: torch.Size, shape, device) -> Bounded:
    return Bounded(low=-1.0, high=1.0, shape=(*batch, *shape), dtype=torch.float32, device=device)


class CarriedState:
    """What a transform that carries state from step to step shares (R's persistent edit and
    the modulator's view): its :meth:`state_shapes` become observation and state specs; each step
    writes :meth:`next_state` of the step's input (after the inverse path) into the next observation,
    then shows it (:meth:`_call`); a reset zeroes the state of the worlds that reset and keeps the
    others'. :func:`adadex.transforms.policy.make_policy` carries the same state through its primer."""

    def state_shapes(self) -> dict:
        """{key: shape} of the state carried between steps (none by default)."""
        return {}

    def next_state(self, td: TensorDictBase) -> dict:
        """{key: tensor}: the state for the next step, from this step's (after the inverse path)."""
        return {}

    def _state_specs(self, spec: Composite) -> Composite:
        for key, shape in self.state_shapes().items():
            spec[key] = Unbounded(shape=(*spec.shape, *shape), dtype=torch.float32, device=spec.device)
        return spec

    def transform_observation_spec(self, observation_spec: Composite) -> Composite:
        return self._state_specs(observation_spec)

    def transform_state_spec(self, state_spec: Composite) -> Composite:
        return self._state_specs(state_spec)

    def _call(self, next_td: TensorDictBase) -> TensorDictBase:
        return next_td

    def _step(self, tensordict: TensorDictBase, next_tensordict: TensorDictBase) -> TensorDictBase:
        if not self.state_shapes():
            return next_tensordict
        next_tensordict.update(self.next_state(tensordict))
        return self._call(next_tensordict)

    def _reset(self, tensordict: TensorDictBase, tensordict_reset: TensorDictBase) -> TensorDictBase:
        """Reset worlds start with zero state; with a partial reset the others keep theirs."""
        shapes = self.state_shapes()
        if not shapes:
            return tensordict_reset
        mask = None if tensordict is None else tensordict.get("_reset", None)
        B = tensordict_reset.batch_size
        for key, shape in shapes.items():
            value = torch.zeros(*B, *shape, device=tensordict_reset.device)
            prev = None if tensordict is None else tensordict.get(key, None)
            if mask is not None and prev is not None:
                keep = ~mask.reshape(B).reshape(*B, *([1] * len(shape)))
                value = torch.where(keep, prev, value)
            tensordict_reset.set(key, value)
        return self._call(tensordict_reset)


class ChannelTransform(CarriedState, Transform):
    """Base of the channel transforms: one per record of :data:`adadex.modules.channels.CHANNELS`.

    A subclass names its record, ``class XModulation(ChannelTransform, channel="X")``, which binds it
    as that channel's transform; it is built as ``cls(config)``. Its inputs are the record's
    ``"modulation"`` entries, each in [−1, 1], added to the action spec. Keys, the TorchRL way, on
    the inverse path: ``out_keys_inv`` are the entries it reads from the policy's side (its action
    entries), ``in_keys_inv`` the entries it edits for the env's side (``edited_keys``, given by the
    subclass, and its carried state). ``_inv_call`` is the channel's own, so the two lists are
    declarations (for readers and tools), not pairs that TorchRL's default inverse would map.

    A channel that carries state from step to step (R's persistent reference edit) returns its
    shapes in :meth:`state_shapes` and the next step's state in :meth:`next_state`; the policy
    graph of :func:`adadex.transforms.policy.make_policy` carries it with a primer.

    Args:
        config: the channels' settings (:class:`~adadex.modules.channels.ModulationConfig`).
        edited_keys: the entries it edits for the env's side (given by the subclass).
    """

    channel: Channel
    entries: tuple = ()

    def __init_subclass__(cls, channel: str | None = None, **kwargs):
        super().__init_subclass__(**kwargs)
        if channel is not None:
            cls.channel = bind_transform(channel, cls)
            cls.entries = cls.channel.keys

    def __init__(self, config: ModulationConfig = ModulationConfig(), edited_keys=()):
        super().__init__(in_keys=[], out_keys=[])
        self.config = config
        self.out_keys_inv = list(self.entries)
        self.in_keys_inv = [*edited_keys, *self.state_shapes()]

    def transform_action_spec(self, action_spec: Composite) -> Composite:
        for key, shape in self.channel.entries:
            action_spec[key] = _unit_box(action_spec.shape, shape, action_spec.device)
        return action_spec

    #: {entry key: b}: entries clipped to [−b, b] instead of [−1, 1]
    entry_bounds: dict = {}

    def _inputs(self, td: TensorDictBase):
        """The entries, clipped to [−1, 1] (``entry_bounds``: wider); None (with missing tolerance) when absent."""
        out = []
        for key in self.entries:
            v = td.get(key, None)
            if v is None:
                if self.missing_tolerance:
                    return None
                raise KeyError(f"{type(self).__name__}: the modulation entry {key} is missing from the input "
                               f"tensordict (keys: {list(td.keys(True, True))})")
            bound = self.entry_bounds.get(key, 1.0)
            out.append(v.clamp(-bound, bound))
        return out


def _compose_pose_edit(edit: torch.Tensor, delta: torch.Tensor) -> torch.Tensor:
    """Object edits (…, 6) = position (3) + rotation vector (3): ``delta`` applied after ``edit``."""
    rot = rotvec_from_quat(quat_mul(quat_from_rotvec(delta[..., 3:]), quat_from_rotvec(edit[..., 3:])))
    return torch.cat([edit[..., :3] + delta[..., :3], rot], dim=-1)


def _edit_pose(pose: torch.Tensor, edit: torch.Tensor) -> torch.Tensor:
    """Poses (…, 7) moved by edits (…, 6): shift the position, rotate on the left."""
    q = quat_mul(quat_from_rotvec(edit[..., 3:]), pose[..., 3:])
    return torch.cat([pose[..., :3] + edit[..., :3], q / torch.linalg.vector_norm(q, dim=-1, keepdim=True)], dim=-1)


class ReferenceModulation(ChannelTransform, channel="R"):
    """Channel R: residuals on the future reference (see the module docstring).

    Args:
        config: λ_hand, λ_object (position, rotation) and ``persistent``.
    """

    def __init__(self, config: ModulationConfig = ModulationConfig()):
        super().__init__(config, (REF_JOINT_POS, REF_OBJECT_POSE, OBSERVATION))

    @property
    def persistent(self) -> bool:
        return self.config.persistent

    def state_shapes(self) -> dict:
        """The persistent edit, ``("modulation", "hand_edit"/"object_edit")``; none with ``persistent=False``."""
        return dict(self.channel.state) if self.persistent else {}

    def next_state(self, td: TensorDictBase) -> dict:
        """The carried edit shifted by one frame (the new last frame unedited)."""
        if not self.persistent:
            return {}
        hand, obj = self._state(td)
        return {HAND_EDIT: shift_edit(hand), OBJECT_EDIT: shift_edit(obj)}

    # -- the edit ---------------------------------------------------------------------------------
    def deltas(self, td: TensorDictBase):
        """(hand (…, 4, 22), object (…, 4, 6)) residuals of this step, scaled by λ; None if absent."""
        a = self._inputs(td)
        if a is None:
            return None
        c = self.config
        scale = torch.tensor([c.lambda_object_pos] * 3 + [c.lambda_object_rot] * 3, dtype=a[1].dtype,
                             device=a[1].device)
        return c.lambda_hand * a[0], a[1] * scale

    def _state(self, td: TensorDictBase):
        ref = td.get(REF_JOINT_POS)
        lead = ref.shape[:-2]
        shapes = dict(self.channel.state)
        hand = td.get(HAND_EDIT, None)
        obj = td.get(OBJECT_EDIT, None)
        if hand is None:
            hand = ref.new_zeros(*lead, *shapes[HAND_EDIT])
        if obj is None:
            obj = ref.new_zeros(*lead, *shapes[OBJECT_EDIT])
        return hand, obj

    @staticmethod
    def _move_reference(td: TensorDictBase, hand: torch.Tensor, obj: torch.Tensor) -> TensorDictBase:
        """Move the reference entries (offsets 0, 1, 2, 4, 12) by per-offset edits and reassemble the 273-D vector."""
        td.set(REF_JOINT_POS, td.get(REF_JOINT_POS) + hand)
        td.set(REF_OBJECT_POSE, _edit_pose(td.get(REF_OBJECT_POSE), obj))
        if OBSERVATION in td.keys():
            td.set(OBSERVATION, flat_from_tensordict(td))
        return td

    def _inv_call(self, td: TensorDictBase) -> TensorDictBase:
        d = self.deltas(td)
        if d is None:
            return td
        d_hand, d_obj = d
        if self.persistent:
            hand, obj = self._state(td)
            hand, obj = hand.clone(), obj.clone()
            hand[..., _FUTURE_ROWS, :] += d_hand
            obj[..., _FUTURE_ROWS, :] = _compose_pose_edit(obj[..., _FUTURE_ROWS, :], d_obj)
            td.set(HAND_EDIT, hand)
            td.set(OBJECT_EDIT, obj)
        # The entries already show the carried edit; add this step's residual on top.
        zero_h, zero_o = d_hand[..., :1, :] * 0, d_obj[..., :1, :] * 0
        return self._move_reference(td, torch.cat([zero_h, d_hand], -2), torch.cat([zero_o, d_obj], -2))

    def _call(self, next_td: TensorDictBase) -> TensorDictBase:
        """Show the carried edit in raw env output (structured reference and the 273-D vector)."""
        if not self.persistent or next_td.get(HAND_EDIT, None) is None:
            return next_td
        hand, obj = self._state(next_td)
        return self._move_reference(next_td, hand[..., _OBS_ROWS, :], obj[..., _OBS_ROWS, :])


def latch(td: TensorDictBase, key, value: torch.Tensor) -> torch.Tensor:
    """The value an episode latched at its first step: ``value`` (…, n) where the carried state ``key``
    (…, n + 1: the latched value and a flag, zero at reset) has not latched yet, the state's value
    where it has; writes the state. Channels A, L and K decide once per episode this way."""
    state = td.get(key, None)
    if state is None:
        state = value.new_zeros(*value.shape[:-1], value.shape[-1] + 1)
    out = torch.where(state[..., -1:] > 0.5, state[..., :-1], value)
    td.set(key, torch.cat([out, torch.ones_like(out[..., :1])], -1))
    return out


class LatchedChoice:
    """What channels A, L and K share: their action is a choice held for the episode (the record's
    one state entry, carried with :func:`latch`) while the config's switch named by the record's
    ``latch`` is on, or taken anew every step (no state) when it is off."""

    @property
    def latched(self) -> bool:
        return bool(getattr(self.config, self.channel.latch))

    def state_shapes(self) -> dict:
        """The latched choice and its flag (the record's state); none when the choice is not latched."""
        return dict(self.channel.state) if self.latched else {}

    def next_state(self, td: TensorDictBase) -> dict:
        return {key: td.get(key) for key, _ in self.channel.state} if self.latched else {}

    def choose(self, td: TensorDictBase, value: torch.Tensor) -> torch.Tensor:
        """``value`` (…, n), this step's choice: latched at the episode's first step when the switch is on."""
        return latch(td, self.channel.state[0][0], value) if self.latched else value

    def arm_and_hand(self, td: TensorDictBase, scale: float, low: float = 0.0) -> tuple[torch.Tensor, torch.Tensor] | None:
        """Channels L and K: this step's choice ``scale · clip(a, low, 1)`` for the arm and for the hand,
        (…, 2), and per joint, (…, 22); None where the channel's entries are absent."""
        a = self._inputs(td)
        if a is None:
            return None
        value = self.choose(td, scale * a[0].clamp(low, 1.0))
        return value, torch.where(_ARM.to(value.device), value[..., :1], value[..., 1:2])


_VISIBLE = torch.tensor(REF_OFFSETS, dtype=torch.float32)
_ARM = torch.arange(NUM_JOINTS) < 6                  # the arm's six joints come first


def read_ahead(frames: torch.Tensor, lead: torch.Tensor) -> torch.Tensor:
    """The visible reference frames (…, 5, D) at offsets :data:`REF_OFFSETS` read ``lead`` (…, D)
    control steps later (≥ 0): each frame at offset o becomes the reference at o + lead, linear between
    the visible frames (exact where o + lead ≤ 2, where kinematic replay and a servo's delay read) and
    held at the last visible frame (t+12) beyond it.

    Args:
        frames: (…, 5, D) the visible frames, at offsets 0, 1, 2, 4, 12.
        lead: (…, D) control steps ahead, per entry (≥ 0).

    Returns:
        (…, 5, D) the frames read ahead.

    Examples:
        >>> import torch
        >>> frames = torch.tensor([0.0, 1.0, 2.0, 4.0, 12.0])[:, None]    # value = the frame's offset
        >>> read_ahead(frames, torch.tensor([3.0]))[:, 0]                 # o + 3, held at 12
        tensor([ 3.,  4.,  5.,  7., 12.])
    """
    grid = _VISIBLE.to(frames)
    at = (grid[:, None] + lead[..., None, :]).clamp(max=float(grid[-1]))             # (…, 5, D)
    i = (torch.searchsorted(grid, at.contiguous(), right=True) - 1).clamp(0, len(grid) - 2)
    lo, hi = grid[i], grid[i + 1]
    w = (at - lo) / (hi - lo)
    return torch.gather(frames, -2, i) * (1 - w) + torch.gather(frames, -2, i + 1) * w


class ReferenceLead(LatchedChoice, ChannelTransform, channel="L"):
    """Channel L, the reference lead: the visible reference (joints at every visible offset, and the
    object's reference) is read ``lead = max_lead · clip(a, 0, 1)`` control steps ahead — the arm's
    joints and the object by the first entry, the hand's joints by the second (:func:`read_ahead`).
    Untrained (a = 0) it is the tracker alone.

    Why a channel: a robot whose servos answer late (a transport delay on the arm, a first-order lag on
    the fingers) follows a reference late by that much; commanding the reference that far ahead is the
    classic feed-forward for it, and how far is the robot's — what identification measures and a
    modulator trained on the identified model can learn. (Measured around replay, the lead pays less
    than one would guess: an 80 ms arm delay costs replay about 1 completion point, and a one-step arm
    lead on the nominal robot did not raise the return on training episodes; docs/modulation.md.) R could
    express it only as 112 numbers per step. With ``lead_latched`` (default) the lead chosen at an
    episode's first step holds for the episode (carried state ``("modulation", "lead_state")``: arm,
    hand, latched flag), as channel A's reach: a delay is the robot's, not the moment's. The reward
    scores the original reference.

    Args:
        config: the channels' settings (:class:`~adadex.modules.channels.ModulationConfig`);
            this one reads ``max_lead`` (control steps) and
            ``lead_latched``.

    Examples:
        >>> import torch
        >>> frames = torch.arange(5.0)[:, None] * torch.ones(5, 22)      # joint value = the visible frame's index
        >>> read_ahead(frames, torch.full((22,), 0.5))[:3, 0]            # offsets 0, 1, 2 → 0.5, 1.5, 2.25
        tensor([0.5000, 1.5000, 2.2500])
    """

    def __init__(self, config: ModulationConfig = ModulationConfig()):
        super().__init__(config, (REF_JOINT_POS, REF_OBJECT_POSE, OBSERVATION))

    def _inv_call(self, td: TensorDictBase) -> TensorDictBase:
        chosen = self.arm_and_hand(td, self.config.max_lead)     # control steps ahead (latched)
        if chosen is None:
            return td
        lead, per_joint = chosen
        td.set(REF_JOINT_POS, read_ahead(td.get(REF_JOINT_POS), per_joint))
        obj = td.get(REF_OBJECT_POSE)
        q = obj[..., 3:].clone()
        for k in range(1, q.shape[-2]):          # quaternions interpolated linearly: each on its predecessor's side
            flip = (q[..., k, :] * q[..., k - 1, :]).sum(-1, keepdim=True) < 0
            q[..., k, :] = torch.where(flip, -q[..., k, :], q[..., k, :])
        moved = read_ahead(torch.cat([obj[..., :3], q], -1), lead[..., :1].expand(*obj.shape[:-2], 7))
        moved = torch.cat([moved[..., :3], moved[..., 3:] / moved[..., 3:].norm(dim=-1, keepdim=True).clamp_min(1e-9)],
                          -1)
        td.set(REF_OBJECT_POSE, torch.where(lead[..., None, :1] > 0, moved, obj))
        if OBSERVATION in td.keys():
            td.set(OBSERVATION, flat_from_tensordict(td))
        return td


def shift_edit(edit: torch.Tensor) -> torch.Tensor:
    """Edits for frames t … t+12 → for frames t+1 … t+13 (the new last frame unedited)."""
    return torch.cat([edit[..., 1:, :], torch.zeros_like(edit[..., :1, :])], dim=-2)


class CompactModulation(ChannelTransform, channel="C"):
    """Channel C, the compact reference edit: 7 numbers instead of R's 112. The palm of every visible
    reference frame (offsets 0, 1, 2, 4, 12) moves by ``λ_palm · a_palm`` (m, base frame) — the arm
    joints of each frame solved through the palm's Jacobian without turning it
    (:class:`adadex.modules.anchor.PalmShift`) — and each finger's flexion joints close by
    ``λ_grip · a_grip`` (index, middle, ring, thumb). The edit is absolute, not carried: the action
    says where the reference is this step, so reaching an object that Table 3 moved is one offset
    read off the view's start offset. (Tried as a rate, the offset carried and changed by the action:
    sampled at scale 0.3 it cost replay 13.6 completion points, and 250 k frames of PPO drifted the
    offsets until replay completed 40.9 % instead of 79.7 %; docs/modulation.md.) The reward scores
    the original reference.

    The palm entry is clipped to ±2 rather than ±1: a sampled TanhNormal never leaves [−1, 1], but a
    modulator with the anchor prior (``Modulator(prior="anchor")``) asks for the anchor's shift plus
    its correction, and the anchor follows objects displaced past ``λ_palm`` (Table 3's N(0, 5 cm)
    puts about 9 % of the objects more than 10 cm off on an axis).

    Args:
        config: the channels' settings (:class:`~adadex.modules.channels.ModulationConfig`);
            this one reads ``lambda_palm`` (m) and ``lambda_grip``
            (rad).
    """

    entry_bounds = {PALM: 2.0}

    def __init__(self, config: ModulationConfig = ModulationConfig()):
        super().__init__(config, (REF_JOINT_POS, OBSERVATION))
        from adadex.modules.anchor import PalmShift

        self._shift = PalmShift()
        mask = torch.zeros(len(GRIP_JOINTS), NUM_JOINTS)
        for f, joints in enumerate(GRIP_JOINTS):
            mask[f, [JOINT_NAMES.index(j) for j in joints]] = 1.0
        self._grip = mask

    def _inv_call(self, td: TensorDictBase) -> TensorDictBase:
        a = self._inputs(td)
        if a is None:
            return td
        palm, grip = a[0] * self.config.lambda_palm, a[1] * self.config.lambda_grip
        ref = td.get(REF_JOINT_POS)                       # (…, 5, 22)
        edit = (grip @ self._grip.to(grip))[..., None, :].expand(*ref.shape[:-1], NUM_JOINTS).clone()
        return move_visible_reference(td, self._shift, palm, edit)


def move_visible_reference(td: TensorDictBase, palm_shift, palm: torch.Tensor,
                           edit: torch.Tensor | None = None) -> TensorDictBase:
    """Add ``edit`` (…, 5, 22) to the visible reference joints (offsets 0, 1, 2, 4, 12) with their arm
    joints replaced by the change that moves each frame's palm by ``palm`` (…, 3) (m, base frame)
    without turning it (``palm_shift``: a :class:`adadex.modules.anchor.PalmShift`); reassembles the
    273-D observation. Channels C and A move the reference this way.

    Args:
        td: the tensordict holding the reference (``REF_JOINT_POS``), edited in place.
        palm_shift: the :class:`~adadex.modules.anchor.PalmShift` solving the arm joints.
        palm: (…, 3) the palm's shift, m, base frame (zero rows are left unsolved).
        edit: (…, 5, 22) added to the joints (its arm columns replaced where the palm moves), or
            None (default): zeros.

    Returns:
        ``td``.
    """
    ref = td.get(REF_JOINT_POS)                           # (…, 5, 22)
    lead, k = ref.shape[:-2], ref.shape[-2]
    edit = ref.new_zeros(ref.shape) if edit is None else edit
    q = ref[..., :6].reshape(-1, 6)
    shift = palm[..., None, :].expand(*lead, k, 3).reshape(-1, 3)
    rows = shift.any(dim=1).nonzero()[:, 0]               # the Jacobian only where the palm moves
    if len(rows):
        flat = edit.reshape(-1, NUM_JOINTS).clone()
        flat[rows, :6] = palm_shift(q[rows], shift[rows])
        edit = flat.reshape(*lead, k, NUM_JOINTS)
    td.set(REF_JOINT_POS, ref + edit)
    if OBSERVATION in td.keys():
        td.set(OBSERVATION, flat_from_tensordict(td))
    return td


class AnchorReach(LatchedChoice, ChannelTransform, channel="A"):
    """Channel A, the object-anchor reach: one number, how far the visible reference's palm moves onto
    the object where it lies. The object anchor (:class:`adadex.modules.anchor.ObjectAnchor`, with the
    anchored feed-forward's settings, :data:`adadex.modules.modulator.PRIOR_ANCHOR`) gives the palm
    shift — the object's horizontal start offset, faded out as the reference carries the object — and
    the action chooses the fraction of it, ``w = clip(0.5 + a, 0, 1)``: a ≤ −0.5 leaves the reference
    alone (replay around kinematic replay), a ≥ 0.5 is the full anchor; with ``reach_smooth``,
    ``w = (1 + a) / 2``, no flat ends. Every visible frame moves (as channel C's palm,
    :func:`move_visible_reference`).

    Why a channel: the anchored feed-forward carries the object (object completion +11 around replay)
    but costs the paper's completion where the object lies far off (past ~8 cm the hand holding it
    is that far off the reference palm); whether to reach is a decision per episode, and a modulator
    exploring C's palm around the anchor (``Modulator(prior="anchor")``) never tried not reaching
    (docs/modulation.md). With ``reach_latched`` (default) the reach chosen at the episode's first step
    holds for the episode: the carried state ``("modulation", "reach_state")`` = (w, latched), zero at
    reset; later steps' reach entries are ignored, so the first step's sample is the exploration and
    the decision (and the modulator's view shows the latched w).

    Args:
        config: the channels' settings (:class:`~adadex.modules.channels.ModulationConfig`);
            this one reads ``reach_latched``, ``reach_smooth`` and ``reach_lookahead`` (the reference
            frame ahead whose object travel times the anchor's hold and release); the anchor's other
            settings are :data:`~adadex.modules.modulator.PRIOR_ANCHOR`.
    """

    def __init__(self, config: ModulationConfig = ModulationConfig()):
        super().__init__(config, (REF_JOINT_POS, OBSERVATION))
        from adadex.modules.anchor import ObjectAnchor, PalmShift
        from adadex.modules.modulator import PRIOR_ANCHOR

        self._anchor = ObjectAnchor(**PRIOR_ANCHOR, lookahead=config.reach_lookahead)
        self._frame = REF_OFFSETS.index(self._anchor.lookahead)
        self._shift = PalmShift(self._anchor.damping, self._anchor.iterations)

    def weight(self, td: TensorDictBase) -> torch.Tensor | None:
        """(…,) the fraction of the anchor's shift this step (latching it at the episode's first step)."""
        a = self._inputs(td)
        if a is None:
            return None
        w = (1.0 + a[0]) / 2.0 if self.config.reach_smooth else (0.5 + a[0]).clamp(0.0, 1.0)
        return self.choose(td, w)[..., 0]

    def _inv_call(self, td: TensorDictBase) -> TensorDictBase:
        w = self.weight(td)
        if w is None:
            return td
        start, ref_start = td.get(OBJECT_START), td.get(REF_OBJECT_START)
        travel = torch.linalg.vector_norm(td.get(REF_OBJECT_POSE)[..., self._frame, :3] - ref_start[..., :3], dim=-1)
        palm = self._anchor.palm_shift(start[..., :2] - ref_start[..., :2], travel) * w[..., None]
        return move_visible_reference(td, self._shift, palm)


class LatentModulation(ChannelTransform, channel="O"):
    """Channel O: the object latent the tracker sees becomes f̃ = clip(f + λ_latent · a, −1, 1).

    Args:
        config: the channels' settings (:class:`~adadex.modules.channels.ModulationConfig`);
            this one reads ``lambda_latent`` (λ_latent).
    """

    def __init__(self, config: ModulationConfig = ModulationConfig()):
        super().__init__(config, (OBJECT_LATENT, OBSERVATION))

    def _inv_call(self, td: TensorDictBase) -> TensorDictBase:
        a = self._inputs(td)
        if a is None:
            return td
        td.set(OBJECT_LATENT, (td.get(OBJECT_LATENT) + self.config.lambda_latent * a[0]).clamp(-1.0, 1.0))
        if OBSERVATION in td.keys():
            td.set(OBSERVATION, flat_from_tensordict(td))
        return td


class ActionModulation(ChannelTransform, channel="T"):
    """Channel T: a bounded residual on the action, action + bound · clip(Δa, −1, 1).

    Args:
        config: the channels' settings (:class:`~adadex.modules.channels.ModulationConfig`);
            this one reads ``action_bound`` (the bound, rad).
        action_key: the tracker's action entry it edits (default ``"action"``).
    """

    def __init__(self, config: ModulationConfig = ModulationConfig(), action_key="action"):
        super().__init__(config, (action_key,))
        self.action_key = action_key

    def _inv_call(self, td: TensorDictBase) -> TensorDictBase:
        a = self._inputs(td)
        if a is None:
            return td
        td.set(self.action_key, td.get(self.action_key) + self.config.action_bound * a[0])
        return td


class GainModulation(LatchedChoice, ChannelTransform, channel="K"):
    """Channel K, a feedback gain: the tracker's action gains ``clip(g · (q_ref,t − q_t), ±gain_bound)``,
    the joints' tracking error at the current frame (against the reference the tracker reads) times a
    gain ``g = max_gain · clip(a, −max_softening / max_gain, 1)`` — the first entry for the arm's six joints,
    the second for the hand's. Untrained (a = 0) it is the tracker alone. A negative gain (``max_softening``
    > 0) softens the servo: its pull ``kp · (q_ref + g · (q_ref − q) − q)`` is ``kp · (1 + g) · (q_ref − q)``.

    Why a channel: a servo softer than the model's, or one carrying a load, sags below its target by
    a steady error that kinematic replay never corrects (a 2 kg payload with arm kp × 0.3 costs replay
    about 10 completion points, docs/sim2real.md); adding the error to the target is the integral
    action such a servo lacks, and how much of it a robot needs is the robot's — what a modulator
    trained on an identified model can learn. T could express it only as a per-step function of the
    view learned from scratch. With ``gain_latched`` (default) the gains chosen at an episode's first
    step hold for the episode (carried state ``("modulation", "gain_state")``: arm, hand, latched
    flag), as channel L's lead.

    Args:
        config: the channels' settings (:class:`~adadex.modules.channels.ModulationConfig`);
            this one reads ``max_gain``, ``max_softening``, ``gain_bound`` (rad) and ``gain_latched``.
        action_key: the tracker's action entry it edits (default ``"action"``).
    """

    def __init__(self, config: ModulationConfig = ModulationConfig(), action_key="action"):
        super().__init__(config, (action_key,))
        self.action_key = action_key

    def _inv_call(self, td: TensorDictBase) -> TensorDictBase:
        c = self.config
        chosen = self.arm_and_hand(td, c.max_gain, -c.max_softening / c.max_gain)     # the gains (latched)
        if chosen is None:
            return td
        _, per_joint = chosen
        error = td.get(REF_JOINT_POS)[..., 0, :] - td.get(JOINT_POS)
        bound = self.config.gain_bound
        td.set(self.action_key, td.get(self.action_key) + (per_joint * error).clamp(-bound, bound))
        return td


class TrackerInTheLoop(Transform):
    """Runs a frozen tracker on the (modulated) observation and writes the env's action.

    The tracker runs deterministically under ``torch.no_grad`` with its parameters frozen, so no
    gradient reaches it; the env's ``action`` entry leaves the outer action spec.

    Args:
        tracker: a :class:`adadex.modules.tracker.Tracker` or any module writing ``"action"``
            from ``"observation"``.
        action_key: the env's action entry it writes (default ``"action"``).
    """

    def __init__(self, tracker, action_key="action"):
        super().__init__(in_keys=[], out_keys=[])
        actor = getattr(tracker, "actor", tracker)
        actor.requires_grad_(False)
        self.tracker = actor.eval()
        self.action_key = action_key
        self.out_keys_inv = list(actor.in_keys)       # read from the policy's side
        self.in_keys_inv = [action_key]               # written for the env

    def transform_action_spec(self, action_spec: Composite) -> Composite:
        spec = action_spec.clone()
        del spec[self.action_key]
        return spec

    def _inv_call(self, td: TensorDictBase) -> TensorDictBase:
        with torch.no_grad(), set_exploration_type(ExplorationType.DETERMINISTIC):
            out = self.tracker(td.select(*self.tracker.in_keys).copy())
        td.set(self.action_key, out.get(self.action_key))
        return td


class FlatModulationAction(Transform):
    """The outer action: one flat ``"action"`` in [−1, 1]^D, split into the channels' entries
    (:class:`adadex.modules.channels.ModulationLayout`). Outermost transform of :func:`modulation`.

    Args:
        layout: the active channels' layout (where each entry sits in the flat action).
        action_key: the outer action's key (default ``"action"``).
    """

    def __init__(self, layout: ModulationLayout, action_key="action"):
        super().__init__(in_keys=[], out_keys=[], in_keys_inv=[key for key, _, _ in layout.segments],
                         out_keys_inv=[action_key])
        self.layout = layout
        self.action_key = action_key

    def transform_action_spec(self, action_spec: Composite) -> Composite:
        spec = action_spec.clone()
        for key, _, _ in self.layout.segments:
            del spec[key]
        if MOD in spec.keys() and spec[MOD].is_empty():   # batched envs refuse empty sub-specs
            del spec[MOD]
        spec[self.action_key] = _unit_box(spec.shape, (self.layout.dim,), spec.device)
        return spec

    def _inv_call(self, td: TensorDictBase) -> TensorDictBase:
        flat = td.get(self.action_key, None)
        if flat is None:
            if self.missing_tolerance:
                return td
            raise KeyError(f"FlatModulationAction: no {self.action_key!r} entry in the input tensordict")
        td = td.exclude(self.action_key)
        for key, value in self.layout.split(flat).items():
            td.set(key, value)
        return td


class ModulatorView(CarriedState, Transform):
    """Writes the modulator's view, ``("modulator", "view")`` (:mod:`adadex.modules.modulator_view`),
    into every observation, and carries the state it needs — the modulator's last action, the steps
    since the reset and the previous frames — zero for worlds that reset.

    It follows the channels' state protocol (:class:`CarriedState`), so
    :func:`adadex.transforms.policy.make_policy` carries the same state on a plain env through its
    primer. Outermost in :func:`modulation`: on the forward path it runs after R has shown its edit;
    on the inverse path it runs first, and with the layout's ``decide_every`` = k > 1 it replaces the
    modulator's action by its last one at every step between decisions (the view's ``held`` part), so
    each decision acts for k control steps.

    Args:
        layout: the modulator's view layout (:attr:`~adadex.modules.modulator.Modulator.view`).
    """

    def __init__(self, layout: ViewLayout):
        super().__init__(in_keys=[], out_keys=[VIEW])
        self.layout = layout

    def state_shapes(self) -> dict:
        return self.layout.state_shapes()

    def next_state(self, td: TensorDictBase) -> dict:
        """The state for the next step, from this step's entries after the inverse path."""
        return next_view_state(td, self.layout)

    def _inv_call(self, td: TensorDictBase) -> TensorDictBase:
        """Between decisions (``decide_every`` > 1), the flat action is the one last applied."""
        if self.layout.decide_every == 1:
            return td
        action, last, steps = td.get("action", None), td.get(LAST_ACTION, None), td.get(STEPS, None)
        if action is None or last is None or steps is None:
            missing = [k for k, v in (("action", action), (LAST_ACTION, last), (STEPS, steps)) if v is None]
            raise UnknownKeyError(f"ModulatorView(decide_every={self.layout.decide_every}) needs {missing} in the "
                                  "tensordict to hold the modulator's action between its decisions")
        td.set("action", torch.where(self.layout.held(steps), last.to(action.dtype), action))
        return td

    def transform_observation_spec(self, observation_spec: Composite) -> Composite:
        spec = self._state_specs(observation_spec)
        spec[VIEW] = Unbounded(shape=(*spec.shape, self.layout.dim), dtype=torch.float32, device=spec.device)
        return spec

    def _call(self, next_td: TensorDictBase) -> TensorDictBase:
        next_td.set(VIEW, view_features(next_td, self.layout))
        return next_td


def channel_transforms(channels, config: ModulationConfig = ModulationConfig()) -> list[ChannelTransform]:
    """The channel transforms for ``channels``, in inverse-path order: the channels that edit the
    tracker's observation, then those that edit its action, each group in registry order (R, L, C, A, O then T, K).

    Args:
        channels: the active channels, as :func:`~adadex.modules.channels.parse_channels` takes them.
        config: the settings each transform is built with (``cls(config)``).
    """
    records = ModulationLayout(channels).records
    return [c.transform(config) for edits in ("observation", "action") for c in records if c.edits == edits]


def modulation(channels="R+O+T", tracker=None, config: ModulationConfig = ModulationConfig(),
               view: ViewLayout | None = None) -> Compose:
    """The modulator's env as one transform: ``TransformedEnv(TrackingEnv(…), modulation(channels, tracker))``.

    Inverse path (what the modulator's action goes through): split the flat action → the channels
    that edit the tracker's observation (R → L → C → A → O) → frozen tracker → those that edit its action (T)
    → env. Every subset of channels works, ``"none"`` included (the outer action is then empty and
    the env runs the tracker alone). ``view`` (a modulator's :attr:`~adadex.modules.modulator.Modulator.view`)
    adds :class:`ModulatorView`, which writes what that modulator reads.

    Args:
        channels: the active channels, as :func:`~adadex.modules.channels.parse_channels` takes
            them (default ``"R+O+T"``).
        tracker: the frozen tracker run inside (:class:`TrackerInTheLoop`); required (None raises
            ``ValueError``).
        config: the channels' settings (:class:`~adadex.modules.channels.ModulationConfig`).
        view: the modulator's view layout, or None (default): no :class:`ModulatorView`. It must be
            for the same channels (``ValueError`` otherwise).

    Returns:
        a ``Compose`` of the transforms, in the order the inverse path needs.

    Example: the README's policy graph in miniature (the tiny dataset, two worlds, untrained nets).

    >>> from torchrl.envs import TransformedEnv
    >>> from adadex.envs.tracking import TrackingEnv
    >>> from adadex.modules.modulator import Modulator
    >>> from adadex.modules.tracker import Tracker
    >>> tracker = Tracker(hidden=(32, 32)).freeze()
    >>> modulator = Modulator("R+O+T", hidden=(32, 32))
    >>> env = TransformedEnv(TrackingEnv(tiny_dataset, num_worlds=2, split=None),
    ...                      modulation("R+O+T", tracker, view=modulator.view))
    >>> env.action_spec.shape            # the modulator's action: 4·22 + 4·6 (R), 64 (O), 22 (T)
    torch.Size([2, 198])
    >>> td = env.rollout(3, modulator.actor)
    >>> td["action"].shape, td["modulation", "hand_edit"].shape     # R's persistent edit rides along
    (torch.Size([2, 3, 198]), torch.Size([2, 3, 13, 22]))
    >>> env.close()
    """
    if tracker is None:
        raise ValueError("modulation() needs the frozen tracker (tracker=…)")
    layout = ModulationLayout(channels)
    chain = channel_transforms(layout.channels, config)
    before = [t for t in chain if t.channel.edits == "observation"]
    after = [t for t in chain if t.channel.edits == "action"]
    if view is not None and view.channels.channels != layout.channels:
        raise ValueError(f"the modulator's view is for channels {view.channels.name}, not {layout.name}")
    # Compose runs inverses last-to-first and specs first-to-last.
    return Compose(*reversed(after), TrackerInTheLoop(tracker), *reversed(before), FlatModulationAction(layout),
                   *([ModulatorView(view)] if view is not None else []))
