"""Object anchoring: move the reference's hand onto the object where it actually lies.

Table 3 displaces the object at each reset (x, y + N(0, 5 cm)), and a tracker whose feed-forward is
kinematic replay closes the hand where the *reference* object is: under the displacement alone,
replay lifts a mug in about a fifth of the episodes (docs/training-log.md). :class:`ObjectAnchor` turns
the feed-forward into replay of a reference shifted onto the observed object:

* ``Δ`` — the horizontal offset between where the object started this episode (the pose the env
  saw at the episode's first frame, ``("object", "start_pose")``) and where the reference object
  starts (``("object", "reference_start")``). It is fixed for the episode: anchoring to the object's
  *current* pose instead made the hand chase an object it had nudged, and under Table 3's action
  noise that ran away (terminations 44 → 86 % for replay so anchored). The height is left alone so
  the hand is never pushed into the table;
* ``w`` — 1 until the reference object at t+``lookahead`` has travelled ``hold`` from its start (the
  references are noisy on purpose: an object at rest jitters by up to 1 cm), then falling linearly
  to 0 over the next ``release`` of travel: the hand reaches and grasps the object where it lies, then,
  as the reference carries the object, returns to the reference path and brings the object onto it.
  ``lookahead`` is one of the observation's future reference frames (t+1, t+2, t+4, t+12): reading
  further ahead starts the return before the reference object moves, which the position servos'
  lag otherwise leaves behind (channel A's ``reach_lookahead``, docs/modulation.md);
* ``Δq`` — the arm-joint change that moves the palm by ``w·Δ`` without turning it, at the next
  reference joints: ``iterations`` Gauss–Newton steps of damped least squares on the palm's pose and
  Jacobian (pytorch-kinematics' chain from the robot's MJCF, folded to its six joints:
  :class:`~adadex.sim.kinematics.RevoluteChainJacobian`). One step, the linearization alone, leaves
  the palm 1.1 cm off its target on average at an 8 cm shift (up to 2.2 cm) and 1.7 cm at 10 cm,
  turned by up to 6°, on the specialist benchmark's references; three steps leave 0.01 / 0.05 cm.
  That miss was where grasps failed: the untrained anchored feed-forward completed 82.5 % of the
  benchmark's frames with one step and 87.4 % with three, 77.2 → 91.9 % on objects displaced
  7–10 cm (docs/training-log.md);
* ``reach`` (optional) — objects displaced by ``|Δ| ≥ reach`` are left where they are (no shift).
  The paper's success thresholds hold a frame to 0.5·T_o + 0.5·T_h ≤ 10 cm: a hand holding an object
  displaced by ``|Δ|`` is ``|Δ|`` off the reference palm while the object is ``|Δ|`` off its reference,
  so past 10 cm every frame from the reach to the return fails, where replay passes every frame
  until the reference carries the object away. On the specialist benchmark's episodes the
  feed-forward alone completed 33.8 % of the frames of objects displaced ≥ 10 cm anchored, and
  56.4 % with ``reach = 0.09`` (replay 58.8 %; docs/training-log.md).

It is a function of what the policy observes, so a tracker using it is still one TensorDictModule
over the observation (distillation clones it as it is).

Example
-------
>>> import torch
>>> anchor = ObjectAnchor(release=0.05)
>>> obs, start, ref_start = torch.zeros(2, 273), torch.zeros(2, 7), torch.zeros(2, 7)
>>> start[:, 0] = 0.03                      # the object started 3 cm off its reference in x
>>> dq = anchor(obs, start, ref_start)
>>> dq.shape, bool(dq[:, 6:].abs().max() == 0), bool(dq[:, :6].abs().max() > 0)
(torch.Size([2, 22]), True, True)
"""

from __future__ import annotations

import pytorch_kinematics as pk
import torch
from torch import nn

from adadex.envs.observation import LAYOUT, NEXT_REF_JOINTS as _NEXT_REF, REF_OFFSETS
from adadex.errors import ConfigError, check_number
from adadex.sim.kinematics import RevoluteChainJacobian, RobotKinematics
from adadex.sim.robot import NUM_JOINTS, TRACKED_SITES

