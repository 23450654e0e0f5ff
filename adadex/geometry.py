"""Poses as numpy arrays: position (3) + unit quaternion (4, **w-first**, as MuJoCo stores it).

scipy's :class:`~scipy.spatial.transform.Rotation` does the rotation algebra; it uses x-y-z-w
(scalar-last) quaternions, so every conversion goes through :func:`rotation` and :func:`quat`.
Quaternions leaving this module are canonical (w ≥ 0), since q and −q are the same rotation.

Example
-------
>>> import numpy as np
>>> q = quat(rotation(np.array([1.0, 0, 0, 0])) * Rotation.from_euler("z", 90, degrees=True))
>>> np.round(q, 4).tolist()
[0.7071, 0.0, 0.0, 0.7071]
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

__all__ = ["Rotation", "rotation", "quat", "canonical", "compose", "inverse", "slerp_poses"]


def rotation(q_wxyz: np.ndarray) -> Rotation:
    """scipy Rotation from (…, 4) w-first quaternions."""
    q = np.asarray(q_wxyz, dtype=np.float64)
    return Rotation.from_quat(np.concatenate([q[..., 1:], q[..., :1]], axis=-1))


def canonical(q_wxyz: np.ndarray) -> np.ndarray:
    """The same rotations with w ≥ 0."""
    q = np.asarray(q_wxyz, dtype=np.float64)
    return np.where(q[..., :1] < 0, -q, q)


def quat(r: Rotation) -> np.ndarray:
    """(…, 4) canonical w-first quaternions of a scipy Rotation."""
    xyzw = r.as_quat()
    return canonical(np.concatenate([xyzw[..., 3:], xyzw[..., :3]], axis=-1))


def compose(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Pose product a ∘ b of (…, 7) poses (broadcast): b expressed in a's frame, returned in a's parent frame."""
    a, b = (np.array(x, dtype=np.float64) for x in np.broadcast_arrays(a, b))
    ra = rotation(a[..., 3:])
    pos = a[..., :3] + ra.apply(b[..., :3].reshape(-1, 3)).reshape(b[..., :3].shape)
    return np.concatenate([pos, quat(ra * rotation(b[..., 3:]))], axis=-1)


def inverse(a: np.ndarray) -> np.ndarray:
    """Inverse of (…, 7) poses."""
    a = np.array(a, dtype=np.float64)
    r = rotation(a[..., 3:]).inv()
    pos = -r.apply(a[..., :3].reshape(-1, 3)).reshape(a[..., :3].shape)
    return np.concatenate([pos, quat(r)], axis=-1)


def slerp_poses(p0: np.ndarray, p1: np.ndarray, s: np.ndarray) -> np.ndarray:
    """Poses between ``p0`` and ``p1`` (7,) at fractions ``s`` (T,): linear position, slerp rotation."""
    s = np.asarray(s, dtype=np.float64)
    key = Rotation.concatenate([rotation(p0[3:]), rotation(p1[3:])])
    rot = Slerp([0.0, 1.0], key)(np.clip(s, 0.0, 1.0))
    pos = p0[:3] + s[:, None] * (p1[:3] - p0[:3])
    return np.concatenate([pos, quat(rot)], axis=-1)
