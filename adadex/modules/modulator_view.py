"""What the modulator sees: the tracker's observation plus what it is scored on, its own edits and a
short history — one flat vector, ``("modulator", "view")``.

The tracker's 273-D observation shows the *edited* reference (channel R edits it), while the reward
scores the *original* one; a modulator that reads only that vector cannot tell its own edit from the
reference, nor the state of the servos, nor where in the episode it is. The view adds, in this order
(:class:`ViewLayout`):

=====================  ==============  =============================================================
``observation``        273             the tracker's observation as the tracker reads it (edited)
``original_error``     29              joint error (22), object position error (3) and quaternion
                                       difference (4) against the *original* reference at t
``original_future``    116             the original reference at t+1, t+2, t+4, t+12: joints (4×22),
                                       object poses (4×7)
``edit``               140 (R only)    the accumulated reference edit at t, t+1, t+2, t+4, t+12: joints
                                       (5×22), object position + rotation vector (5×6)
``lead``               2 (L only)      the lead channel L latched for the episode, control steps (arm,
                                       hand; 0 until it does)
``reach``              1 (A only)      the reach channel A latched for the episode (0 until it does)
``gain``               2 (K only)      the gains channel K latched for the episode (arm, hand; 0 until
                                       it does)
``start_offset``       3               where the object started the episode minus where the reference
                                       had it (Table 3 moves it by N(0, 5 cm) per axis)
``servo_lag``          22              joint targets minus joint positions
``last_action``        D               the modulator's previous action (its flat action, [−1, 1])
``phase``              1               control steps since the episode began, ÷ 100
``held``               1 (k > 1 only)  1 between the modulator's decisions, 0 where it decides
                                       (``decide_every`` = k: at the episode's steps 0, k, 2k, …)
``history``            H × 51          the H previous frames' joint positions (22), joint targets (22)
                                       and object pose (7), newest first (zeros before the first step)
=====================  ==============  =============================================================

With ``decide_every`` = k > 1 the modulator decides every k control steps and its action holds in
between (:class:`adadex.transforms.modulation.ModulatorView` repeats its last action there; the
modulator's heads are a fixed N(0, 1) that no parameter moves where ``held`` is set). One decision
then moves the tracker for k steps — an edit large enough for the return to show — and PPO scores
one choice per k steps instead of k nearly invisible ones.

The view's state is what the modulator's environment carries from step to step (zero at reset):
``("modulation", "last_action")``, ``("modulation", "steps")`` and ``("modulation", "history")``.
:class:`adadex.transforms.modulation.ModulatorView` carries them in the transformed env (training);
:func:`adadex.transforms.policy.make_policy` carries them through its primer (evaluation on a plain
env). Both call the functions here, so the two paths see the same numbers.

Example
-------
>>> layout = ViewLayout("R+T", history=3)
>>> layout.dim, layout.action_dim
(871, 134)
>>> [name for name, _ in layout.parts][:3]
['observation', 'original_error', 'original_future']
"""

from __future__ import annotations

import torch
from tensordict import TensorDictBase

from adadex.envs.observation import (JOINT_POS, JOINT_TARGET, OBJECT_POSE, OBJECT_START, OBS_DIM, OBSERVATION,
                                     REF_JOINT_POS, REF_OBJECT_POSE, REF_OBJECT_START, REF_OFFSETS)
from adadex.errors import UnknownKeyError, check_number
from adadex.modules.channels import GAIN_STATE, HAND_EDIT, LEAD_STATE, MOD, OBJECT_EDIT, REACH_STATE, ModulationLayout
from adadex.quat import quat_conj, quat_diff, quat_from_rotvec, quat_mul
from adadex.sim.robot import NUM_JOINTS

VIEW = ("modulator", "view")
LAST_ACTION = (MOD, "last_action")
STEPS = (MOD, "steps")
HISTORY = (MOD, "history")
#: one history frame: joint positions, joint targets, object pose
FRAME_DIM = 2 * NUM_JOINTS + 7
_FUTURE = len(REF_OFFSETS) - 1
_ROWS = list(REF_OFFSETS)


class ViewLayout:
    """The parts of the view for a channel set and history length (see the module docstring)."""

    def __init__(self, channels="R+O+T", history: int = 3, decide_every: int = 1):
        check_number("ViewLayout.history", history, integer=True)
        check_number("ViewLayout.decide_every", decide_every, low=1, integer=True)
        self.channels = ModulationLayout(channels)
        self.history = int(history)
        self.decide_every = int(decide_every)
        self.action_dim = self.channels.dim
        parts = [("observation", OBS_DIM), ("original_error", NUM_JOINTS + 7),
                 ("original_future", _FUTURE * (NUM_JOINTS + 7))]
        if "R" in self.channels:
            parts.append(("edit", len(REF_OFFSETS) * (NUM_JOINTS + 6)))
        if "L" in self.channels:
            parts.append(("lead", 2))
        if "A" in self.channels:
            parts.append(("reach", 1))
        if "K" in self.channels:
            parts.append(("gain", 2))
        parts += [("start_offset", 3), ("servo_lag", NUM_JOINTS), ("last_action", self.action_dim), ("phase", 1)]
        if self.decide_every > 1:
            parts.append(("held", 1))
        parts.append(("history", self.history * FRAME_DIM))
        self.parts = tuple(parts)
        self.dim = sum(n for _, n in parts)

    def slices(self) -> dict[str, slice]:
        """Part name → its slice of the view."""
        out, start = {}, 0
        for name, n in self.parts:
            out[name] = slice(start, start + n)
            start += n
        return out

    def state_shapes(self) -> dict:
        """{key: shape} of the state the view needs carried between steps."""
        return {LAST_ACTION: (self.action_dim,), STEPS: (1,), HISTORY: (self.history, FRAME_DIM)}

    def __repr__(self) -> str:
        every = f", decide_every={self.decide_every}" if self.decide_every > 1 else ""
        return f"ViewLayout({self.channels.name!r}, history={self.history}{every}, dim={self.dim})"

    def held(self, steps: torch.Tensor) -> torch.Tensor:
        """(…, 1) bool: where the modulator's action holds at this step (``steps``: control steps
        taken in the episode, the view's state) — every step that is not a multiple of ``decide_every``."""
        return (steps.round().long() % self.decide_every) != 0


