"""A scripted grasp-and-lift: proof that the robot and contact model can manipulate.

The grasp is planned as fingertip placement: thumb on one side of the object, index and middle
fingertips on the opposite side, each where its line across the object meets the surface
(:func:`pinch_surface`: a mug's body, not its bounding box, which holds the handle), palm facing
down. :func:`fingertip_grasp` solves for all 22 joints
by bounded least squares on MuJoCo forward kinematics (with MuJoCo's Jacobians);
:func:`plan_pinch` gives a pinch's touch, open and closed postures on an object at any pose (what
:mod:`adadex.data.planned_grasp` puts into references). The script then opens the hand above the
object, descends, closes to a posture whose fingertips lie ``squeeze`` metres *inside* the object
(the position servos then press with a force set by their gains and effort limits), lifts and
holds. It runs through :class:`~adadex.sim.batched.BatchedSim`, so it exercises the batched
simulator too.

Example::

    from adadex.sim.grasp import scripted_grasp_lift
    result = scripted_grasp_lift("cube_050")
    result.max_slip < 0.02 and result.lift_achieved > 0.09
"""

from __future__ import annotations

from dataclasses import dataclass

import mujoco
import numpy as np
from scipy.optimize import least_squares

from adadex.errors import ConfigError
from adadex.geometry import first_hits
from adadex.sim.batched import BatchedSim, flung
from adadex.sim.ik import IKError, solve_arm_ik
from adadex.sim.robot import FINGER_RADIUS, HOME_QPOS, NUM_JOINTS, TRACKED_SITES
from adadex.sim.scene import CONTROL_HZ, OBJECT_HOME_XY, build_scene_model

_TIP = {s: i for i, s in enumerate(TRACKED_SITES)}
_RING_CURLED = {"rf_mcp": 1.6, "rf_rot": 0.0, "rf_pip": 1.5, "rf_dip": 1.2}


@dataclass
class GraspResult:
    """Outcome of :func:`scripted_grasp_lift` (distances in metres)."""

    object_name: str
    lift_achieved: float            # object height gain at the end of the hold
    max_slip: float                 # largest drift of the object in the palm frame after closing
    object_in_palm: np.ndarray      # (T, 3) object position in the palm frame, every control step
    object_height: np.ndarray       # (T,) object z, every control step
    phase_ends: dict[str, int]      # control-step index at which each phase ends
    #: MuJoCo diverged, or the object was flung faster than MAX_OBJECT_SPEED (the lift and slip then
    #: measure the fling, not the grasp)
    unstable: bool


#: sideways offset of the index and middle fingertips from the pinch line (m)
FINGER_SPREAD = 0.022


def pinch_surface(triangles: np.ndarray, approach=(1.0, 0.0, 0.0), spread: float = FINGER_SPREAD, *,
                  height: float = 0.0) -> dict:
    """Where each digit of the pinch meets an object, in the frame of its ``triangles`` (F, 3, 3):
    the thumb along the line through the origin (raised ``height`` m along the object's z axis) from
    the −``approach`` side, index and middle ``spread`` to either side of it from the +``approach``
    side. A finger whose line misses (an object narrower than the spread) rests beside the middle
    line's point. Raises ``IKError`` when the pinch line misses the object."""
    u = np.asarray(approach, float) / np.linalg.norm(approach)
    v = np.cross([0.0, 0.0, 1.0], u)
    up = np.array([0.0, 0.0, float(height)])
    lines = {"thumb_tip": (up - u, u), "index_tip": (up + u + spread * v, -u),
             "middle_tip": (up + u - spread * v, -u), "centre": (up + u, -u)}
    dist, _ = first_hits(np.asarray(triangles, float), np.array([o for o, _ in lines.values()]),
                         np.array([d for _, d in lines.values()]))
    if not np.isfinite(dist[[0, 3]]).all():
        raise IKError("the pinch line through the object's origin misses it")
    hit = {k: o + t * d for (k, (o, d)), t in zip(lines.items(), dist) if np.isfinite(t)}
    for k, side in (("index_tip", 1.0), ("middle_tip", -1.0)):
        if k not in hit:
            hit[k] = hit["centre"] + side * spread * v
    del hit["centre"]
    return hit


