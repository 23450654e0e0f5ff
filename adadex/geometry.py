"""Poses as numpy arrays: position (3) + unit quaternion (4, **w-first**, as MuJoCo stores it).

The quaternion algebra is :mod:`adadex.quat`'s (one definition for numpy and torch); this module
adds what poses need on top of it — composing, inverting, interpolating — and the bridge to scipy's
:class:`~scipy.spatial.transform.Rotation` for what scipy does best (Slerp, Euler angles, random
rotations, rotation matrices). scipy uses x-y-z-w (scalar-last) quaternions, so every conversion goes
through :func:`rotation` and :func:`quat`. Quaternions leaving this module are canonical (w ≥ 0), since
q and −q are the same rotation; input quaternions are normalized, as scipy does.

:func:`first_hits` casts rays at a triangle mesh (where a grasp's digits meet an object: the
synthesizer's human grasps, the scripted robot pinch).

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

__all__ = ["Rotation", "rotation", "quat", "compose", "inverse", "slerp_poses", "first_hits"]


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


def first_hits(triangles: np.ndarray, origins: np.ndarray, dirs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Distance to and index of the first triangle each ray hits (inf, -1 on a miss).

    Möller–Trumbore over all (ray, triangle) pairs; the meshes here have a few thousand faces and
    a grasp casts four rays, so brute force beats building a spatial index (trimesh's needs rtree).
    """
    v0, e1, e2 = triangles[:, 0], triangles[:, 1] - triangles[:, 0], triangles[:, 2] - triangles[:, 0]
    p = np.cross(dirs[:, None], e2[None])                       # (R, F, 3)
    det = np.einsum("rfk,fk->rf", p, e1)
    ok = np.abs(det) > 1e-12
    inv = np.where(ok, 1.0 / np.where(ok, det, 1.0), 0.0)
    s = origins[:, None] - v0[None]
    u = np.einsum("rfk,rfk->rf", s, p) * inv
    qv = np.cross(s, e1[None])
    v = np.einsum("rk,rfk->rf", dirs, qv) * inv
    t = np.einsum("fk,rfk->rf", e2, qv) * inv
    hit = ok & (u >= 0) & (v >= 0) & (u + v <= 1) & (t > 0)
    t = np.where(hit, t, np.inf)
    idx = np.argmin(t, axis=1)
    dist = t[np.arange(len(t)), idx]
    return dist, np.where(np.isfinite(dist), idx, -1)