def _zeros_like_state(td: TensorDictBase, layout: ViewLayout) -> dict:
    ref = td.get(REF_JOINT_POS)
    return {k: ref.new_zeros(*td.batch_size, *s) for k, s in layout.state_shapes().items()}


def _edits(td: TensorDictBase):
    """The accumulated reference edit at the observed offsets (zeros without a persistent R)."""
    ref_q = td.get(REF_JOINT_POS)
    hand, obj = td.get(HAND_EDIT, None), td.get(OBJECT_EDIT, None)
    hand = ref_q.new_zeros(*ref_q.shape) if hand is None else hand[..., _ROWS, :]
    obj = ref_q.new_zeros(*ref_q.shape[:-1], 6) if obj is None else obj[..., _ROWS, :]
    return hand, obj


def original_reference(td: TensorDictBase, edits=None) -> tuple[torch.Tensor, torch.Tensor]:
    """The reference before R's carried edit: (joints (…, 5, 22), object poses (…, 5, 7)), undoing
    :func:`adadex.transforms.modulation.ReferenceModulation`'s edit (shift, left rotation);
    ``edits``: that edit at the observed offsets when the caller already read it."""
    hand, obj = _edits(td) if edits is None else edits
    ref_q, ref_o = td.get(REF_JOINT_POS), td.get(REF_OBJECT_POSE)
    q = quat_mul(quat_conj(quat_from_rotvec(obj[..., 3:])), ref_o[..., 3:])
    return ref_q - hand, torch.cat([ref_o[..., :3] - obj[..., :3], q], dim=-1)


def view_features(td: TensorDictBase, layout: ViewLayout) -> torch.Tensor:
    """The (…, layout.dim) view of ``td`` (an env step's entries with the view's state)."""
    lead = td.batch_size
    joint_pos, obj = td.get(JOINT_POS), td.get(OBJECT_POSE)
    edits = _edits(td)
    orig_q, orig_o = original_reference(td, edits)
    state = {k: td.get(k, None) for k in layout.state_shapes()}
    if any(v is None for v in state.values()):
        missing = [k for k, v in state.items() if v is None]
        raise UnknownKeyError(f"the modulator's view needs its state {missing} in the tensordict: run it on "
                              "TransformedEnv(env, modulation(…, view=…)) or add policy.primer() to the env")
    parts = {
        "observation": td.get(OBSERVATION),
        "original_error": torch.cat([joint_pos - orig_q[..., 0, :], obj[..., :3] - orig_o[..., 0, :3],
                                     quat_diff(obj[..., 3:], orig_o[..., 0, 3:])], -1),
        "original_future": torch.cat([orig_q[..., 1:, :].reshape(*lead, -1), orig_o[..., 1:, :].reshape(*lead, -1)],
                                     -1),
        "start_offset": td.get(OBJECT_START)[..., :3] - td.get(REF_OBJECT_START)[..., :3],
        "servo_lag": td.get(JOINT_TARGET) - joint_pos,
        "last_action": state[LAST_ACTION],
        "phase": state[STEPS] / 100.0,
        "held": layout.held(state[STEPS]).to(joint_pos.dtype),
        "history": state[HISTORY].reshape(*lead, -1),
    }
    if "R" in layout.channels:
        hand, ob = edits
        parts["edit"] = torch.cat([hand.reshape(*lead, -1), ob.reshape(*lead, -1)], -1)
    if "L" in layout.channels:
        ahead = td.get(LEAD_STATE, None)
        parts["lead"] = joint_pos.new_zeros(*lead, 2) if ahead is None else ahead[..., :2]
    if "A" in layout.channels:
        reach = td.get(REACH_STATE, None)
        parts["reach"] = joint_pos.new_zeros(*lead, 1) if reach is None else reach[..., :1]
    if "K" in layout.channels:
        gain = td.get(GAIN_STATE, None)
        parts["gain"] = joint_pos.new_zeros(*lead, 2) if gain is None else gain[..., :2]
    return torch.cat([parts[name] for name, _ in layout.parts], -1)


def next_view_state(td: TensorDictBase, layout: ViewLayout) -> dict:
    """The view's state for the next step, from this step's entries after the inverse path (its
    ``("modulation", …)`` channel entries are the modulator's action)."""
    state = {k: td.get(k, None) for k in layout.state_shapes()}
    if any(v is None for v in state.values()):
        state = _zeros_like_state(td, layout)
    entries = [td.get(key).reshape(*td.batch_size, -1).clamp(-1.0, 1.0) for key, _, _ in layout.channels.segments]
    frame = torch.cat([td.get(JOINT_POS), td.get(JOINT_TARGET), td.get(OBJECT_POSE)], -1)
    history = torch.cat([frame[..., None, :], state[HISTORY][..., :-1, :]], -2) if layout.history else state[HISTORY]
    return {LAST_ACTION: torch.cat(entries, -1) if entries else state[LAST_ACTION],
            STEPS: state[STEPS] + 1, HISTORY: history}