ARM_JOINTS = 6
#: the reference frames ahead (control steps) whose object position the observation holds
LOOKAHEADS = REF_OFFSETS[1:]


def ref_object_slice(lookahead: int = 1) -> slice:
    """Where the flat observation holds the reference object's position at t+``lookahead`` (one of
    :data:`LOOKAHEADS`; :class:`~adadex.errors.ConfigError` otherwise)."""
    if lookahead not in LOOKAHEADS or isinstance(lookahead, bool):
        raise ConfigError(f"the object anchor's lookahead must be one of the observation's reference frames ahead "
                          f"{LOOKAHEADS} (control steps), got {lookahead!r}")
    start = LAYOUT["ref_object_future"].start + 7 * LOOKAHEADS.index(lookahead)
    return slice(start, start + 3)


class PalmShift:
    """(n, 6) arm joints, (n, 3) palm shift (m, base frame) → (n, 6) arm-joint change that moves the
    palm by the shift without turning it: ``iterations`` damped Gauss–Newton steps on the palm's pose,
    each re-linearized at the joints reached (see the module docstring for what one step misses).
    Shared by :class:`ObjectAnchor` and the modulator's compact channel
    (:class:`adadex.transforms.modulation.CompactModulation`). Holds no parameters.

    Args:
        damping: the Gauss–Newton steps' damping λ (> 0; default 0.02): each solves
            (J Jᵀ + λ² I) x = error.
        iterations: Gauss–Newton steps (≥ 1; default 3).

    Examples:
        >>> import torch
    >>> dq = PalmShift()(torch.zeros(4, 6), torch.tensor([[0.05, 0.0, 0.0]]).expand(4, 3))
    >>> dq.shape, bool(dq.abs().max() > 0)
    (torch.Size([4, 6]), True)
    """

    def __init__(self, damping: float = 0.02, iterations: int = 3):
        self.damping = float(check_number("PalmShift.damping", damping, strict_low=True))
        self.iterations = int(check_number("PalmShift.iterations", iterations, low=1, integer=True))
        palm = pk.SerialChain(RobotKinematics(dtype=torch.float32).chain, TRACKED_SITES[0])
        names = palm.get_joint_parameter_names()
        if len(names) != ARM_JOINTS:
            raise ValueError(f"the palm's chain should hold the {ARM_JOINTS} arm joints, got {names}")
        self._palm = RevoluteChainJacobian(palm)

    def __call__(self, q: torch.Tensor, shift: torch.Tensor) -> torch.Tensor:
        if self._palm.folds.device != q.device:
            self._palm.to(device=q.device)
        dtype = q.dtype
        q, shift = q.float(), shift.float()
        eye = torch.eye(6, dtype=q.dtype, device=q.device)
        error = torch.cat([shift, torch.zeros_like(shift)], dim=-1)
        x, target = q, None
        for _ in range(self.iterations):
            jac, pose = self._palm(x)                                        # (n, 6, 6), (n, 4, 4) in the base frame
            if target is None:                                              # at q the error is the shift itself
                target = pose[:, :3, 3] + shift, pose[:, :3, :3]
            else:
                turn = target[1] @ pose[:, :3, :3].transpose(1, 2)
                error = torch.cat([target[0] - pose[:, :3, 3],
                                   0.5 * torch.stack([turn[:, 2, 1] - turn[:, 1, 2], turn[:, 0, 2] - turn[:, 2, 0],
                                                      turn[:, 1, 0] - turn[:, 0, 1]], dim=-1)], dim=-1)
            x = x + (jac.transpose(1, 2) @ torch.linalg.solve(jac @ jac.transpose(1, 2) + self.damping ** 2 * eye,
                                                             error[:, :, None]))[:, :, 0]
        return (x - q).to(dtype)


