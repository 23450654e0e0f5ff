"""The observation layout: structured entries, and the flat 273-D vector of the paper's Table 4.

The tracking environment writes structured entries (batch dims first)::

    ("proprio", "joint_pos")          (…, 22)       ("object", "pose")     (…, 7)
    ("proprio", "link_pose")          (…, 5, 7)     ("object", "latent")   (…, 64)
    ("reference", "hand_joint_pos")   (…, 5, 22)    reference frames at offsets REF_OFFSETS = (0, 1, 2, 4, 12)
    ("reference", "hand_link_pose")   (…, 5, 5, 7)
    ("reference", "object_pose")      (…, 5, 7)
    ("object", "start_pose")          (…, 7)        the object's pose seen at the episode's first frame
    ("object", "reference_start")     (…, 7)        the reference object's pose at that frame

(the last two are outside the 273-D vector; an object-anchored tracker reads them,
:mod:`adadex.modules.anchor`), and :func:`flat_observation` assembles the 273-D vector in exactly
this order (:data:`LAYOUT`):

====================  =======  ==========================================================
``joint_pos``         0–22     arm-hand joint positions
``link_pose``         22–57    palm pose and the 4 fingertip poses (5 × 7)
``object_pose``       57–64    object pose
``object_error``      64–71    object position minus reference position at t; quaternion
                               difference (:func:`adadex.quat.quat_diff`, current vs reference)
``ref_object_future`` 71–99    reference object poses at t+1, t+2, t+4, t+12
``joint_error``       99–121   joint positions minus reference joint positions at t
``ref_joint_future``  121–209  reference joint positions at t+1, t+2, t+4, t+12
``latent``            209–273  object latent
====================  =======  ==========================================================

This is the one function that builds the vector; the environment and the policy modules both call
it (:func:`flat_from_tensordict` reads the structured keys).

Example
-------
>>> import torch
>>> obs = flat_observation(torch.zeros(8, 22), torch.zeros(8, 5, 7), torch.zeros(8, 7), torch.zeros(8, 64),
...                        torch.zeros(8, 5, 22), torch.zeros(8, 5, 7))
>>> obs.shape
torch.Size([8, 273])
"""

from __future__ import annotations

import torch

from adadex.arrays import namespace
from adadex.errors import ArrayError
from adadex.quat import quat_diff
from adadex.sim.robot import NUM_JOINTS, TRACKED_SITES

REF_OFFSETS = (0, 1, 2, 4, 12)
#: Size of the object latent (the point-cloud encoder's code).
LATENT_DIM = 64
#: Size of the flat observation vector.
OBS_DIM = 273

OBSERVATION = "observation"                 # the flat 273-D vector
JOINT_POS = ("proprio", "joint_pos")
JOINT_TARGET = ("proprio", "joint_target")
LINK_POSE = ("proprio", "link_pose")
OBJECT_POSE = ("object", "pose")
OBJECT_LATENT = ("object", "latent")
OBJECT_START = ("object", "start_pose")        # (…, 7) the object pose seen at the episode's first frame
REF_JOINT_POS = ("reference", "hand_joint_pos")
REF_LINK_POSE = ("reference", "hand_link_pose")
REF_OBJECT_POSE = ("reference", "object_pose")
#: (…, 7) the reference object's pose at the episode's first frame (in the "object" group: teacher
#: rollouts keep a dataset index under "reference")
REF_OBJECT_START = ("object", "reference_start")
#: Ground truth the env reports for evaluation and logs, never for a policy: the metric errors
#: (``(PRIVILEGED, "errors", name)``), the unstable-physics flag and the reward's terms. A policy
#: reads only the keys above; TorchRL modules that take every observation key must leave this out.
PRIVILEGED = "privileged"
ERRORS = (PRIVILEGED, "errors")
UNSTABLE = (PRIVILEGED, "unstable")
REWARD_TERMS = (PRIVILEGED, "reward_terms")
REFERENCE_INDEX = (PRIVILEGED, "reference_index")
STEP = (PRIVILEGED, "step")

