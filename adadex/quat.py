"""Quaternion algebra, w-first (as MuJoCo stores them), batched over leading dims.

This is the one definition of each quaternion operation in adadex — product, conjugate,
normalization, difference, angle, rotating vectors, rotation-vector maps — and every one runs on
torch tensors (with autograd) and numpy arrays alike (:mod:`adadex.arrays`). Pose helpers and the
bridge to scipy (for Slerp, Euler angles, random rotations) are in :mod:`adadex.geometry`.

The *difference* of two orientations is defined here once and used everywhere (observation,
reward, metrics): ``quat_diff(a, b)`` is the rotation that takes ``b`` to ``a``, ``a ⊗ b⁻¹``, as a
unit quaternion with w ≥ 0; its angle, :func:`quat_angle`, is the rotation error. Both treat q and
−q as the same rotation.

Example
-------
>>> import math, torch
>>> a = torch.tensor([math.cos(0.25), 0.0, 0.0, math.sin(0.25)])   # 0.5 rad about z
>>> b = torch.tensor([1.0, 0.0, 0.0, 0.0])
>>> round(float(quat_angle(quat_diff(a, b))), 6), round(float(quat_angle(quat_diff(-a, b))), 6)
(0.5, 0.5)
>>> import numpy as np
>>> np.round(quat_rotate(a.numpy(), np.array([1.0, 0.0, 0.0])), 4).tolist()   # x turns toward y
[0.8776, 0.4794, 0.0]
>>> np.round(rotvec_from_quat(quat_from_rotvec(np.array([0.0, 0.0, 0.5]))), 6).tolist()
[0.0, 0.0, 0.5]
"""

from __future__ import annotations

import numpy as np
import torch

from adadex.arrays import namespace


def _hamilton_table() -> np.ndarray:
    """(16, 4) structure constants of the Hamilton product: (a ⊗ b)_i = Σ_jk C[4j + k, i] a_j b_k."""
    c = np.zeros((4, 4, 4))
    # (j, k) → (i, sign): e.g. w·x → +x, x·y → +z, y·x → −z.
    table = {(0, 0): (0, 1), (0, 1): (1, 1), (0, 2): (2, 1), (0, 3): (3, 1),
             (1, 0): (1, 1), (1, 1): (0, -1), (1, 2): (3, 1), (1, 3): (2, -1),
             (2, 0): (2, 1), (2, 1): (3, -1), (2, 2): (0, -1), (2, 3): (1, 1),
             (3, 0): (3, 1), (3, 1): (2, 1), (3, 2): (1, -1), (3, 3): (0, -1)}
    for (j, k), (i, sign) in table.items():
        c[j, k, i] = sign
    return c.reshape(16, 4)


_CONSTANTS = {"hamilton": _hamilton_table(), "conj": np.array([1.0, -1.0, -1.0, -1.0])}
_CACHE: dict = {}


def _constant(name: str, like):
    """The constant ``name`` in ``like``'s namespace, dtype and device (converted once, then cached)."""
    is_torch = isinstance(like, torch.Tensor)
    key = (name, like.dtype, like.device) if is_torch else (name, like.dtype)
    c = _CACHE.get(key)
    if c is None:
        c = _CONSTANTS[name]
        c = _CACHE[key] = torch.as_tensor(c, dtype=like.dtype, device=like.device) if is_torch else c.astype(like.dtype)
    return c


def quat_mul(a, b):
    """Hamilton product a ⊗ b of (…, 4) w-first quaternions (broadcast over leading dims).

    One outer product and one small matmul instead of 28 scalar ops: this runs in every env step."""
    outer = a[..., :, None] * b[..., None, :]
    outer = outer.reshape(*outer.shape[:-2], 16)
    return outer @ _constant("hamilton", outer)


def quat_conj(q):
    """Conjugate (the inverse of a unit quaternion)."""
    return q * _constant("conj", q)


def quat_canonical(q):
    """The same rotation with w ≥ 0."""
    return namespace(q).where(q[..., :1] < 0, -q, q)


def quat_diff(a, b):
    """Relative rotation a ⊗ b⁻¹ (takes ``b`` to ``a``), canonical (w ≥ 0). The one definition."""
    return quat_canonical(quat_mul(a, quat_conj(b)))


def quat_angle(q):
    """Rotation angle in [0, π] of (…, 4) unit quaternions, robust near 0 and π."""
    xp = namespace(q)
    return 2.0 * xp.arctan2(xp.linalg.vector_norm(q[..., 1:], axis=-1), abs(q[..., 0]))


def quat_angle_between(a, b):
    """``quat_angle(quat_diff(a, b))`` computed from the dot product alone (the relative rotation's w
    is a·b for unit quaternions): the same value, a fraction of the work, for rewards and metrics."""
    xp = namespace(a)
    w = abs((a * b).sum(axis=-1))
    return 2.0 * xp.arctan2(xp.sqrt(xp.clip(1.0 - w * w, 0.0, None)), w)


def quat_normalize(q):
    """(…, 4) quaternions scaled to unit norm (e.g. after float32 rounding)."""
    return q / namespace(q).linalg.vector_norm(q, axis=-1, keepdims=True)


def _cross(a, b):
    """Cross product over the last axis, by indexing (numpy's and torch's ``cross`` differ in signature)."""
    return a[..., [1, 2, 0]] * b[..., [2, 0, 1]] - a[..., [2, 0, 1]] * b[..., [1, 2, 0]]


def quat_rotate(q, v):
    """(…, 3) vectors ``v`` rotated by (…, 4) unit quaternions ``q`` (broadcast): q ⊗ (0, v) ⊗ q⁻¹.

    Computed as v + w·t + u × t with t = 2 u × v (u the vector part of q), without the two products."""
    u = q[..., 1:]
    t = 2.0 * _cross(u, v)
    return v + q[..., :1] * t + _cross(u, t)


def quat_from_rotvec(v):
    """(…, 3) rotation vectors (axis · angle, rad) → (…, 4) unit quaternions; exact at 0."""
    xp = namespace(v)
    angle = xp.linalg.vector_norm(v, axis=-1, keepdims=True)
    half = 0.5 * angle
    # sin(θ/2)/θ → 1/2 as θ → 0; the Taylor form keeps the gradient finite there.
    k = xp.where(angle > 1e-6, xp.sin(half) / xp.clip(angle, 1e-6, None), 0.5 - angle * angle / 48.0)
    return xp.concatenate([xp.cos(half), k * v], axis=-1)


def rotvec_from_quat(q):
    """(…, 4) unit quaternions → (…, 3) rotation vectors with angle in [0, π] (q and −q agree)."""
    xp = namespace(q)
    q = quat_canonical(q)
    s = xp.linalg.vector_norm(q[..., 1:], axis=-1, keepdims=True)
    angle = 2.0 * xp.arctan2(s, q[..., :1])
    k = xp.where(s > 1e-6, angle / xp.clip(s, 1e-6, None), 2.0 + s * s / 3.0)
    return k * q[..., 1:]
