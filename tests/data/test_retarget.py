"""Tests of keypoint retargeting: round trips through the robot's own forward kinematics, the analytic
Jacobian, joint limits, reported residuals, input validation, and warm-started tracking."""

from functools import lru_cache

import numpy as np
import pytest
import torch

from adadex.data.retarget import (
    _MATCHED,
    DEFAULT_WEIGHTS,
    TABLE_CLEARANCE_POINTS,
    Retargeter,
    hand_length,
)
from adadex.data.object_contact import ObjectContact, hand_collision_spheres
from adadex.sim.kinematics import RobotKinematics
from adadex.sim.robot import HOME_QPOS, JOINT_NAMES, NUM_JOINTS, joint_limits

LIMITS = joint_limits()


pytestmark = pytest.mark.usefixtures("one_torch_thread")   # tests/data/conftest.py


@lru_cache(maxsize=1)
def retargeter() -> Retargeter:
    return Retargeter()


@lru_cache(maxsize=1)
def fk() -> RobotKinematics:
    return RobotKinematics()


def joint_trajectories(B=6, T=40, seed=0, arm=0.4, margin=0.05):
    """(B, T, 22) smooth joint trajectories: each a min-jerk-like blend between two random postures,
    the arm within ``arm`` rad of HOME_QPOS, fingers anywhere in their ranges (``margin`` of each range
    kept clear of the limits)."""
    rng = np.random.default_rng(seed)
    lo, hi = LIMITS[:, 0].copy(), LIMITS[:, 1].copy()
    lo[:6] = np.maximum(lo[:6], HOME_QPOS[:6] - arm)
    hi[:6] = np.minimum(hi[:6], HOME_QPOS[:6] + arm)
    pad = margin * (hi - lo)
    q0 = rng.uniform(lo + pad, hi - pad, (B, NUM_JOINTS))
    q1 = rng.uniform(lo + pad, hi - pad, (B, NUM_JOINTS))
    s = np.linspace(0.0, 1.0, T)
    s = s * s * (3 - 2 * s)
    return q0[:, None] + s[None, :, None] * (q1 - q0)[:, None]


def robot_keypoints(q: np.ndarray) -> np.ndarray:
    return retargeter().robot_keypoints(torch.as_tensor(q)).numpy()


def link_positions(q: np.ndarray) -> np.ndarray:
    return fk().link_poses(torch.as_tensor(q)).numpy()[..., :3]


# ------------------------------------------------------------------------------------------------
# The acceptance test


def test_robot_keypoints_round_trip_within_5mm():
    """Keypoints of the robot's own FK at known joints retarget back: every tracked link within 5 mm,
    at every frame of every sequence."""
    q = joint_trajectories(B=6, T=40, seed=0)
    res = retargeter().retarget(robot_keypoints(q), scale=1.0)
    assert res.joint_pos.shape == q.shape
    err = np.linalg.norm(link_positions(res.joint_pos) - link_positions(q), axis=-1)     # (B, T, 5)
    b, t, k = np.unravel_index(int(err.argmax()), err.shape)
    assert err.max() < 0.005, f"sequence {b}, frame {t}, link {k}: {err.max() * 1000:.1f} mm from the truth"
    assert res.tip_error.max() < 0.005 and res.palm_error.max() < 0.005


def test_round_trip_thumb_hyperextended():
    """Regression: a thumb with its IP joint bent backward (a posture the first-frame solve used to
    miss, stopping ~3 cm off with the MCP at its lower limit) is recovered."""
    q = np.tile(HOME_QPOS, (1, 3, 1))
    q[..., 18:22] = [0.43, 0.70, -0.25, -0.82]
    res = retargeter().retarget(robot_keypoints(q), scale=1.0)
    err = np.linalg.norm(link_positions(res.joint_pos) - link_positions(q), axis=-1)
    assert err.max() < 0.005, f"{err.max() * 1000:.1f} mm"


# ------------------------------------------------------------------------------------------------
# Forward model