_SIZES = (("joint_pos", NUM_JOINTS), ("link_pose", 7 * len(TRACKED_SITES)), ("object_pose", 7), ("object_error", 7),
          ("ref_object_future", 7 * (len(REF_OFFSETS) - 1)), ("joint_error", NUM_JOINTS),
          ("ref_joint_future", NUM_JOINTS * (len(REF_OFFSETS) - 1)), ("latent", LATENT_DIM))


def _layout() -> dict[str, slice]:
    out, start = {}, 0
    for name, size in _SIZES:
        out[name] = slice(start, start + size)
        start += size
    assert start == OBS_DIM, start
    return out


#: Name → slice of the flat vector.
LAYOUT: dict[str, slice] = _layout()
#: The reference joints at t+1 within the flat vector (kinematic replay's next target).
NEXT_REF_JOINTS = slice(LAYOUT["ref_joint_future"].start, LAYOUT["ref_joint_future"].start + NUM_JOINTS)


_TAILS = ((NUM_JOINTS,), (len(TRACKED_SITES), 7), (7,), (LATENT_DIM,), (len(REF_OFFSETS), NUM_JOINTS),
          (len(REF_OFFSETS), 7))


def flat_observation(joint_pos: torch.Tensor, link_pose: torch.Tensor, object_pose: torch.Tensor,
                     latent: torch.Tensor, ref_joint_pos: torch.Tensor, ref_object_pose: torch.Tensor) -> torch.Tensor:
    """(…, 273) from the structured entries (shapes in the module docstring; reference arrays
    hold the frames at :data:`REF_OFFSETS`, the current one first); torch tensors or numpy arrays.

    Args:
        joint_pos: (…, 22) joint positions, rad.
        link_pose: (…, 5, 7) palm and fingertip poses (position m + wxyz quaternion).
        object_pose: (…, 7) object pose.
        latent: (…, 64) object latent.
        ref_joint_pos: (…, 5, 22) reference joint positions at the offsets.
        ref_object_pose: (…, 5, 7) reference object poses at the offsets.

    Returns:
        (…, 273) in the order of :data:`LAYOUT`. A wrong shape raises :class:`~adadex.errors.ArrayError`.
    """
    lead = tuple(joint_pos.shape[:-1])
    for name, x, tail in (("joint_pos", joint_pos, _TAILS[0]), ("link_pose", link_pose, _TAILS[1]),
                          ("object_pose", object_pose, _TAILS[2]), ("latent", latent, _TAILS[3]),
                          ("ref_joint_pos", ref_joint_pos, _TAILS[4]), ("ref_object_pose", ref_object_pose, _TAILS[5])):
        if tuple(x.shape) != lead + tail:
            raise ArrayError(f"{name}: expected shape {tuple(lead + tail)}, got {tuple(x.shape)}")
    ref_obj_now = ref_object_pose[..., 0, :]
    return namespace(joint_pos).concatenate([
        joint_pos,
        link_pose.reshape(*lead, -1),
        object_pose,
        object_pose[..., :3] - ref_obj_now[..., :3],
        quat_diff(object_pose[..., 3:], ref_obj_now[..., 3:]),
        ref_object_pose[..., 1:, :].reshape(*lead, -1),
        joint_pos - ref_joint_pos[..., 0, :],
        ref_joint_pos[..., 1:, :].reshape(*lead, -1),
        latent,
    ], axis=-1)


def flat_from_tensordict(td) -> torch.Tensor:
    """:func:`flat_observation` of a TensorDict holding the structured keys.

    Args:
        td: a TensorDict with the structured entries (module docstring), e.g. the environment's output.
    """
    return flat_observation(td.get(JOINT_POS), td.get(LINK_POSE), td.get(OBJECT_POSE), td.get(OBJECT_LATENT),
                            td.get(REF_JOINT_POS), td.get(REF_OBJECT_POSE))
