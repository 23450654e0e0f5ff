"""Arm inverse kinematics on a MuJoCo model: place a body (by default the palm) at a pose.

Damped least squares on the 6 arm joints with MuJoCo's body Jacobian, within joint limits. It is
used for scripted motions (the grasp check, demos); batched retargeting of human motion to the whole
arm + hand lives in :mod:`adadex.data.retarget` and uses pytorch-kinematics.

Example
-------
>>> import numpy as np
>>> from adadex.sim.scene import build_scene_model
>>> from adadex.sim.ik import solve_arm_ik
>>> m = build_scene_model(None)
>>> q, err = solve_arm_ik(m, "palm", np.array([0.4, 0.0, 0.3]), np.diag([1.0, -1.0, -1.0]))
>>> bool(err < 1e-4)
True
"""

from __future__ import annotations

import mujoco
import numpy as np

from adadex.errors import AdadexError
from adadex.sim.robot import HOME_QPOS, NUM_JOINTS


class IKError(AdadexError, RuntimeError):
    """The arm could not reach the requested pose within tolerance."""


def _rot_error(r_target: np.ndarray, r_cur: np.ndarray) -> np.ndarray:
    """Rotation vector of r_target · r_curᵀ (world frame)."""
    q = np.zeros(4)
    mujoco.mju_mat2Quat(q, (r_target @ r_cur.T).reshape(-1))
    v = np.zeros(3)
    mujoco.mju_quat2Vel(v, q, 1.0)
    return v


def solve_arm_ik(model: mujoco.MjModel, body: str, target_pos: np.ndarray, target_rot: np.ndarray,
                 q_init: np.ndarray | None = None, *, iters: int = 300, damping: float = 1e-3,
                 tol: float = 1e-5, restarts: int = 0, seed: int = 0) -> tuple[np.ndarray, float]:
    """Arm joints (first 6) that put ``body``'s frame at ``target_pos``/``target_rot`` (3×3).

    Returns ``(qpos[22], error)`` where error is position error (m) + rotation error (rad); hand
    joints keep their values from ``q_init`` (default :data:`HOME_QPOS`). With ``restarts > 0``,
    if the solve from ``q_init`` misses, up to ``restarts`` seeded random arm configurations are
    tried and the best solution is returned (joint limits make the problem non-convex).
    """
    q0 = np.array(HOME_QPOS if q_init is None else q_init, dtype=float)[:NUM_JOINTS]
    best = _solve_once(model, body, target_pos, target_rot, q0, iters, damping, tol)
    rng = np.random.default_rng(seed)
    lo, hi = model.jnt_range[:6, 0], model.jnt_range[:6, 1]
    for _ in range(restarts):
        if best[1] < tol:
            break
        q = q0.copy()
        q[:6] = rng.uniform(0.8 * lo, 0.8 * hi)
        cand = _solve_once(model, body, target_pos, target_rot, q, iters, damping, tol)
        if cand[1] < best[1]:
            best = cand
    return best


def _solve_once(model, body, target_pos, target_rot, q, iters, damping, tol):
    data = mujoco.MjData(model)
    data.qpos[:NUM_JOINTS] = q
    bid = model.body(body).id
    lo, hi = model.jnt_range[:6, 0], model.jnt_range[:6, 1]
    jacp = np.zeros((3, model.nv))
    jacr = np.zeros((3, model.nv))
    err = np.inf
    for _ in range(iters):
        mujoco.mj_kinematics(model, data)
        mujoco.mj_comPos(model, data)
        e = np.concatenate([target_pos - data.xpos[bid], _rot_error(target_rot, data.xmat[bid].reshape(3, 3))])
        err = float(np.linalg.norm(e[:3]) + np.linalg.norm(e[3:]))
        if err < tol:
            break
        mujoco.mj_jacBody(model, data, jacp, jacr, bid)
        J = np.vstack([jacp[:, :6], jacr[:, :6]])
        dq = J.T @ np.linalg.solve(J @ J.T + damping * np.eye(6), e)
        data.qpos[:6] = np.clip(data.qpos[:6] + dq, lo, hi)
    out = np.array(data.qpos[:NUM_JOINTS])
    return out, err