def test_points_jacobian_matches_finite_differences():
    rt = Retargeter(contact=ObjectContact())   # its points include the hand's collision spheres
    rng = np.random.default_rng(1)
    q = torch.as_tensor(rng.uniform(LIMITS[:, 0], LIMITS[:, 1], (4, NUM_JOINTS)))
    pts, jac = rt._points_jacobian(q)
    # matched keypoints, then table-clearance points, then the hand's collision spheres
    K = len(_MATCHED) + len(TABLE_CLEARANCE_POINTS) + len(hand_collision_spheres())
    assert pts.shape == (4, K, 3) and jac.shape == (4, K, 3, NUM_JOINTS)
    eps = 1e-5
    fd = torch.empty_like(jac)
    for j in range(NUM_JOINTS):
        dq = torch.zeros(NUM_JOINTS, dtype=torch.float64)
        dq[j] = eps
        fd[..., j] = (rt._points_jacobian(q + dq)[0] - rt._points_jacobian(q - dq)[0]) / (2 * eps)
    diff = (jac - fd).abs()
    n, k, a, j = np.unravel_index(int(diff.argmax()), diff.shape)
    assert diff.max() < 1e-7, (f"configuration {n}, point {k}, axis {a}, joint "
                               f"{JOINT_NAMES[j]}: analytic {jac[n, k, a, j]:.8f} vs numeric {fd[n, k, a, j]:.8f}")


def test_robot_keypoints_layout():
    """Matched keypoints are the named robot frames; the little finger (no robot counterpart) copies the ring."""
    q = joint_trajectories(B=2, T=3, seed=2)
    kp = robot_keypoints(q)
    assert kp.shape == (2, 3, 21, 3)
    np.testing.assert_array_equal(kp[..., [7, 8, 9, 20], :], kp[..., [10, 11, 12, 19], :])
    # Fingertip keypoints are the tracked fingertip sites (thumb, index, middle, ring).
    np.testing.assert_allclose(kp[..., [16, 17, 18, 19], :], link_positions(q)[..., 1:, :], atol=1e-9)


# ------------------------------------------------------------------------------------------------
# Results


def test_results_within_joint_limits_on_unreachable_targets():
    """Fingers stretched 1.6× and the palm pulled out of reach: the solve ends at limits, never beyond."""
    q = joint_trajectories(B=3, T=8, seed=3)
    kp = robot_keypoints(q)
    kp = kp[..., :1, :] + 1.6 * (kp - kp[..., :1, :])
    kp[2] += [1.5, 0.0, 0.0]   # wrist 1.5 m further out than the arm reaches
    res = retargeter().retarget(kp, scale=1.0)
    qn = res.joint_pos
    assert np.all(qn >= LIMITS[:, 0]) and np.all(qn <= LIMITS[:, 1])
    at_limit = ((qn <= LIMITS[:, 0] + 1e-6) | (qn >= LIMITS[:, 1] - 1e-6)).sum(-1)
    np.testing.assert_array_equal(res.at_limit, at_limit)
    assert res.at_limit.max() > 0
    assert res.palm_error[2].min() > 0.5     # reported, not hidden


@pytest.mark.parametrize("batched", [False, True])
def test_residual_per_frame_shapes_and_values(batched):
    B, T = 2, 5
    q = joint_trajectories(B=B, T=T, seed=4)
    kp = robot_keypoints(q)
    kp = kp + np.random.default_rng(0).normal(0, 0.004, kp.shape)    # not exactly reachable
    scale = 1.1
    res = retargeter().retarget(kp if batched else kp[0], scale=scale)
    lead = (B, T) if batched else (T,)
    assert res.joint_pos.shape == (*lead, NUM_JOINTS)
    for name in ("residual", "tip_error", "palm_error", "at_limit"):
        assert getattr(res, name).shape == lead, name
    assert res.scale.shape == ((B,) if batched else (1,))
    np.testing.assert_allclose(res.scale, scale)
    # Recompute the reported errors from the returned joints and the scaled targets.
    target = kp[..., :1, :] + scale * (kp - kp[..., :1, :])
    if not batched:
        target = target[0]
    dist = np.linalg.norm(robot_keypoints(res.joint_pos) - target, axis=-1)[..., list(_MATCHED)]
    np.testing.assert_allclose(res.residual, np.sqrt((dist ** 2).mean(-1)), atol=1e-9)
    np.testing.assert_allclose(res.tip_error, dist[..., [_MATCHED.index(i) for i in (16, 17, 18, 19)]].max(-1),
                               atol=1e-9)
    np.testing.assert_allclose(res.palm_error, dist[..., [_MATCHED.index(i) for i in (0, 4)]].max(-1), atol=1e-9)
    assert np.all(res.residual > 0) and np.all(res.residual < 0.02)


def test_auto_scale_is_one_for_robot_keypoints():
    q = joint_trajectories(B=3, T=10, seed=5)
    kp = robot_keypoints(q)
    res = retargeter().retarget(kp)
    np.testing.assert_allclose(res.scale, 1.0, atol=0.03)
    np.testing.assert_allclose(res.scale, retargeter().robot_length / np.median(hand_length(kp), axis=1))
    # A hand 20 % smaller is scaled up by 1.25.
    small = kp[..., :1, :] + 0.8 * (kp - kp[..., :1, :])
    np.testing.assert_allclose(retargeter().retarget(small).scale, res.scale / 0.8, rtol=1e-6)


