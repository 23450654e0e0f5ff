"""The kinematic-replay controller: the floor every learned tracker must beat.

``replay_policy()`` outputs Δq = q̂_{t+1} − q_target: the next reference joints minus the current
joint targets, so the targets follow the reference (and catch up after an action was clipped at
``TrackingConfig.max_action``). This is the reference replayed open-loop through the PD servos.

Example::

    from adadex.envs.replay import replay_policy
    td = env.rollout(299, replay_policy(), break_when_any_done=False)
"""

from __future__ import annotations

import torch
from tensordict.nn import TensorDictModule

from adadex.envs.observation import JOINT_TARGET, REF_JOINT_POS


def _delta(ref_joint_pos: torch.Tensor, joint_target: torch.Tensor) -> torch.Tensor:
    return ref_joint_pos[..., 1, :] - joint_target


def replay_policy() -> TensorDictModule:
    """A TensorDictModule reading ``("reference", "hand_joint_pos")`` and ``("proprio", "joint_target")``
    and writing ``"action"``."""
    return TensorDictModule(_delta, in_keys=[REF_JOINT_POS, JOINT_TARGET], out_keys=["action"])
