"""The per-frame functions give the same numbers on numpy arrays (the env's step) and torch tensors
(the policy modules, evaluation): one definition, two namespaces."""

import numpy as np
import pytest
import torch

from adadex.arrays import namespace, to_float
from adadex.envs.observation import flat_observation
from adadex.envs.reward import RewardConfig, tracking_reward
from adadex.eval.metrics import ERROR_NAMES, frame_errors
from adadex.geometry import compose, inverse, quat, rotation
from adadex.quat import (
    quat_angle,
    quat_angle_between,
    quat_conj,
    quat_diff,
    quat_from_rotvec,
    quat_mul,
    quat_normalize,
    quat_rotate,
    rotvec_from_quat,
)


def _quats(rng, *shape):
    q = rng.normal(size=(*shape, 4)).astype(np.float32)
    return q / np.linalg.norm(q, axis=-1, keepdims=True)


def _frame(seed=0, B=6):
    """A (B,) batch of hand, object and reference states, some close to the reference (bonus and
    gates on), some far."""
    rng = np.random.default_rng(seed)
    ref_link = np.concatenate([rng.normal(0, 0.1, (B, 5, 5, 3)), _quats(rng, B, 5, 5)], -1).astype(np.float32)
    ref_obj = np.concatenate([rng.normal(0, 0.1, (B, 5, 3)), _quats(rng, B, 5)], -1).astype(np.float32)
    ref_obj[:, 0, :3] = ref_link[:, 0, 0, :3] + 0.03          # reference hand near its object
    near = np.linspace(0.001, 0.3, B, dtype=np.float32)[:, None]   # world b is this far off
    link = ref_link[:, 0].copy()
    link[..., :3] += near[:, None] * rng.normal(size=(B, 5, 3)).astype(np.float32)
    link[:, :, 3:] = -link[:, :, 3:]                            # q ≡ −q
    obj = ref_obj[:, 0].copy()
    obj[:, :3] += near * rng.normal(size=(B, 3)).astype(np.float32)
    ref_q = rng.normal(0, 0.5, (B, 5, 22)).astype(np.float32)
    q = ref_q[:, 0] + near * rng.normal(size=(B, 22)).astype(np.float32)
    latent = rng.uniform(-1, 1, (B, 64)).astype(np.float32)
    return dict(q=q, link=link, obj=obj, latent=latent, ref_q=ref_q, ref_link=ref_link, ref_obj=ref_obj)


def _torch(d):
    return {k: torch.from_numpy(v.copy()) for k, v in d.items()}


def test_namespace_and_to_float():
    assert namespace(np.zeros(2)) is np and namespace(torch.zeros(2)) is torch
    assert to_float(np.array([True, False]), np.zeros(1, np.float32)).dtype == np.float32
    assert to_float(torch.tensor([True]), torch.zeros(1, dtype=torch.float64)).dtype == torch.float64


def test_quaternion_functions_agree():
    rng = np.random.default_rng(1)
    a, b = _quats(rng, 8), _quats(rng, 8)
    ta, tb = torch.from_numpy(a), torch.from_numpy(b)
    for fn in (quat_mul, quat_diff):
        out = fn(a, b)
        assert isinstance(out, np.ndarray) and out.dtype == np.float32
        np.testing.assert_allclose(out, fn(ta, tb).numpy(), atol=1e-6)
    np.testing.assert_allclose(quat_conj(a), quat_conj(ta).numpy())
    np.testing.assert_allclose(quat_angle(quat_diff(a, b)), quat_angle_between(tb, ta).numpy(), atol=2e-3)
    np.testing.assert_allclose(quat_angle_between(a, b), quat_angle_between(ta, tb).numpy(), atol=1e-6)
    # broadcasting one quaternion against a batch
    np.testing.assert_allclose(quat_mul(a, b[0]), quat_mul(ta, tb[0]).numpy(), atol=1e-6)