def fingertip_grasp(model: mujoco.MjModel, surface: dict, *,
                    approach: np.ndarray = np.array([1.0, 0.0, 0.0]), clearance: float = 0.0,
                    q_init: np.ndarray | None = None, min_wrist_height: float = 0.2,
                    hand_only: bool = False) -> tuple[np.ndarray, float]:
    """Joint positions placing the thumb tip on one side of an object and index + middle tips on the other.

    The contact normal is ``approach`` (horizontal; the thumb is on the −approach side); the wrist
    stays above ``min_wrist_height`` so the arm clears the table. ``surface`` holds each digit's
    surface point in the world (:func:`pinch_surface`, shifted to where the object is); fingertip
    sphere centres are put ``FINGER_RADIUS + clearance`` out from them along the pinch axis
    (negative clearance = inside the object, for squeezing). With ``hand_only`` the arm keeps its
    joints from ``q_init`` and only the fingers move. Returns ``(qpos[22], residual_m)``.
    """
    u = np.asarray(approach, float)
    u = u / np.linalg.norm(u)
    out = FINGER_RADIUS + clearance
    targets = {"thumb_tip": surface["thumb_tip"] - out * u, "index_tip": surface["index_tip"] + out * u,
               "middle_tip": surface["middle_tip"] + out * u}
    data = mujoco.MjData(model)
    lo, hi = model.jnt_range[:NUM_JOINTS, 0], model.jnt_range[:NUM_JOINTS, 1]
    q0 = np.clip(np.array(HOME_QPOS if q_init is None else q_init, float), lo, hi)
    distal = {"thumb_tip": model.body("th_ds").id, "index_tip": model.body("if_ds").id,
              "middle_tip": model.body("mf_ds").id}
    ring = [model.joint(n).id for n in _RING_CURLED]
    ring_target = np.array(list(_RING_CURLED.values()))
    wrist = [model.body("link4").id, model.body("link5").id, model.body("link6").id]

    free = np.arange(6 if hand_only else 0, NUM_JOINTS)
    dofs = model.jnt_dofadr[free]
    sites = {s: model.site(s).id for s in targets}

    def pose(x):
        q = q0.copy()
        q[free] = x
        data.qpos[:NUM_JOINTS] = q
        mujoco.mj_kinematics(model, data)
        return q

    def residual(x):
        q = pose(x)
        r = [data.site_xpos[sites[s]] - t for s, t in targets.items()]
        for s, b in distal.items():  # distal links come down vertically, clear of the object
            d = data.site_xpos[sites[s]] - data.xpos[b]
            r.append(0.02 * (d / np.linalg.norm(d) - [0.0, 0.0, -1.0]))
        r.append(np.maximum(0.0, min_wrist_height - data.xpos[wrist, 2]))  # keep the arm off the table
        r.append(0.02 * (q[ring] - ring_target))
        r.append(1e-3 * (q - q0))
        return np.concatenate(r)

    jsite, jbody = np.zeros((3, model.nv)), np.zeros((3, model.nv))

    def jacobian(x):
        """The residual's derivative, from MuJoCo's site and body Jacobians (one kinematics pass,
        where finite differences take one per joint)."""
        pose(x)
        mujoco.mj_comPos(model, data)
        rows = []
        for s in targets:
            mujoco.mj_jacSite(model, data, jsite, None, sites[s])
            rows.append(jsite[:, dofs].copy())
        for s, b in distal.items():
            d = data.site_xpos[sites[s]] - data.xpos[b]
            n = np.linalg.norm(d)
            mujoco.mj_jacSite(model, data, jsite, None, sites[s])
            mujoco.mj_jacBody(model, data, jbody, None, b)
            rows.append(0.02 * (np.eye(3) - np.outer(d, d) / n ** 2) / n @ (jsite - jbody)[:, dofs])
        for b in wrist:
            mujoco.mj_jacBody(model, data, jbody, None, b)
            rows.append(-jbody[2:3, dofs] * (min_wrist_height - data.xpos[b, 2] > 0))
        rows.append(0.02 * (np.array(ring)[:, None] == free[None, :]))
        rows.append(1e-3 * (np.arange(NUM_JOINTS)[:, None] == free[None, :]))
        return np.vstack(rows)

    sol = least_squares(residual, q0[free], jac=jacobian, bounds=(lo[free], hi[free]), xtol=1e-10, ftol=1e-10,
                        max_nfev=400)
    q = q0.copy()
    q[free] = sol.x
    data.qpos[:NUM_JOINTS] = q
    mujoco.mj_kinematics(model, data)
    err = max(np.linalg.norm(data.site(s).xpos - t) for s, t in targets.items())
    return q, float(err)


def translate_palm(model: mujoco.MjModel, q: np.ndarray, shift) -> np.ndarray:
    """Joint positions ``q`` with the palm moved by ``shift`` (m, world frame) and its orientation and
    the hand's joints kept (arm IK). Raises ``IKError`` if the arm cannot get there."""
    data = mujoco.MjData(model)
    data.qpos[:NUM_JOINTS] = q
    mujoco.mj_kinematics(model, data)
    palm = model.body("palm").id
    target = data.xpos[palm] + np.asarray(shift, float)
    out, err = solve_arm_ik(model, "palm", target, data.xmat[palm].reshape(3, 3).copy(), q, restarts=10)
    if err > 1e-3:
        raise IKError(f"cannot move the palm by {list(shift)} from this posture (error {err:.1e})")
    return out


