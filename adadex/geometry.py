"""Poses as numpy arrays: position (3) + unit quaternion (4, **w-first**, as MuJoCo stores it).

The quaternion algebra is :mod:`adadex.quat`'s (one definition for numpy and torch); this module
adds what poses need on top of it — composing, inverting, interpolating — and the bridge to scipy's
:class:`~scipy.spatial.transform.Rotation` for what scipy does best (Slerp, Euler angles, random
rotations, rotation matrices). scipy uses x-y-z-w (scalar-last) quaternions, so every conversion goes
through :func:`rotation` and :func:`quat`. Quaternions leaving this module are canonical (w ≥ 0), since
q and −q are the same rotation; input quaternions are normalized, as scipy does.

Example
-------
>>> import numpy as np
>>> q = quat(rotation(np.array([1.0, 0, 0, 0])) * Rotation.from_euler("z", 90, degrees=True))
>>> np.round(q, 4).tolist()
[0.7071, 0.0, 0.0, 0.7071]
>>> pose = np.concatenate([[1.0, 0.0, 0.0], q])          # 1 m along x, turned 90° about z
>>> np.round(compose(pose, [1.0, 0, 0, 1, 0, 0, 0]), 4).tolist()   # a point 1 m ahead of it
[1.0, 1.0, 0.0, 0.7071, 0.0, 0.0, 0.7071]
>>> np.round(compose(inverse(pose), pose), 12).tolist()
[0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0]
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

from adadex.quat import quat_canonical, quat_conj, quat_mul, quat_normalize, quat_rotate

__all__ = ["Rotation", "rotation", "quat", "compose", "inverse", "slerp_poses"]


def rotation(q_wxyz: np.ndarray) -> Rotation:
    """scipy Rotation from (…, 4) w-first quaternions."""
    q = np.asarray(q_wxyz, dtype=np.float64)
    return Rotation.from_quat(np.concatenate([q[..., 1:], q[..., :1]], axis=-1))


def quat(r: Rotation) -> np.ndarray:
    """(…, 4) canonical w-first quaternions of a scipy Rotation."""
    xyzw = r.as_quat()
    return quat_canonical(np.concatenate([xyzw[..., 3:], xyzw[..., :3]], axis=-1))


def compose(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Pose product a ∘ b of (…, 7) poses (broadcast): b expressed in a's frame, returned in a's parent frame."""
    a, b = (np.array(x, dtype=np.float64) for x in np.broadcast_arrays(a, b))
    qa, qb = quat_normalize(a[..., 3:]), quat_normalize(b[..., 3:])
    pos = a[..., :3] + quat_rotate(qa, b[..., :3])
    return np.concatenate([pos, quat_canonical(quat_mul(qa, qb))], axis=-1)


def inverse(a: np.ndarray) -> np.ndarray:
    """Inverse of (…, 7) poses."""
    a = np.array(a, dtype=np.float64)
    q = quat_conj(quat_normalize(a[..., 3:]))
    return np.concatenate([-quat_rotate(q, a[..., :3]), quat_canonical(q)], axis=-1)


def slerp_poses(p0: np.ndarray, p1: np.ndarray, s: np.ndarray) -> np.ndarray:
    """Poses between ``p0`` and ``p1`` (7,) at fractions ``s`` (T,): linear position, slerp rotation."""
    s = np.asarray(s, dtype=np.float64)
    key = Rotation.concatenate([rotation(p0[3:]), rotation(p1[3:])])
    rot = Slerp([0.0, 1.0], key)(np.clip(s, 0.0, 1.0))
    pos = p0[:3] + s[:, None] * (p1[:3] - p0[:3])
    return np.concatenate([pos, quat(rot)], axis=-1)
