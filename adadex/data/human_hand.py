"""A kinematic human hand that produces 21 keypoints in MANO joint order.

The synthesizer animates this hand (wrist pose + 20 joint angles per frame) and retargeting maps
its keypoints to the robot, exactly as it would map keypoints of captured human motion. Its
proportions are a human's (phalanx lengths and knuckle positions of an adult hand), so the
robot — whose palm is shorter and fingers longer, with no little finger — can follow it only
approximately: that is the *embodiment bias* the references carry on purpose.

Keypoint order (:data:`KEYPOINT_NAMES`, the MANO order: its 16 joints, then the 5 tips)::

    0 wrist   1-3 index MCP, PIP, DIP    4-6 middle    7-9 little    10-12 ring
    13-15 thumb CMC, MCP, IP    16 thumb tip  17 index tip  18 middle tip  19 ring tip  20 little tip

Hand frame (the robot's palm frame too): fingers along +z, palm facing −x, index finger on +y.

Angles (:data:`ANGLE_NAMES`, 20 per frame): for index, middle, little, ring — MCP flexion, MCP
abduction, PIP flexion, DIP flexion; for the thumb — CMC flexion, CMC abduction, MCP flexion, IP
flexion. Positive flexion curls toward the palm.

Example
-------
>>> import numpy as np
>>> hand = HumanHand()
>>> kp = hand.keypoints(np.array([[0, 0, 0, 1.0, 0, 0, 0]]), np.zeros((1, 20)))
>>> kp.shape, round(float(kp[0, 18, 2]), 3)   # open hand: middle tip straight up the z axis
((1, 21, 3), 0.191)
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from adadex.quat import quat_normalize, quat_rotate

KEYPOINT_NAMES = (
    "wrist", "index1", "index2", "index3", "middle1", "middle2", "middle3", "little1", "little2", "little3",
    "ring1", "ring2", "ring3", "thumb1", "thumb2", "thumb3",
    "thumb_tip", "index_tip", "middle_tip", "ring_tip", "little_tip",
)
FINGERS = ("index", "middle", "little", "ring")  # MANO order
ANGLE_NAMES = tuple(f"{f}_{j}" for f in FINGERS for j in ("mcp", "abd", "pip", "dip")) + (
    "thumb_cmc", "thumb_abd", "thumb_mcp", "thumb_ip")
NUM_ANGLES = len(ANGLE_NAMES)
TIP_INDEX = {"thumb": 16, "index": 17, "middle": 18, "ring": 19, "little": 20}
_FINGER_KP = {"index": (1, 2, 3, 17), "middle": (4, 5, 6, 18), "little": (7, 8, 9, 20), "ring": (10, 11, 12, 19)}
_THUMB_KP = (13, 14, 15, 16)

#: Joint-angle bounds (rad) used by the synthesizer's grasp solver, per angle in :data:`ANGLE_NAMES` order.
ANGLE_LIMITS = np.array(
    [(-0.3, 1.6), (-0.35, 0.35), (0.0, 1.8), (0.0, 1.4)] * 4
    + [(-0.4, 1.2), (-0.6, 0.9), (-0.2, 1.1), (-0.3, 1.4)]
)

# Adult hand (m): knuckle positions in the hand frame and bone lengths (MCP→PIP, PIP→DIP, DIP→tip).
_KNUCKLES = {"index": (0.0, 0.024, 0.090), "middle": (0.0, 0.004, 0.094),
             "little": (0.0, -0.032, 0.080), "ring": (0.0, -0.014, 0.089)}
_BONES = {"index": (0.040, 0.024, 0.022), "middle": (0.045, 0.028, 0.024),
          "little": (0.033, 0.020, 0.021), "ring": (0.042, 0.027, 0.023)}
_THUMB_BASE = (-0.012, 0.022, 0.028)
_THUMB_BONES = (0.045, 0.032, 0.028)
_THUMB_DIR = (-0.30, 0.70, 0.65)     # rest direction of the thumb metacarpal
_THUMB_CURL = (-1.0, -0.45, 0.0)     # the thumb flexes toward the palm and the fingers


def _rx(a: np.ndarray) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    o, z = np.ones_like(a), np.zeros_like(a)
    return np.stack([np.stack([o, z, z], -1), np.stack([z, c, -s], -1), np.stack([z, s, c], -1)], -2)


def _flex(a: np.ndarray) -> np.ndarray:
    """Rotation by ``a`` about −y: +z bends toward −x (the palm side)."""
    c, s = np.cos(a), np.sin(a)
    o, z = np.ones_like(a), np.zeros_like(a)
    return np.stack([np.stack([c, z, -s], -1), np.stack([z, o, z], -1), np.stack([s, z, c], -1)], -2)


def _frame_from_z(z_axis, x_hint) -> np.ndarray:
    z = np.asarray(z_axis, float) / np.linalg.norm(z_axis)
    x = np.asarray(x_hint, float) - np.dot(x_hint, z) * z
    x /= np.linalg.norm(x)
    return np.stack([x, np.cross(z, x), z], axis=1)


@dataclass(frozen=True)
class HumanHand:
    """A human hand of a given overall ``scale`` (1 = adult average, wrist→middle tip 0.191 m).

    ``bone_scale`` multiplies each finger's bones (keys as in :data:`FINGERS` plus ``"thumb"``); the
    synthesizer draws it per reference to vary proportions between "people".
    """

    scale: float = 1.0
    bone_scale: dict = field(default_factory=dict)

    @property
    def length(self) -> float:
        """Wrist → middle fingertip with the hand flat, m."""
        return self.scale * (_KNUCKLES["middle"][2] + sum(_BONES["middle"]) * self.bone_scale.get("middle", 1.0))

    def keypoints(self, wrist_pose: np.ndarray, angles: np.ndarray) -> np.ndarray:
        """(T, 21, 3) world keypoints from (T, 7) wrist poses and (T, 20) angles."""
        wrist_pose = np.asarray(wrist_pose, float)
        angles = np.asarray(angles, float)
        T = len(wrist_pose)
        local = np.zeros((T, 21, 3))
        for i, f in enumerate(FINGERS):
            mcp, abd, pip, dip = (angles[:, 4 * i + k] for k in range(4))
            bones = np.array(_BONES[f]) * self.bone_scale.get(f, 1.0)
            rot = _rx(abd) @ _flex(mcp)
            p = np.broadcast_to(np.array(_KNUCKLES[f]), (T, 3)).copy()
            idx = _FINGER_KP[f]
            local[:, idx[0]] = p
            for k, (bend, length) in enumerate(zip((pip, dip, None), bones)):
                p = p + rot[:, :, 2] * length
                local[:, idx[k + 1]] = p
                if bend is not None:
                    rot = rot @ _flex(bend)
        cmc, tabd, tmcp, tip = (angles[:, 16 + k] for k in range(4))
        base = _frame_from_z(_THUMB_DIR, -np.array(_THUMB_CURL))  # flexion bends toward −x
        rot = base @ _rx(tabd) @ _flex(cmc)
        p = np.broadcast_to(np.array(_THUMB_BASE), (T, 3)).copy()
        local[:, _THUMB_KP[0]] = p
        bones = np.array(_THUMB_BONES) * self.bone_scale.get("thumb", 1.0)
        for k, (bend, length) in enumerate(zip((tmcp, tip, None), bones)):
            p = p + rot[:, :, 2] * length
            local[:, _THUMB_KP[k + 1]] = p
            if bend is not None:
                rot = rot @ _flex(bend)
        local *= self.scale
        world = quat_rotate(quat_normalize(wrist_pose[:, None, 3:]), local)
        return world + wrist_pose[:, None, :3]