#: the horizontal axes a scripted pinch can squeeze along (the object in its canonical pose)
PINCH_AXES = {"x": np.array([1.0, 0.0, 0.0]), "y": np.array([0.0, 1.0, 0.0])}
#: how far the fingertips open away from the surface before closing (m)
OPEN_CLEARANCE = 0.03
#: how far inside the object the closed fingertips are commanded (m): the servos then press
SQUEEZE = 0.012


@dataclass
class Pinch:
    """A pinch planned on an object at a pose: the three postures of the hand (22 joints each)."""

    touch: np.ndarray      # fingertips on the surface
    open: np.ndarray       # the same arm, fingertips ``OPEN_CLEARANCE`` out
    closed: np.ndarray     # the same arm, fingertips ``squeeze`` inside (what the servos are sent)
    approach: np.ndarray   # (3,) world pinch axis; the thumb is on its negative side
    residual: float        # fingertip distance from the touch targets, m
    height: float = 0.0    # the pinch line's height above the object's origin, m


def plan_pinch(model: mujoco.MjModel, triangles: np.ndarray, object_pose, approach, *, squeeze: float = SQUEEZE,
               q_init: np.ndarray | None = None, tolerance: float = 5e-3, label: str = "the object",
               height: float = 0.0) -> Pinch:
    """Plan a pinch of an object whose mesh ``triangles`` (object frame) sit at ``object_pose`` (7,
    w-first), squeezing along ``approach`` (3, in the object's frame; horizontal when the object is
    upright) ``height`` m above its origin: the digits where :func:`pinch_surface` puts them, solved by
    :func:`fingertip_grasp` from ``q_init``. Raises ``IKError`` when the touch posture misses by more
    than ``tolerance`` m."""
    pose = np.asarray(object_pose, float)
    rot = np.empty(9)
    mujoco.mju_quat2Mat(rot, pose[3:] / np.linalg.norm(pose[3:]))
    rot = rot.reshape(3, 3)
    u = rot @ np.asarray(approach, float)
    surface = {k: rot @ p + pose[:3] for k, p in pinch_surface(triangles, approach=approach, height=height).items()}
    touch, err = fingertip_grasp(model, surface, approach=u, q_init=q_init)
    if err > tolerance:
        raise IKError(f"fingertip grasp of {label} along {np.round(u, 3).tolist()} at "
                      f"{pose[:3].round(3).tolist()} not reachable (residual {1000 * err:.1f} mm)")
    # open/closed postures need not be met exactly (the fingers' reach ends)
    open_, _ = fingertip_grasp(model, surface, approach=u, clearance=OPEN_CLEARANCE, q_init=touch, hand_only=True)
    closed, _ = fingertip_grasp(model, surface, approach=u, clearance=-squeeze, q_init=touch, hand_only=True)
    return Pinch(touch, open_, closed, u, err, float(height))


@dataclass(frozen=True)
class Overlap:
    """The deepest overlap of the robot with the object over some postures: ``depth`` m (0: none),
    at posture ``index``, by robot body ``body`` (``None`` where nothing overlaps)."""

    depth: float
    index: int | None
    body: str | None


def object_overlap(model: mujoco.MjModel, joint_pos, object_pose, *, skip: tuple[str, ...] = ()) -> Overlap:
    """How deep the robot reaches into the object, kinematically, over postures ``joint_pos`` (N, 22)
    with the object at ``object_pose`` ((N, 7) or one (7,) for all): the deepest of the robot–object
    contacts MuJoCo's collision finds (table contacts are not counted; bodies named in ``skip`` are
    not either, e.g. the fingertips meant to press in). ``model`` is a scene holding the object
    (:func:`~adadex.sim.scene.build_scene_model`). A planned approach that overlaps the object pushes
    or flings it before the grasp (:mod:`adadex.data.planned_grasp` refuses one).

    Example::

        m = build_scene_model("bottle_01")
        object_overlap(m, pinch.open[None], pose).depth     # 0.0 where the open hand clears the bottle
    """
    q = np.atleast_2d(np.asarray(joint_pos, float))
    poses = np.broadcast_to(np.asarray(object_pose, float), (len(q), 7))
    data = mujoco.MjData(model)
    obj = model.body("object").id
    skipped = {model.body(n).id for n in skip} | {0}
    deepest, where, who = 0.0, None, None
    for k in range(len(q)):
        data.qpos[:NUM_JOINTS] = q[k]
        data.qpos[NUM_JOINTS:NUM_JOINTS + 7] = poses[k]
        mujoco.mj_kinematics(model, data)
        mujoco.mj_collision(model, data)
        for c in data.contact[:data.ncon]:
            b1, b2 = model.geom_bodyid[c.geom1], model.geom_bodyid[c.geom2]
            if (b1 == obj) == (b2 == obj):
                continue
            other = b2 if b1 == obj else b1
            if other not in skipped and -c.dist > deepest:
                deepest, where, who = float(-c.dist), k, model.body(other).name
    return Overlap(deepest, where, who)