# ------------------------------------------------------------------------------------------------
# Bad input


@pytest.mark.parametrize("shape", [(5, 20, 3), (5, 21, 2), (21, 3), (1, 2, 5, 21, 3)])
def test_wrong_shape(shape):
    with pytest.raises(ValueError, match=r"keypoints: expected shape .*got \(" + ", ".join(map(str, shape))):
        retargeter().retarget(np.zeros(shape))


def test_nan_keypoints_named_by_sequence_and_frame():
    kp = robot_keypoints(joint_trajectories(B=2, T=4, seed=6))
    kp[1, 3, 7, 2] = np.nan
    with pytest.raises(ValueError, match="non-finite value in sequence 1 at frame 3"):
        retargeter().retarget(kp)
    kp[1, 3, 7, 2] = np.inf
    with pytest.raises(ValueError, match="non-finite"):
        retargeter().retarget(kp[1])


@pytest.mark.parametrize("scale", [0.0, -1.0, np.nan, np.inf, [1.0, -0.5]])
def test_bad_scale(scale):
    kp = robot_keypoints(joint_trajectories(B=2, T=2, seed=7))
    with pytest.raises(ValueError, match="scale must be positive and finite"):
        retargeter().retarget(kp, scale=scale)


def test_bad_scale_string():
    with pytest.raises(ValueError, match="scale must be a number or 'auto', got 'big'"):
        retargeter().retarget(np.zeros((2, 21, 3)), scale="big")


def test_unknown_weight_kind():
    with pytest.raises(ValueError, match=r"unknown keypoint kinds in weights: \['elbow'\]") as e:
        Retargeter(weights={"elbow": 1.0, "tip": 2.0})
    for kind in DEFAULT_WEIGHTS:
        assert kind in str(e.value)


def test_bad_iterations():
    with pytest.raises(ValueError, match="iters and first_iters must be ≥ 1"):
        Retargeter(iters=0)


# ------------------------------------------------------------------------------------------------
# Warm-started tracking


def easy_sequence(T=20, seed=8):
    """A slow move near HOME_QPOS (every joint within 0.15 rad of it)."""
    rng = np.random.default_rng(seed)
    q1 = HOME_QPOS + rng.uniform(-0.15, 0.15, NUM_JOINTS)
    s = np.linspace(0.0, 1.0, T)[:, None]
    return HOME_QPOS + s * (q1 - HOME_QPOS)


def test_warm_start_matches_fresh_per_frame_solves():
    q = easy_sequence()
    kp = robot_keypoints(q)
    warm = retargeter().retarget(kp, scale=1.0)
    fresh = retargeter().retarget(kp[:, None], scale=1.0)    # every frame its own 1-frame sequence
    fresh_q = fresh.joint_pos[:, 0]
    np.testing.assert_allclose(link_positions(warm.joint_pos), link_positions(fresh_q), atol=1e-3)
    np.testing.assert_allclose(warm.joint_pos, fresh_q, atol=0.05)   # distal finger joints are weakly determined
    np.testing.assert_allclose(warm.joint_pos[:, :6], fresh_q[:, :6], atol=2e-3)
    np.testing.assert_allclose(warm.residual, fresh.residual[:, 0], atol=5e-4)
    assert warm.residual.max() < 1e-3


def test_retarget_is_deterministic():
    q = joint_trajectories(B=2, T=10, seed=9)
    kp = robot_keypoints(q) + np.random.default_rng(1).normal(0, 0.003, (2, 10, 21, 3))
    a = retargeter().retarget(kp)
    b = Retargeter().retarget(kp)
    for name in ("joint_pos", "residual", "tip_error", "palm_error", "at_limit", "scale"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=name)


def test_table_clearance_keeps_the_arm_above_the_table():
    """Targets that would pull the palm into the table: the clearance term keeps it out."""
    rt, free = retargeter(), Retargeter(table_weight=0.0, retry_above=np.inf)
    q = HOME_QPOS.copy()
    kp = robot_keypoints(q[None, None])[0]
    kp[:, :, 2] -= 0.25                      # the whole hand 25 cm lower: below the table top
    lowest = []
    for r in (rt, free):
        res = r.retarget(kp)
        pts, _ = r._points_jacobian(torch.as_tensor(res.joint_pos))
        lowest.append(float(pts[:, len(_MATCHED):len(_MATCHED) + len(TABLE_CLEARANCE_POINTS), 2].min()))
    assert lowest[1] < -0.03                 # without the term the palm goes through the table
    assert lowest[0] > -0.01                 # with it, the clearance points stay (nearly) above