def test_rotations_and_rotation_vectors_agree_with_each_other_and_scipy():
    rng = np.random.default_rng(3)
    q = quat_normalize(_quats(rng, 8).astype(np.float64))   # unit in float64, as scipy makes them
    v = rng.normal(size=(8, 3))
    rv = rng.normal(size=(8, 3))
    rv[0] = 0.0                                   # the rotvec maps are exact at 0
    tq, tv, trv = (torch.from_numpy(x) for x in (q, v, rv))
    np.testing.assert_allclose(quat_rotate(q, v), quat_rotate(tq, tv).numpy(), atol=1e-12)
    np.testing.assert_allclose(quat_rotate(q, v), rotation(q).apply(v), atol=1e-12)
    np.testing.assert_allclose(quat_from_rotvec(rv), quat_from_rotvec(trv).numpy(), atol=1e-12)
    np.testing.assert_allclose(rotvec_from_quat(q), rotvec_from_quat(tq).numpy(), atol=1e-12)
    np.testing.assert_allclose(rotvec_from_quat(q), rotation(q).as_rotvec(), atol=1e-12)
    np.testing.assert_allclose(rotvec_from_quat(quat_from_rotvec(rv)), rv, atol=1e-12)
    np.testing.assert_allclose(quat_normalize(3.0 * q), q, atol=1e-15)
    np.testing.assert_allclose(quat_normalize(3.0 * tq).numpy(), q, atol=1e-15)
    # rotating by q ⊗ p is rotating by p, then by q
    p = quat_normalize(_quats(rng, 8).astype(np.float64))
    np.testing.assert_allclose(quat_rotate(quat_mul(q, p), v), quat_rotate(q, quat_rotate(p, v)), atol=1e-12)


def test_pose_helpers_agree_with_scipy():
    rng = np.random.default_rng(4)
    a = np.concatenate([rng.normal(size=(6, 3)), _quats(rng, 6)], -1)   # float32-rounded quaternions
    b = np.concatenate([rng.normal(size=(6, 3)), _quats(rng, 6)], -1)
    ab = compose(a, b)
    ra, rb = rotation(a[:, 3:]), rotation(b[:, 3:])
    np.testing.assert_allclose(ab[:, :3], a[:, :3] + ra.apply(b[:, :3]), atol=1e-12)
    np.testing.assert_allclose(ab[:, 3:], quat(ra * rb), atol=1e-12)
    assert (ab[:, 3] >= 0).all()
    np.testing.assert_allclose(compose(inverse(a), a), np.tile([0, 0, 0, 1.0, 0, 0, 0], (6, 1)), atol=1e-12)


def test_flat_observation_agrees():
    d = _frame()
    t = _torch(d)
    args = ("q", "link", "obj", "latent", "ref_q", "ref_obj")
    out = flat_observation(*(d[k] for k in args))
    assert isinstance(out, np.ndarray) and out.shape == (6, 273) and out.dtype == np.float32
    np.testing.assert_allclose(out, flat_observation(*(t[k] for k in args)).numpy(), atol=1e-6)
    with pytest.raises(ValueError, match="link_pose"):
        flat_observation(d["q"], d["link"][:, :4], d["obj"], d["latent"], d["ref_q"], d["ref_obj"])


def test_frame_errors_and_reward_agree():
    d = _frame(seed=2)
    results = []
    for x in (d, _torch(d)):
        err = frame_errors(x["obj"], x["ref_obj"][:, 0], x["link"][:, 0], x["ref_link"][:, 0, 0], x["q"],
                           x["ref_q"][:, 0])
        kw = dict(joint_pos=x["q"], link_pose=x["link"], object_pose=x["obj"], ref_joint_pos=x["ref_q"][:, 0],
                  ref_link_pose=x["ref_link"][:, 0], ref_object_pose=x["ref_obj"][:, 0])
        with_err, terms = tracking_reward(RewardConfig(), errors=err, **kw)
        without, _ = tracking_reward(RewardConfig(), **kw)
        results.append((err, with_err, without, terms))
    (ne, nr, nr2, nt), (te, tr, tr2, tt) = results
    for k in ERROR_NAMES:
        np.testing.assert_allclose(ne[k], te[k].numpy(), atol=1e-6)
    np.testing.assert_allclose(nr, tr.numpy(), atol=1e-5)
    np.testing.assert_allclose(nr, nr2, atol=1e-4)      # errors passed in or recomputed: the same reward
    for k in nt:
        np.testing.assert_allclose(nt[k], tt[k].numpy(), atol=1e-5)
    # the batch spans both sides of the gates and the bonus, so every branch was compared
    assert 0 < (nt["bonus"] > 0).sum() < len(nr)
    assert (nt["proximity"] < 0).any()
