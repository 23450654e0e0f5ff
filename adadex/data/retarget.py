"""Human hand keypoints → robot joint positions, by least squares on keypoint distances.

Each human keypoint that has a robot counterpart (:data:`ROBOT_POINTS`: wrist ↔ flange, knuckles ↔
finger joint axes, fingertips ↔ fingertip sites; the human little finger has none) gives a residual
``w_k · (p_k(q) − target_k)``. Targets are the human keypoints scaled about the human wrist by
``scale`` (robot hand length / human hand length, estimated from the keypoints by default), so the
arm places the palm where the human wrist and knuckles are and the fingers match the human's.

The solve is damped Gauss–Newton within joint limits, on pytorch-kinematics forward kinematics
with an analytic Jacobian (joint axis × lever arm, from the same forward pass). It runs batched
over sequences and goes frame by frame, each frame warm-started from the previous frame's solution
(the first from :data:`~adadex.sim.robot.HOME_QPOS`, base turned toward the wrist, with more
iterations); a small pull toward the
previous frame keeps redundant joints from wandering. The result reports per-frame residuals.

Example
-------
>>> import torch
>>> from adadex.data.retarget import Retargeter
>>> rt = Retargeter()
>>> q = torch.tensor(rt.robot_keypoints_fk_demo_q(), dtype=torch.float64)      # (2, 22)
>>> kp = rt.robot_keypoints(q[None])                                            # (1, 2, 21, 3)
>>> res = rt.retarget(kp.numpy())
>>> bool(res.tip_error.max() < 0.005)
True
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from adadex.sim.kinematics import RobotKinematics
from adadex.sim.robot import HOME_QPOS, JOINT_NAMES, NUM_JOINTS, joint_limits

#: Robot frame (body or site) matched to each human keypoint; ``None`` = not matched.
ROBOT_POINTS = (
    "link6",
    "if_bs", "if_md", "if_ds",
    "mf_bs", "mf_md", "mf_ds",
    None, None, None,
    "rf_bs", "rf_md", "rf_ds",
    "th_bs", "th_px", "th_ds",
    "thumb_tip", "index_tip", "middle_tip", "ring_tip", None,
)
_MATCHED = tuple(i for i, n in enumerate(ROBOT_POINTS) if n is not None)
_TIPS = (16, 17, 18, 19)
_PALM = (0, 4)   # wrist and middle knuckle: where the arm puts the palm (index/ring knuckle spacing differs by design)
_MIDDLE_CHAIN = (0, 4, 5, 6, 18)

#: Points kept above the table top during retargeting: (frame, offset in the frame, clearance in m) —
#: the forearm, wrist and flange capsule ends, the palm block's corners and the finger joints
#: (see ``adadex.sim.robot``).
TABLE_CLEARANCE_POINTS = (
    ("link4", (0.0, 0.0, 0.0), 0.045), ("link4", (0.0, 0.0, -0.10), 0.045),
    ("link5", (0.0, 0.0, 0.0), 0.04), ("link5", (0.038, 0.03, 0.0), 0.04), ("link6", (0.0, 0.0, 0.0), 0.04),
) + tuple(("link6", (x, y, z), 0.008) for x in (-0.015, 0.015) for y in (-0.071, 0.065) for z in (0.015, 0.115)) + tuple(
    (f, (0.0, 0.0, 0.0), 0.008) for f in ("th_ds", "th_px", "if_ds", "mf_ds", "rf_ds"))

#: Default residual weight per keypoint kind.
DEFAULT_WEIGHTS = {"wrist": 1.0, "knuckle": 0.5, "joint": 0.1, "tip": 1.0}


def _kind(i: int) -> str:
    if i == 0:
        return "wrist"
    if i in _TIPS:
        return "tip"
    return "knuckle" if i in (1, 4, 10) else "joint"   # the thumb's chain differs most: its tip leads


def hand_length(keypoints: np.ndarray) -> np.ndarray:
    """Wrist → middle fingertip along the bones (invariant to finger flexion), per frame, m."""
    kp = np.asarray(keypoints)
    seg = np.diff(kp[..., _MIDDLE_CHAIN, :], axis=-2)
    return np.linalg.norm(seg, axis=-1).sum(-1)


@dataclass
class RetargetResult:
    """Per sequence and frame: joint positions and residuals (all (B, T, …) numpy arrays)."""

    joint_pos: np.ndarray       # (B, T, 22)
    residual: np.ndarray        # (B, T) RMS distance over matched keypoints, m
    tip_error: np.ndarray       # (B, T) largest fingertip distance, m
    palm_error: np.ndarray      # (B, T) largest wrist / middle-knuckle distance, m
    at_limit: np.ndarray        # (B, T) number of joints at a limit
    scale: np.ndarray           # (B,) keypoint scale used


class Retargeter:
    """Batched keypoint retargeting (see the module docstring).

    Args:
        weights: residual weight per keypoint kind (``wrist``, ``knuckle``, ``joint``, ``tip``).
        iters: Gauss–Newton iterations per frame (warm-started).
        first_iters: iterations for the first frame (from ``HOME_QPOS`` or ``q_init``).
        smooth: weight (m/rad) of the pull toward the previous frame's joints.
        table_weight: weight of the penalty on arm and palm points below the table top plus their
            clearance (:data:`TABLE_CLEARANCE_POINTS`); 0 disables it.
        damping: Levenberg damping added to the normal equations.
        max_step: largest change of one joint per iteration, rad.
        retry_above: a sequence whose wrist/knuckle error exceeds this (m) at some frame is tracked
            again from every start posture, keeping the best (``inf`` to skip).
    """

    def __init__(self, *, weights: dict | None = None, iters: int = 4, first_iters: int = 60,
                 smooth: float = 3e-3, damping: float = 1e-6, max_step: float = 0.25, retry_above: float = 0.05,
                 table_weight: float = 3.0):
        w = dict(DEFAULT_WEIGHTS, **(weights or {}))
        unknown = set(w) - set(DEFAULT_WEIGHTS)
        if unknown:
            raise ValueError(f"unknown keypoint kinds in weights: {sorted(unknown)}; "
                             f"expected {sorted(DEFAULT_WEIGHTS)}")
        if iters < 1 or first_iters < 1:
            raise ValueError(f"iters and first_iters must be ≥ 1, got {iters}, {first_iters}")
        self.iters, self.first_iters = iters, first_iters
        self.smooth, self.damping, self.max_step, self.retry_above = smooth, damping, max_step, retry_above
        self.fk = RobotKinematics()
        chain = self.fk.chain
        self._frames = [ROBOT_POINTS[i] for i in _MATCHED] + [f for f, _, _ in TABLE_CLEARANCE_POINTS]
        self._offsets = torch.tensor([[0.0, 0.0, 0.0]] * len(_MATCHED) + [o for _, o, _ in TABLE_CLEARANCE_POINTS],
                                     dtype=torch.float64)
        self._clearance = torch.tensor([c for _, _, c in TABLE_CLEARANCE_POINTS], dtype=torch.float64)
        self.table_weight = table_weight
        self._w = torch.tensor([w[_kind(i)] for i in _MATCHED], dtype=torch.float64)
        # Joint frames and, per matched point, which joints move it (ancestors in the tree).
        joint_frame, axis, movers = {}, {}, {}

        def walk(frame, above):
            if frame.joint.joint_type == "revolute":
                joint_frame[frame.joint.name] = frame.name
                axis[frame.joint.name] = frame.joint.axis.to(torch.float64)
                above = above + [frame.joint.name]
            movers[frame.name] = above
            for ch in frame.children:
                walk(ch, above)

        walk(chain._root, [])
        self._joint_frames = [joint_frame[n] for n in JOINT_NAMES]
        self._axes = torch.stack([axis[n] for n in JOINT_NAMES])               # (22, 3) local axes
        moves = torch.zeros(len(self._frames), NUM_JOINTS, dtype=torch.float64)
        for k, name in enumerate(self._frames):
            moves[k, [JOINT_NAMES.index(j) for j in movers[name]]] = 1.0
        self._moves = moves
        self._all = list(dict.fromkeys(self._frames + self._joint_frames))
        self._idx = chain.get_frame_indices(*self._all)
        self._perm = self.fk._perm
        lim = torch.as_tensor(joint_limits())
        self._lo, self._hi = lim[:, 0], lim[:, 1]
        self.robot_length = float(hand_length(self.robot_keypoints(torch.zeros(1, 1, NUM_JOINTS))[0, 0].numpy()))

    # -- forward model -------------------------------------------------------------------------
    def _transforms(self, q: torch.Tensor) -> dict[str, torch.Tensor]:
        mats = self.fk.chain.forward_kinematics(q[:, self._perm], frame_indices=self._idx)
        return {name: mats[name].get_matrix() for name in self._all}

    def _points_jacobian(self, q: torch.Tensor):
        """(N, P, 3) robot points (matched keypoints, then table-clearance points), (N, P, 3, 22) Jacobian."""
        m = self._transforms(q)
        pts = torch.stack([m[n][:, :3, 3] + m[n][:, :3, :3] @ self._offsets[k] for k, n in enumerate(self._frames)],
                          dim=1)
        origin = torch.stack([m[n][:, :3, 3] for n in self._joint_frames], dim=1)      # (N, 22, 3)
        rot = torch.stack([m[n][:, :3, :3] for n in self._joint_frames], dim=1)        # (N, 22, 3, 3)
        axis = torch.einsum("njab,jb->nja", rot, self._axes)                            # (N, 22, 3)
        lever = pts[:, :, None, :] - origin[:, None, :, :]                              # (N, K, 22, 3)
        jac = torch.linalg.cross(axis[:, None].expand_as(lever), lever, dim=-1) * self._moves[None, :, :, None]
        return pts, jac.permute(0, 1, 3, 2)

    def robot_keypoints(self, q: torch.Tensor) -> torch.Tensor:
        """(…, 21, 3) the robot's own keypoints at joints ``q`` (…, 22); the little finger copies the ring."""
        lead = q.shape[:-1]
        pts, _ = self._points_jacobian(q.reshape(-1, NUM_JOINTS).to(torch.float64))
        pts = pts[:, : len(_MATCHED)]
        out = torch.zeros(pts.shape[0], len(ROBOT_POINTS), 3, dtype=torch.float64)
        out[:, list(_MATCHED)] = pts
        out[:, [7, 8, 9, 20]] = out[:, [10, 11, 12, 19]]
        return out.reshape(*lead, len(ROBOT_POINTS), 3)

    @staticmethod
    def robot_keypoints_fk_demo_q() -> np.ndarray:
        """Two joint vectors used by the docstring example: home and a grasp-like posture."""
        q2 = HOME_QPOS.copy()
        q2[[6, 8, 10, 12]] += 0.4
        return np.stack([HOME_QPOS, q2])

    # -- solve ---------------------------------------------------------------------------------
    def retarget(self, keypoints: np.ndarray, *, scale: float | np.ndarray | str = "auto",
                 q_init: np.ndarray | None = None, lengths=None, progress=None) -> RetargetResult:
        """Retarget ``keypoints`` (T, 21, 3) or (B, T, 21, 3) in the world frame.

        ``scale`` multiplies keypoint offsets from the wrist; ``"auto"`` uses robot hand length /
        median human hand length per sequence. ``progress`` is an optional callable taking the
        number of frames just done (a tqdm ``update``). ``lengths`` (B,) gives each sequence's real
        length when a batch was padded; padded frames then do not count toward the retry decision.
        """
        kp = np.asarray(keypoints, dtype=np.float64)
        single = kp.ndim == 3
        if single:
            kp = kp[None]
        if kp.ndim != 4 or kp.shape[2:] != (len(ROBOT_POINTS), 3):
            raise ValueError(f"keypoints: expected shape (T, 21, 3) or (B, T, 21, 3), got {np.shape(keypoints)}")
        if not np.isfinite(kp).all():
            b, t = np.argwhere(~np.isfinite(kp))[0][:2]
            raise ValueError(f"keypoints: non-finite value in sequence {b} at frame {t}")
        B, T = kp.shape[:2]
        if isinstance(scale, str):
            if scale != "auto":
                raise ValueError(f"scale must be a number or 'auto', got {scale!r}")
            s = self.robot_length / np.median(hand_length(kp), axis=1)
        else:
            s = np.broadcast_to(np.asarray(scale, dtype=np.float64), (B,)).copy()
        if not (np.isfinite(s).all() and (s > 0).all()):
            raise ValueError(f"scale must be positive and finite, got {s}")
        wrist = kp[:, :, :1]
        target = torch.as_tensor(wrist + s[:, None, None, None] * (kp - wrist))[:, :, list(_MATCHED)]

        if q_init is None:  # home posture, base turned toward the first wrist position
            q_init = np.tile(HOME_QPOS, (B, 1))
            q_init[:, 0] = np.arctan2(kp[:, 0, 0, 1], kp[:, 0, 0, 0])
        q = torch.as_tensor(np.broadcast_to(q_init, (B, NUM_JOINTS)).copy()).clamp(self._lo, self._hi)
        out_q, out_err = self._track(target, self._solve_first(target[:, 0], q)[0], progress)
        palm = [_MATCHED.index(i) for i in _PALM]
        valid = torch.ones(B, T, dtype=torch.bool) if lengths is None else \
            torch.arange(T)[None] < torch.as_tensor(np.asarray(lengths))[:, None]

        def palm_error(err, rows):  # (n, T) wrist/palm error, zero on padded frames
            return err[..., palm].amax(-1) * valid[rows]

        failing = torch.nonzero(palm_error(out_err, slice(None)).amax(1) > self.retry_above).flatten()
        if len(failing) and self.retry_above < np.inf:
            # Tracking lost the fit: the arm posture chosen at frame 0 ran into a joint limit later on.
            # Track those sequences again from every start posture and keep the best whole sequence.
            starts = self._starts(q[failing])[1:8]   # the other arm postures (the thumb does not move the palm)
            K, F = len(starts), len(failing)
            tgt = target[failing].repeat(K, 1, 1, 1)
            q0, _ = self._solve_frame(tgt[:, 0], torch.cat(starts), self.first_iters)
            alt_q, alt_err = self._track(tgt, q0, None)
            score = palm_error(alt_err, failing.repeat(K)).quantile(0.95, dim=1).reshape(K, F)
            pick = score.argmin(0) * F + torch.arange(F)
            better = score.min(0).values < palm_error(out_err[failing], failing).quantile(0.95, dim=1)
            out_q[failing[better]] = alt_q[pick[better]]
            out_err[failing[better]] = alt_err[pick[better]]
        err = out_err.numpy()
        tips = [_MATCHED.index(i) for i in _TIPS]
        palm = [_MATCHED.index(i) for i in _PALM]
        qn = out_q.numpy()
        lim = joint_limits()
        result = RetargetResult(
            joint_pos=qn, residual=np.sqrt((err ** 2).mean(-1)), tip_error=err[..., tips].max(-1),
            palm_error=err[..., palm].max(-1),
            at_limit=((qn <= lim[:, 0] + 1e-6) | (qn >= lim[:, 1] - 1e-6)).sum(-1), scale=s)
        if single:
            for name in ("joint_pos", "residual", "tip_error", "palm_error", "at_limit"):
                setattr(result, name, getattr(result, name)[0])
        return result

    def _track(self, target: torch.Tensor, q: torch.Tensor, progress):
        """Frame-by-frame solve of (B, T, K, 3) targets from the frame-0 solution ``q``."""
        B, T = target.shape[:2]
        out_q = torch.empty(B, T, NUM_JOINTS, dtype=torch.float64)
        out_err = torch.empty(B, T, len(_MATCHED), dtype=torch.float64)
        for t in range(T):
            q, err = self._solve_frame(target[:, t], q, self.first_iters if t == 0 else self.iters)
            out_q[:, t], out_err[:, t] = q, err
            if progress is not None:
                progress(B)
        return out_q, out_err

    def _starts(self, q0: torch.Tensor) -> list[torch.Tensor]:
        """Start postures: ``q0`` and variants with the forearm/wrist rolled or the wrist bent."""
        starts = [q0]
        for d4, d6, d5 in ((np.pi / 2, 0.0, 0.0), (-np.pi / 2, 0.0, 0.0), (0.0, np.pi / 2, 0.0), (0.0, -np.pi / 2, 0.0),
                           (0.0, 0.0, -0.8), (np.pi, np.pi, 0.0), (-np.pi, -np.pi, 0.0)):
            q = q0.clone()
            q[:, 3] += d4
            q[:, 5] += d6
            q[:, 4] += d5
            starts.append(torch.minimum(torch.maximum(q, self._lo), self._hi))
        for cmc, axl in ((1.2, 0.3), (0.3, 1.2), (1.2, 1.2)):  # thumb swung across the palm and/or raised
            q = q0.clone()
            q[:, 18], q[:, 19] = cmc, axl
            starts.append(q)
        # Thumb bent backward (MCP straight, IP hyperextended): from the flexed starts above the
        # solve can stop with the MCP at its lower limit and the IP bent the wrong way, tip ~3 cm off.
        q = q0.clone()
        q[:, 20], q[:, 21] = 0.0, -0.8
        starts.append(q)
        return starts

    def _solve_first(self, target: torch.Tensor, q0: torch.Tensor):
        """First frame: solve from several arm postures (elbow, wrist flips) and keep the best."""
        starts = self._starts(q0)
        B, K = len(q0), len(starts)
        qs = torch.cat(starts)
        qs, errs = self._solve_frame(target.repeat(K, 1, 1), qs, self.first_iters)
        w = self._w[None]
        # Among equally good fits prefer forearm and wrist rolls near the middle of their range.
        cost = ((w * errs) ** 2).sum(-1) + 2e-4 * (qs[:, 3] ** 2 + qs[:, 5] ** 2)
        cost = cost.reshape(K, B)
        best = cost.argmin(0)
        pick = best * B + torch.arange(B)
        return qs[pick], errs[pick]

    def _solve_frame(self, target: torch.Tensor, q_prev: torch.Tensor, iters: int):
        q = q_prev.clone()
        w = self._w[None, :, None]
        eye = torch.eye(NUM_JOINTS, dtype=torch.float64)
        reg = self.smooth ** 2
        K = len(_MATCHED)
        for _ in range(iters):
            pts, jac = self._points_jacobian(q)
            below = (self._clearance - pts[:, K:, 2]).clamp(min=0.0)                  # (N, C)
            r = torch.cat([(w * (pts[:, :K] - target)).reshape(len(q), -1), self.table_weight * below], dim=1)
            J = torch.cat([(w[..., None] * jac[:, :K]).reshape(len(q), -1, NUM_JOINTS),
                           -self.table_weight * (below > 0)[..., None] * jac[:, K:, 2]], dim=1)
            A = J.transpose(1, 2) @ J + (self.damping + reg) * eye
            g = (J.transpose(1, 2) @ r[..., None])[..., 0] + reg * (q - q_prev)
            dq = -torch.linalg.solve(A, g).clamp(-self.max_step, self.max_step)
            q = torch.minimum(torch.maximum(q + dq, self._lo), self._hi)
        pts, _ = self._points_jacobian(q)
        return q, torch.linalg.norm(pts[:, :K] - target, dim=-1)