class ObjectAnchor(nn.Module):
    """(flat observation, object start pose, reference object start pose) → (…, 22) joint offset of
    the feed-forward (see the module docstring).

    Args:
        release: m the reference object travels, after ``hold``, while the anchor fades out (> 0).
        hold: m of travel from its start within which the reference object counts as at rest.
        damping: m, damping of the least-squares step (keeps it bounded near singular arm poses).
        reach: m; > 0 leaves objects displaced this far or farther unanchored; 0: no limit.
        iterations: Gauss–Newton steps towards the shifted palm pose (1: the linearized step alone,
            what trackers saved before 2026-11-26 used).
        lookahead: control steps ahead at which the reference object's travel is read (one of
            :data:`LOOKAHEADS`; default 1, the next frame).
    """

    def __init__(self, release: float = 0.05, hold: float = 0.02, damping: float = 0.02, reach: float = 0.0,
                 iterations: int = 3, lookahead: int = 1):
        super().__init__()
        self.release = float(check_number("ObjectAnchor.release", release, strict_low=True))
        self.hold = float(check_number("ObjectAnchor.hold", hold))
        self.damping = float(check_number("ObjectAnchor.damping", damping, strict_low=True))
        self.reach = float(check_number("ObjectAnchor.reach", reach))
        self.iterations = int(check_number("ObjectAnchor.iterations", iterations, low=1, integer=True))
        self._ref_object = ref_object_slice(lookahead)
        self.lookahead = int(lookahead)
        self._shift = PalmShift(damping, iterations)     # no nn.Module: its tensors stay out of the state dict

    def weight(self, observation: torch.Tensor, ref_object_start: torch.Tensor) -> torch.Tensor:
        """(…,) anchor weight: 1 while the reference object (at t+``lookahead``) is at rest, 0 once it
        travelled ``hold + release`` from its start."""
        return self.travel_weight(torch.linalg.vector_norm(observation[..., self._ref_object]
                                                           - ref_object_start[..., :3], dim=-1))

    def travel_weight(self, travel: torch.Tensor) -> torch.Tensor:
        """(…,) anchor weight of the reference object's travel (m) from its start at t+1."""
        return (1.0 - (travel - self.hold) / self.release).clamp(0.0, 1.0)

    def palm_shift(self, offset_xy: torch.Tensor, travel: torch.Tensor) -> torch.Tensor:
        """(…, 3) palm shift (m, base frame) of the anchor: ``w·Δ`` with the height left alone, from
        the object's horizontal start offset ``Δ`` (…, 2) and the reference object's travel (…,)
        (``reach`` applied). What :meth:`forward` moves the palm by; the modulator's anchor prior
        (:class:`adadex.modules.modulator.ActionShift`) asks channel C for the same shift."""
        weight = self.travel_weight(travel)
        if self.reach > 0:
            weight = weight * (offset_xy.norm(dim=-1) < self.reach)
        return torch.cat([offset_xy * weight[..., None], torch.zeros_like(offset_xy[..., :1])], dim=-1)

    def forward(self, observation: torch.Tensor, object_start: torch.Tensor, ref_object_start: torch.Tensor
                ) -> torch.Tensor:
        lead = observation.shape[:-1]
        obs = observation.reshape(-1, observation.shape[-1])
        start, ref_start = object_start.reshape(-1, 7), ref_object_start.reshape(-1, 7)
        travel = torch.linalg.vector_norm(obs[:, self._ref_object] - ref_start[:, :3], dim=-1)
        shift = self.palm_shift(start[:, :2] - ref_start[:, :2], travel)       # palm: move, do not turn
        out = torch.zeros(obs.shape[0], NUM_JOINTS, dtype=obs.dtype, device=obs.device)
        rows = shift.any(dim=1).nonzero()[:, 0]      # the Jacobian only where there is a shift
        if len(rows):
            out[rows, :ARM_JOINTS] = self._shift(obs[rows, _NEXT_REF][:, :ARM_JOINTS], shift[rows, :3])
        return out.reshape(*lead, NUM_JOINTS)
