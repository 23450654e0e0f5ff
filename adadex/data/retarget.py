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

Given the object's trajectory and ``contact=ObjectContact()``, the solve also keeps the hand out of
the object and puts the fingertips on it where the human's touch it
(:mod:`adadex.data.object_contact`), by Levenberg–Marquardt steps.

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

from adadex.data.object_contact import ObjectContact, hand_collision_spheres, hull_planes
from adadex.errors import ArrayError, ConfigError
from adadex.geometry import rotation
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
        contact: object-aware retargeting (:class:`~adadex.data.object_contact.ObjectContact`: the
            hand kept out of the object, fingertips pressed onto it where the human's touch it),
            used when :meth:`retarget` is given the object's trajectory; ``None`` (default) ignores
            the object.
    """

    def __init__(self, *, weights: dict | None = None, iters: int = 4, first_iters: int = 60,
                 smooth: float = 3e-3, damping: float = 1e-6, max_step: float = 0.25, retry_above: float = 0.05,
                 table_weight: float = 3.0, contact: ObjectContact | None = None):
        w = dict(DEFAULT_WEIGHTS, **(weights or {}))
        unknown = set(w) - set(DEFAULT_WEIGHTS)
        if unknown:
            raise ConfigError(f"unknown keypoint kinds in weights: {sorted(unknown)}; "
                              f"expected {sorted(DEFAULT_WEIGHTS)}")
        if iters < 1 or first_iters < 1:
            raise ConfigError(f"iters and first_iters must be ≥ 1, got {iters}, {first_iters}")
        self.iters, self.first_iters = iters, first_iters
        self.smooth, self.damping, self.max_step, self.retry_above = smooth, damping, max_step, retry_above
        self.fk = RobotKinematics()
        chain = self.fk.chain
        spheres = hand_collision_spheres() if contact is not None else ()
        self.contact = contact
        self._frames = [ROBOT_POINTS[i] for i in _MATCHED] + [f for f, _, _ in TABLE_CLEARANCE_POINTS] + [
            s.frame for s in spheres]
        self._offsets = torch.tensor([[0.0, 0.0, 0.0]] * len(_MATCHED) + [o for _, o, _ in TABLE_CLEARANCE_POINTS]
                                     + [s.offset for s in spheres], dtype=torch.float64)
        self._radius = torch.tensor([s.radius for s in spheres], dtype=torch.float64)   # tips first (4)
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
        self._point_frame = torch.tensor([self._all.index(f) for f in self._frames])
        self._joint_frame = torch.tensor([self._all.index(f) for f in self._joint_frames])
        self._perm = self.fk._perm
        lim = torch.as_tensor(joint_limits())
        self._lo, self._hi = lim[:, 0], lim[:, 1]
        self.robot_length = float(hand_length(self.robot_keypoints(torch.zeros(1, 1, NUM_JOINTS))[0, 0].numpy()))

    # -- forward model -------------------------------------------------------------------------
    def _transforms(self, q: torch.Tensor) -> torch.Tensor:
        """(N, A, 4, 4) world transforms of the frames in ``self._all``."""
        mats = self.fk.chain.forward_kinematics(q[:, self._perm], frame_indices=self._idx)
        return torch.stack([mats[name].get_matrix() for name in self._all], dim=1)

    def _points_jacobian(self, q: torch.Tensor):
        """(N, P, 3) robot points (matched keypoints, table-clearance points, hand collision spheres),
        (N, P, 3, 22) Jacobian."""
        m = self._transforms(q)
        frames = m[:, self._point_frame]                                                # (N, P, 4, 4)
        pts = frames[..., :3, 3] + (frames[..., :3, :3] @ self._offsets[None, :, :, None])[..., 0]
        joints = m[:, self._joint_frame]
        origin, rot = joints[..., :3, 3], joints[..., :3, :3]                           # (N, 22, 3), (N, 22, 3, 3)
        axis = torch.einsum("njab,jb->nja", rot, self._axes)                            # (N, 22, 3)
        lever = pts[:, :, None, :] - origin[:, None, :, :]                              # (N, P, 22, 3)
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
                 q_init: np.ndarray | None = None, lengths=None, progress=None,
                 object_pose: np.ndarray | None = None, object_names=None) -> RetargetResult:
        """Retarget ``keypoints`` (T, 21, 3) or (B, T, 21, 3) in the world frame.

        ``scale`` multiplies keypoint offsets from the wrist; ``"auto"`` uses robot hand length /
        median human hand length per sequence. ``progress`` is an optional callable taking the
        number of frames just done (a tqdm ``update``). ``lengths`` (B,) gives each sequence's real
        length when a batch was padded; padded frames then do not count toward the retry decision.
        ``object_pose`` ((T, 7) or (B, T, 7), position + w-first quaternion) and ``object_names``
        (one name, or B) switch on the object terms of ``contact`` (keep out, fingertip contact).
        """
        kp = np.asarray(keypoints, dtype=np.float64)
        single = kp.ndim == 3
        if single:
            kp = kp[None]
        if kp.ndim != 4 or kp.shape[2:] != (len(ROBOT_POINTS), 3):
            raise ArrayError(f"keypoints: expected shape (T, 21, 3) or (B, T, 21, 3), got {np.shape(keypoints)}")
        if not np.isfinite(kp).all():
            b, t = np.argwhere(~np.isfinite(kp))[0][:2]
            raise ArrayError(f"keypoints: non-finite value in sequence {b} at frame {t}")
        B, T = kp.shape[:2]
        if isinstance(scale, str):
            if scale != "auto":
                raise ConfigError(f"scale must be a number or 'auto', got {scale!r}")
            s = self.robot_length / np.median(hand_length(kp), axis=1)
        else:
            s = np.broadcast_to(np.asarray(scale, dtype=np.float64), (B,)).copy()
        if not (np.isfinite(s).all() and (s > 0).all()):
            raise ConfigError(f"scale must be positive and finite, got {s}")
        wrist = kp[:, :, :1]
        target = torch.as_tensor(wrist + s[:, None, None, None] * (kp - wrist))[:, :, list(_MATCHED)]

        obj = self._object_terms(kp, object_pose, object_names)
        if q_init is None:  # home posture, base turned toward the first wrist position
            q_init = np.tile(HOME_QPOS, (B, 1))
            q_init[:, 0] = np.arctan2(kp[:, 0, 0, 1], kp[:, 0, 0, 0])
        q = torch.as_tensor(np.broadcast_to(q_init, (B, NUM_JOINTS)).copy()).clamp(self._lo, self._hi)
        q0 = self._solve_first(target[:, 0], q, _frame(obj, 0))[0]
        out_q, out_err = self._track(target, q0, progress, obj)
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
            alt_obj = _rows(obj, failing.repeat(K))
            q0, _ = self._solve_frame(tgt[:, 0], torch.cat(starts), self.first_iters, _frame(alt_obj, 0))
            alt_q, alt_err = self._track(tgt, q0, None, alt_obj)
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

    # -- the object ----------------------------------------------------------------------------
    def _object_terms(self, kp: np.ndarray, object_pose, object_names):
        """Per sequence: hull planes (B, F, 4, padded); per frame: object rotation (B, T, 3, 3) and
        position (B, T, 3), each human fingertip's contact weight (B, T, 4) and the robot fingertip
        sphere's contact target (B, T, 4, 3); ``None`` without an object."""
        if object_pose is None and object_names is None:
            return None
        if object_pose is None or object_names is None:
            raise ConfigError("object_pose and object_names go together: give both or neither")
        B, T = kp.shape[:2]
        pose = np.asarray(object_pose, dtype=np.float64)
        pose = np.broadcast_to(pose, (B, *pose.shape)) if pose.ndim == 2 else pose
        if pose.shape != (B, T, 7):
            raise ArrayError(f"object_pose: expected shape ({T}, 7) or ({B}, {T}, 7) to match the keypoints, "
                             f"got {np.shape(object_pose)}")
        if not np.isfinite(pose).all():
            b, t = np.argwhere(~np.isfinite(pose))[0][:2]
            raise ArrayError(f"object_pose: non-finite value in sequence {b} at frame {t}")
        names = [object_names] * B if isinstance(object_names, str) else list(object_names)
        if len(names) != B:
            raise ConfigError(f"object_names: expected one name or {B}, got {len(names)}")
        if self.contact is None:
            return None
        planes = [hull_planes(n) for n in names]
        F = max(len(p) for p in planes)
        padded = np.zeros((B, F, 4))
        padded[..., 3] = -1.0          # a dummy face 1 m behind every point: never the farthest
        for b, p in enumerate(planes):
            padded[b, : len(p)] = p
        rot = rotation(pose[..., 3:].reshape(-1, 4)).as_matrix().reshape(B, T, 3, 3)
        tips = np.einsum("btji,btkj->btki", rot, kp[:, :, list(_TIPS)] - pose[:, :, None, :3])   # object frame
        dist = np.einsum("btkj,bfj->btkf", tips, padded[..., :3]) + padded[:, None, None, :, 3]
        face = dist.argmax(-1)
        normal = np.take_along_axis(padded[:, None, None, :, :3], face[..., None, None], axis=3)[..., 0, :]
        depth = dist.max(-1)
        # Where the human touches, pressed in: the robot's tip sphere centre ``radius − squeeze`` out
        # from the human fingertip's nearest face, along that face's normal.
        out = self._radius[:4].numpy()[:, None] - self.contact.squeeze
        contact = tips - normal * (depth[..., None] - out)
        contact = np.einsum("btij,btkj->btki", rot, contact) + pose[:, :, None, :3]   # world frame
        active = self.contact.activation(depth)
        return tuple(torch.as_tensor(np.ascontiguousarray(a)) for a in (padded, rot, pose[..., :3], active, contact))

    def _object_residuals(self, centres: torch.Tensor, jac: torch.Tensor, obj):
        """Fingertip-contact and keep-out residuals (N, 12 + H − 4) and Jacobians of the hand spheres."""
        planes, rot, pos, active, contact = obj
        c = self.contact
        tip_w = (c.contact * active)[..., None]                                         # (N, 4, 1)
        tip_r = (tip_w * (centres[:, :4] - contact)).reshape(len(centres), -1)
        tip_J = (tip_w[..., None] * jac[:, :4]).reshape(len(centres), -1, NUM_JOINTS)
        normal = torch.einsum("nij,nfj->nfi", rot, planes[..., :3])                  # world face normals
        offset = planes[..., 3] - (normal * pos[:, None]).sum(-1)
        dist, face = (torch.einsum("nhk,nfk->nhf", centres[:, 4:], normal) + offset[:, None]).max(-1)
        grad = torch.gather(normal, 1, face[..., None].expand(-1, -1, 3))             # (N, H, 3)
        depth = (self._radius[4:] - dist).clamp(min=0.0)
        keep_J = -c.keep_out * (depth > 0)[..., None] * torch.einsum("nhk,nhkj->nhj", grad, jac[:, 4:])
        return torch.cat([tip_r, c.keep_out * depth], dim=1), torch.cat([tip_J, keep_J], dim=1)

    def _track(self, target: torch.Tensor, q: torch.Tensor, progress, obj=None):
        """Frame-by-frame solve of (B, T, K, 3) targets from the frame-0 solution ``q``."""
        B, T = target.shape[:2]
        out_q = torch.empty(B, T, NUM_JOINTS, dtype=torch.float64)
        out_err = torch.empty(B, T, len(_MATCHED), dtype=torch.float64)
        iters = self.iters if obj is None else max(self.iters, self.contact.iters)
        for t in range(T):
            q, err = self._solve_frame(target[:, t], q, self.first_iters if t == 0 else iters, _frame(obj, t))
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

    def _solve_first(self, target: torch.Tensor, q0: torch.Tensor, obj=None):
        """First frame: solve from several arm postures (elbow, wrist flips) and keep the best."""
        starts = self._starts(q0)
        B, K = len(q0), len(starts)
        qs = torch.cat(starts)
        qs, errs = self._solve_frame(target.repeat(K, 1, 1), qs, self.first_iters,
                                     _rows(obj, torch.arange(B).repeat(K)))
        w = self._w[None]
        # Among equally good fits prefer forearm and wrist rolls near the middle of their range.
        cost = ((w * errs) ** 2).sum(-1) + 2e-4 * (qs[:, 3] ** 2 + qs[:, 5] ** 2)
        cost = cost.reshape(K, B)
        best = cost.argmin(0)
        pick = best * B + torch.arange(B)
        return qs[pick], errs[pick]

    def _solve_frame(self, target: torch.Tensor, q_prev: torch.Tensor, iters: int, obj=None):
        """Damped Gauss–Newton from ``q_prev``; with the object terms, Levenberg–Marquardt: a step that
        does not lower the cost is refused and the damping raised (their hinges make plain steps
        overshoot)."""
        eye = torch.eye(NUM_JOINTS, dtype=torch.float64)
        reg = self.smooth ** 2
        K = len(_MATCHED)
        q = q_prev.clone()
        r, J, pts = self._residuals(q, target, obj)
        cost = None if obj is None else (r ** 2).sum(1)
        lam = torch.full((len(q), 1, 1), self.damping if obj is None else max(self.damping, self.contact.damping),
                         dtype=torch.float64)
        for _ in range(iters):
            A = J.transpose(1, 2) @ J + (lam + reg) * eye
            g = (J.transpose(1, 2) @ r[..., None])[..., 0] + reg * (q - q_prev)
            dq = -torch.linalg.solve(A, g).clamp(-self.max_step, self.max_step)
            q_new = torch.minimum(torch.maximum(q + dq, self._lo), self._hi)
            r_new, J_new, pts_new = self._residuals(q_new, target, obj)
            if obj is None:
                q, r, J, pts = q_new, r_new, J_new, pts_new
                continue
            cost_new = (r_new ** 2).sum(1) + reg * ((q_new - q_prev) ** 2).sum(1)
            ok = cost_new <= cost
            q, r, J, pts = (torch.where(ok.reshape((-1,) + (1,) * (a.dim() - 1)), a, b)
                            for a, b in ((q_new, q), (r_new, r), (J_new, J), (pts_new, pts)))
            cost = torch.where(ok, cost_new, cost)
            lam = torch.where(ok[:, None, None], lam / 3, lam * 4).clamp(1e-6, 1e3)
        return q, torch.linalg.norm(pts[:, :K] - target, dim=-1)

    def _residuals(self, q: torch.Tensor, target: torch.Tensor, obj):
        """Weighted residuals (N, R), their Jacobian (N, R, 22) and the robot points at ``q``."""
        w = self._w[None, :, None]
        K, S = len(_MATCHED), len(_MATCHED) + len(TABLE_CLEARANCE_POINTS)
        pts, jac = self._points_jacobian(q)
        below = (self._clearance - pts[:, K:S, 2]).clamp(min=0.0)                      # (N, C)
        r = [(w * (pts[:, :K] - target)).reshape(len(q), -1), self.table_weight * below]
        J = [(w[..., None] * jac[:, :K]).reshape(len(q), -1, NUM_JOINTS),
             -self.table_weight * (below > 0)[..., None] * jac[:, K:S, 2]]
        if obj is not None:
            r_obj, J_obj = self._object_residuals(pts[:, S:], jac[:, S:], obj)
            r.append(r_obj)
            J.append(J_obj)
        return torch.cat(r, dim=1), torch.cat(J, dim=1), pts


def _frame(obj, t: int):
    """The object terms at frame ``t`` (planes per sequence, the rest per frame)."""
    return None if obj is None else (obj[0], *(a[:, t] for a in obj[1:]))


def _rows(obj, rows: torch.Tensor):
    return None if obj is None else tuple(a[rows] for a in obj)