def scripted_grasp_lift(object_name: str = "cube_050", *, lift: float = 0.10, hold_s: float = 3.0,
                        squeeze: float = SQUEEZE, nthread: int = 0, model=None, axis: str = "x") -> GraspResult:
    """Run the scripted grasp on ``object_name`` resting at the default spot, squeezing along ``axis``
    (``"x"``: away from the robot, or ``"y"``: across); see module docstring.

    The plan: settle above the object, descend, close, squeeze, lift, hold (``hold_s``), stepped in
    one world at the control rate.

    Args:
        object_name: the object (default ``"cube_050"``), resting at :data:`OBJECT_HOME_XY`.
        lift: how far the palm rises in the lift phase, m (default 0.10).
        hold_s: duration of the final hold, s (default 3.0).
        squeeze: how far the fingertips close past the object's surface, m (default
            :data:`SQUEEZE`, 0.012).
        nthread: threads of the :class:`BatchedSim` rollout pool (default 0: the calling thread).
        model: the scene model to use (default: :func:`build_scene_model` of ``object_name``); it
            must hold that object.
        axis: the pinch direction, ``"x"`` or ``"y"`` (default ``"x"``); others raise
            :class:`~adadex.errors.ConfigError`.

    Returns:
        a :class:`GraspResult` (lift achieved, slip in the palm frame, per-step traces).
    """
    from adadex.sim import objects

    if axis not in PINCH_AXES:
        raise ConfigError(f"axis must be one of {sorted(PINCH_AXES)}, got {axis!r}")
    info = objects.get_object(object_name)
    model = model if model is not None else build_scene_model(object_name)
    obj0 = np.array([OBJECT_HOME_XY[0], OBJECT_HOME_XY[1], info.half_height])
    pinch = plan_pinch(model, info.mesh().triangles, np.r_[obj0, 1.0, 0.0, 0.0, 0.0], PINCH_AXES[axis],
                       squeeze=squeeze, label=f"{object_name} along {axis}")
    q_open, q_closed = pinch.open, pinch.closed
    # Above and lifted: the same hand posture, the palm translated straight up (arm IK only).
    q_above = translate_palm(model, q_open, [0, 0, 0.10])
    q_lift = translate_palm(model, q_closed, [0, 0, lift])

    steps = lambda s: int(round(s * CONTROL_HZ))  # noqa: E731
    plan = [  # (phase, control steps, start posture, end posture)
        ("settle", steps(1.0), q_above, q_above),
        ("descend", steps(1.5), q_above, q_open),
        ("close", steps(1.0), q_open, q_closed),
        ("squeeze", steps(0.5), q_closed, q_closed),
        ("lift", steps(1.5), q_closed, q_lift),
        ("hold", steps(hold_s), q_lift, q_lift),
    ]
    sim = BatchedSim(model, 1, nthread=nthread)
    sim.reset(qpos=np.concatenate([q_above, [*obj0[:2], obj0[2] + 1e-3, 1, 0, 0, 0]]))
    in_palm, heights, ends, unstable = [], [], {}, False
    palm_rot = np.empty(9)
    for name, n, start, end in plan:
        for k in range(n):
            a = (k + 1) / n
            out = sim.step(((1 - a) * start + a * end)[None, :])
            unstable |= bool(out.unstable[0] or flung(out.object_vel)[0])
            mujoco.mju_quat2Mat(palm_rot, out.link_pose[0, _TIP["palm"], 3:])
            rel = out.object_pose[0, :3] - out.link_pose[0, _TIP["palm"], :3]
            in_palm.append(palm_rot.reshape(3, 3).T @ rel)
            heights.append(out.object_pose[0, 2])
        ends[name] = len(heights)
    sim.close()
    in_palm_arr, heights_arr = np.array(in_palm), np.array(heights)
    after_close = in_palm_arr[ends["squeeze"] - 1:]
    slip = float(np.linalg.norm(after_close - after_close[0], axis=1).max())
    return GraspResult(object_name=object_name, lift_achieved=float(heights_arr[-1] - obj0[2]),
                       max_slip=slip, object_in_palm=in_palm_arr, object_height=heights_arr,
                       phase_ends=ends, unstable=unstable)
