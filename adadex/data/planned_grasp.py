"""References that hold the object with a grasp planned for this hand, not the human's.

Retargeting moves the human's grasp onto the robot: the fingertips go where the human's were. Those
contacts do not make a pinch on this hand — in simulation the closing hand presses the object into
the table and pushes it away: kinematic replay carries 15 of the 161 training references of the
``small`` dataset whose object rises (``python benchmarks/replay_grasp.py --all-groups``). A pinch
planned for the robot (:func:`adadex.sim.grasp.plan_pinch`: thumb on one side, index and middle on
the other, each where its line meets the object's surface, commanded ``squeeze`` m inside) lifts 56
of those references' 65 objects. :func:`plan_hold` puts that pinch into a retargeted reference:

=============================  =======================================================================
frames (synthesis phases)      robot joints
=============================  =======================================================================
before ``approach``            retargeted (the hand at rest, far from the object; the arm re-solved
                               for the same palm poses from the grasp's posture where that shortens
                               the way to the grasp: ``rest_resolved``)
``approach`` → ``grasp``       joint-space blend to the open pinch 8 cm above the object, then down
                               to the open pinch (the last ``grasp − reach`` frames, or as few as the
                               descent needs where the way there needs more frames than precede it)
``grasp`` → ``manipulate``     the fingers close to the squeeze posture (earlier, if closing within
                               :data:`MAX_STEP` per frame takes longer); the palm holds from here on
``manipulate`` → release       the palm keeps its pose in the object's frame while the object moves
                               along its reference path (arm IK per frame, warm-started)
release → + ``open`` frames    the fingers open again
then                           the palm rises 8 cm, and the joints blend back to the retargeted
                               retreat, which they follow from the end of the retreat on
=============================  =======================================================================

The release is the later of the human's release and the object coming to rest (synthesis phases
``release`` and ``placed``), so the hand never lets go of a moving object. The object's path is
the reference's own, noise included; the palm follows it low-passed (:func:`smooth_poses`).

The pinch axis is one of the object's horizontal body axes (±x, ±y), tried in the order that puts
the thumb nearest the robot (the scripted grasp's side), each solved from the retargeted and the
home posture; of those whose fingertips reach their surface points within :data:`TOLERANCE`, the
first whose hold moves no arm joint more than :data:`MAX_STEP` per frame wins. The pinch line runs
through the object's middle, or higher (:data:`PINCH_HEIGHTS`) where the hand would otherwise reach
into the object: pinched at its middle, a bottle or a wineglass has the palm and the index finger's
inner links 2–3 cm inside it, and the approach then pins the object to the table and flings it
before the fingers close. No plan is taken whose hand, from the approach to the close, reaches more
than :data:`MAX_OVERLAP` into the object (:func:`~adadex.sim.grasp.object_overlap`, the object where
the reference has it). A reference with no reachable pinch, or whose hold the arm cannot follow,
raises :class:`PlannedGraspError` (the build counts it as ``no_planned_grasp``).

Example::

    from adadex.data.planned_grasp import plan_hold
    q = plan_hold(retargeted_q, object_pose, "mug_04", motion.phases)   # (T, 22)
"""

from __future__ import annotations

import functools

import mujoco
import numpy as np
from scipy.ndimage import gaussian_filter1d

from adadex.errors import AdadexError
from adadex.geometry import compose, inverse
from adadex.sim.grasp import PINCH_AXES, SQUEEZE, object_overlap, plan_pinch, translate_palm
from adadex.sim.ik import IKError, solve_arm_ik
from adadex.sim.objects import get_object
from adadex.sim.robot import HOME_QPOS, NUM_JOINTS
from adadex.sim.scene import CONTROL_HZ, build_scene_model

#: largest fingertip miss of the planned touch posture, and palm miss (m + rad) of a held frame
TOLERANCE = 5e-3
#: height of the open hand above its pinch before it descends, and of the palm's rise after release (m)
CLEARANCE_HEIGHT = 0.08
#: seconds the fingers take to open after the release, and the palm to rise
OPEN_S, RISE_S = 0.6, 0.6
#: Gaussian smoothing (frames) of the object path the held palm follows
SMOOTHING = 2.0
#: what the planner builds, recorded in a dataset's info (``planner``) so a build made by an earlier one is
#: told apart: 1 the first (2026-11-25); 2 the approach the servos can follow (2026-12-07, night); 3 no
#: approach that reaches into the object (2026-12-07, late; docs/references.md)
PLANNER_VERSION = 3
#: largest joint change per frame of the blends the plan adds (rad; the env's servo targets move ≤ 0.1)
MAX_STEP = 0.08
#: clearance of a preferred pinch's arm joints from their limits (rad)
LIMIT_MARGIN = 0.25
#: deepest the planned hand may reach into the object before it closes (m; the open fingertips are
#: :data:`~adadex.sim.grasp.OPEN_CLEARANCE` out, so anything deeper is a link passing through it)
MAX_OVERLAP = 3e-3
#: heights of the pinch line above the object's origin tried, in units of its half height: a tall or
#: wide-topped object pinched at its middle puts the palm and the index finger's inner links inside it
PINCH_HEIGHTS = (0.0, 0.35, 0.7)
#: required phase names (from :class:`adadex.data.synth.HumanMotion`)
PHASES = ("approach", "reach", "grasp", "manipulate", "placed", "release", "retreat")


class PlannedGraspError(AdadexError, ValueError):
    """No pinch planned for this hand fits the reference; the message says why and where."""


@functools.lru_cache(maxsize=1)
def _robot_model() -> mujoco.MjModel:
    return build_scene_model(None)


@functools.lru_cache(maxsize=4)
def _object_model(object_name: str) -> mujoco.MjModel:
    return build_scene_model(object_name)


#: the digits a pinch presses into the object on purpose
_PRESSING = ("th_ds", "if_ds", "mf_ds")


def _min_jerk(n: int) -> np.ndarray:
    s = np.arange(1, n + 1) / n
    return s ** 3 * (10 - 15 * s + 6 * s ** 2)


def _blend(a: np.ndarray, b: np.ndarray, n: int) -> np.ndarray:
    """(n, 22) joint positions from just after ``a`` to ``b`` (min-jerk; the last is ``b`` exactly)."""
    out = a + _min_jerk(n)[:, None] * (b - a)
    out[-1:] = b
    return out


def _palm_pose(model: mujoco.MjModel, q: np.ndarray) -> np.ndarray:
    data = mujoco.MjData(model)
    data.qpos[:NUM_JOINTS] = q
    mujoco.mj_kinematics(model, data)
    return np.concatenate([data.xpos[model.body("palm").id], data.xquat[model.body("palm").id]])


#: the pinch axes a reference may use: the object's horizontal body axes either way
DIRECTIONS = {f"{s}{k}": sign * v for k, v in PINCH_AXES.items() for s, sign in (("+", 1.0), ("-", -1.0))}


def axis_order(object_pose: np.ndarray) -> list[str]:
    """:data:`DIRECTIONS` (``"+x"``, ``"-y"`` …) for an object at ``object_pose``, the one that puts the
    thumb nearest the robot first."""
    rot = np.empty(9)
    mujoco.mju_quat2Mat(rot, object_pose[3:] / np.linalg.norm(object_pose[3:]))
    outward = np.r_[object_pose[:2], 0.0] / max(np.linalg.norm(object_pose[:2]), 1e-9)
    along = outward @ rot.reshape(3, 3)                  # the outward direction in the object's frame
    return sorted(DIRECTIONS, key=lambda k: -float(along @ DIRECTIONS[k]))


def smooth_poses(poses: np.ndarray, sigma: float = SMOOTHING) -> np.ndarray:
    """(T, 7) poses low-passed with a Gaussian of ``sigma`` frames (positions, and quaternions made
    sign-consistent, filtered and normalized): the hand holds the object's path, not its jitter,
    which near a wrist singularity would swing the arm's roll joints from frame to frame."""
    p = np.array(poses, float)
    quat = p[:, 3:].copy()
    flip = np.cumprod(np.where(np.sum(quat[1:] * quat[:-1], axis=1) < 0, -1.0, 1.0))
    quat[1:] *= flip[:, None]
    out = gaussian_filter1d(np.concatenate([p[:, :3], quat], axis=1), sigma, axis=0, mode="nearest")
    out[:, 3:] /= np.linalg.norm(out[:, 3:], axis=1, keepdims=True)
    return out


def _frames_for(a: np.ndarray, b: np.ndarray) -> int:
    """Frames a min-jerk blend from ``a`` to ``b`` needs to stay within :data:`MAX_STEP` per frame."""
    return int(np.ceil(1.875 * np.abs(b - a).max() / MAX_STEP))


def _limit_margin(model: mujoco.MjModel, q: np.ndarray) -> float:
    lo, hi = model.jnt_range[:6, 0], model.jnt_range[:6, 1]
    return float(np.minimum(q[:6] - lo, hi - q[:6]).min())


def _pinches(model, object_name: str, object_pose: np.ndarray, q_near: np.ndarray, squeeze: float, tried: list):
    """Reachable pinches with their axis, best first, solved as they are asked for: at the heights
    :data:`PINCH_HEIGHTS` (lowest first), each along the axes in :func:`axis_order`, each solved from
    ``q_near`` (the retargeted posture: the shortest way there) and from the home posture; a pinch
    whose open hand reaches more than :data:`MAX_OVERLAP` into the object, or whose touch posture's
    links other than the pressing fingertips reach deeper than the squeeze, is skipped; those whose arm comes within
    :data:`LIMIT_MARGIN` of a joint limit come last (the hold must be able to turn the wrist either
    way). Why others failed goes to ``tried``."""
    info = get_object(object_name)
    triangles = info.mesh().triangles
    scene = _object_model(object_name)
    near_limits = []
    for level in PINCH_HEIGHTS:
        for axis in axis_order(object_pose):
            for init in (q_near, HOME_QPOS):
                try:
                    pinch = plan_pinch(model, triangles, object_pose, DIRECTIONS[axis], squeeze=squeeze,
                                       q_init=init, tolerance=TOLERANCE, label=object_name,
                                       height=level * info.half_height)
                except IKError as e:
                    tried.append(f"{axis}@{level}: {e}")
                    continue
                opened = object_overlap(scene, pinch.open, object_pose)
                touching = object_overlap(scene, pinch.touch, object_pose, skip=_PRESSING)
                if opened.depth > MAX_OVERLAP or touching.depth > max(MAX_OVERLAP, squeeze):
                    inside = opened if opened.depth > MAX_OVERLAP else touching
                    tried.append(f"{axis}@{level}: the hand's {inside.body} lies {1000 * inside.depth:.0f} mm "
                                 f"inside the object")
                    continue
                if _limit_margin(model, pinch.touch) < LIMIT_MARGIN:
                    near_limits.append((pinch, axis))
                else:
                    yield pinch, axis
    yield from near_limits


def _hold(model, start: np.ndarray, palm: np.ndarray, fingers: np.ndarray, object_name: str, first: int):
    """(n, 22) joints putting the palm at ``palm`` (n, 7) with the hand at ``fingers`` (n, 22), each
    frame's arm IK warm-started from the last; raises :class:`PlannedGraspError` on a miss."""
    out = np.empty((len(palm), NUM_JOINTS))
    prev, rot = start, np.empty(9)
    for k in range(len(palm)):
        init = prev.copy()
        init[6:] = fingers[k, 6:]
        mujoco.mju_quat2Mat(rot, palm[k, 3:])
        prev, err = solve_arm_ik(model, "palm", palm[k, :3], rot.reshape(3, 3), init, tol=1e-5, iters=100)
        if err > TOLERANCE:
            raise PlannedGraspError(f"{object_name}: the arm cannot hold the pinch at frame {first + k} "
                                    f"(palm misses by {1000 * err:.1f} mm + mrad)")
        out[k] = prev
    return out


def plan_hold(joint_pos: np.ndarray, object_pose: np.ndarray, object_name: str, phases: dict, *,
              squeeze: float = SQUEEZE, fps: float = CONTROL_HZ, info: dict | None = None) -> np.ndarray:
    """The retargeted ``joint_pos`` (T, 22) with the grasp, hold and release replaced by a planned pinch
    (see the module docstring). ``object_pose`` (T, 7) is the reference's object path; ``phases`` the
    synthesis phases (first frame of each, :data:`PHASES`). ``info``, if given, receives the chosen
    axis, the planning residuals and the frames where the fingers close and open. Of the reachable
    pinches the first whose hold moves no arm joint more than :data:`MAX_STEP` per frame is taken,
    else the smoothest. Returns a new (T, 22) array."""
    q_ret = np.asarray(joint_pos, float)
    T = len(q_ret)
    missing = [p for p in PHASES if p not in phases]
    if missing:
        raise PlannedGraspError(f"{object_name}: the reference has no synthesis phase(s) {missing}; a planned "
                                f"grasp needs the phases of a synthesized motion")
    approach, reach, grasp, manip = (int(phases[k]) for k in ("approach", "reach", "grasp", "manipulate"))
    release = max(int(phases["release"]), int(phases["placed"]))
    n_rise = max(2, round(RISE_S * fps))
    if not 0 < approach < reach < grasp < manip <= release or release + 3 * n_rise >= T:
        raise PlannedGraspError(f"{object_name}: phases {dict(phases)} do not fit a planned grasp in {T} frames")
    model = _robot_model()
    smooth = smooth_poses(object_pose)
    best, tried = None, []
    for pinch, axis in _pinches(model, object_name, object_pose[grasp], q_ret[grasp], squeeze, tried):
        try:
            plan = _plan(model, q_ret, smooth, pinch, object_name, approach, reach, grasp, manip, release,
                         n_rise, fps)
        except (PlannedGraspError, IKError) as e:
            tried.append(f"{axis}: {e}")
            continue
        if best is None or plan["arm_step"] < best[0]["arm_step"]:
            best = (plan, axis, pinch)
        if plan["arm_step"] <= MAX_STEP:
            break
    if best is None:
        raise PlannedGraspError(f"{object_name}: no planned pinch fits at frame {grasp}: " + "; ".join(tried))
    plan, axis, pinch = best
    if info is not None:
        info.update(axis=axis, height=pinch.height, touch_residual=float(pinch.residual), squeeze=float(squeeze),
                    **{k: v for k, v in plan.items() if k != "q"})
    return plan["q"]


def _in_branch_of(model, q_ret: np.ndarray, approach: int, above: np.ndarray) -> np.ndarray:
    """``q_ret`` with its arm joints up to ``approach`` re-solved for the same palm poses (warm-started
    backwards from ``approach``, from the grasp's posture ``above`` and from the retargeted posture with
    its wrist flipped), where that shortens the way to ``above``; else ``q_ret`` itself. The retargeted
    hand at rest can sit in the other branch of the wrist (j4 and j6 half a turn away, the palm posed
    alike), and the way from there to the pinch turns both wrist joints about π: faster than the
    servos' targets may move in the frames the reference leaves it. The palm, fingertips and fingers
    stay as the reference has them."""
    flipped = q_ret[approach].copy()
    flipped[3], flipped[4], flipped[5] = flipped[3] + np.pi, -flipped[4], flipped[5] + np.pi
    flipped[[3, 5]] = (flipped[[3, 5]] + np.pi) % (2 * np.pi) - np.pi
    palms = [_palm_pose(model, q_ret[k]) for k in range(approach + 1)]
    best, rot = q_ret, np.empty(9)
    for seed in (above, flipped):
        out, init = q_ret.copy(), seed.copy()
        for k in range(approach, -1, -1):
            mujoco.mju_quat2Mat(rot, palms[k][3:])
            init[6:] = q_ret[k, 6:]
            init, err = solve_arm_ik(model, "palm", palms[k][:3], rot.reshape(3, 3), init, tol=1e-6, iters=200)
            if err > 1e-4:
                break
            out[k] = init
        else:
            if _frames_for(out[0], above) < _frames_for(best[0], above):
                best = out
    return best


def _plan(model, q_ret, smooth, pinch, object_name, approach, reach, grasp, manip, release, n_rise, fps) -> dict:
    """One pinch's plan, laid out backwards from the object's first motion (``manip``): the fingers
    close no faster than :data:`MAX_STEP` per frame and are closed when the object starts to move."""
    T = len(q_ret)
    above = translate_palm(model, pinch.open, [0.0, 0.0, CLEARANCE_HEIGHT])
    close = manip - max(manip - grasp, _frames_for(pinch.open[6:], pinch.closed[6:]))
    descent = _frames_for(above, pinch.open)
    descend = close - max(grasp - reach, descent)
    resolved = _in_branch_of(model, q_ret, approach, above)
    rest_resolved, q_ret = resolved is not q_ret, resolved
    # earlier if the way is long, but not before the first frame; where even that leaves the way too few
    # frames, the descent takes only what it needs and the way the rest (the servos then lag only where
    # the way is longer than every frame before the descent allows)
    start = max(0, min(approach, descend - _frames_for(q_ret[approach], above)))
    way = _frames_for(q_ret[0], above)
    if start == 0 and descend < way:
        descend = min(close - descent, way)
    n_open = max(round(OPEN_S * fps), _frames_for(pinch.closed[6:], pinch.open[6:]))
    end = release + n_open
    if descend - start < 2 or end + 2 * n_rise >= T:
        raise PlannedGraspError(f"{object_name}: the pinch does not fit the reference's timing "
                                f"(approach from frame {start}, release until {end} of {T})")
    q = q_ret.copy()
    q[start + 1: descend + 1] = _blend(q_ret[start], above, descend - start)
    q[descend + 1: close + 1] = _blend(above, pinch.open, close - descend)
    inside = object_overlap(_object_model(object_name), q[start: close + 1], smooth[start: close + 1])
    if inside.depth > MAX_OVERLAP:
        raise PlannedGraspError(f"{object_name}: the approach passes {1000 * inside.depth:.0f} mm into the object "
                                f"at frame {start + inside.index} (the hand's {inside.body})")
    fingers = np.empty((end - close, NUM_JOINTS))                    # the hand, frames close+1 … end
    fingers[: manip - close] = _blend(pinch.open, pinch.closed, manip - close)
    fingers[manip - close: release - close] = pinch.closed
    fingers[release - close:] = _blend(pinch.closed, pinch.open, n_open)
    # The palm keeps its pose in the object's frame (the object's path smoothed: see smooth_poses).
    in_object = compose(inverse(smooth[grasp]), _palm_pose(model, pinch.touch))
    q[close + 1: end + 1] = _hold(model, q[close], compose(smooth[close + 1: end + 1], in_object), fingers,
                                  object_name, close + 1)
    up = translate_palm(model, q[end], [0.0, 0.0, CLEARANCE_HEIGHT])
    q[end + 1: end + n_rise + 1] = _blend(q[end], up, n_rise)
    # back to the retargeted retreat, no faster than MAX_STEP per frame (or by the last frame)
    back = end + n_rise + _frames_for(up, q_ret[min(T - 1, end + 3 * n_rise)])
    back = min(T - 1, max(back, end + 2 * n_rise))
    q[end + n_rise + 1: back + 1] = _blend(up, q_ret[back], back - end - n_rise)
    arm_step = float(np.abs(np.diff(q[descend: end + 1, :6], axis=0)).max())
    approach_step = float(np.abs(np.diff(q[start: descend + 1], axis=0)).max())
    return {"q": q, "approach_from": int(start), "approach_step": approach_step, "rest_resolved": rest_resolved,
            "approach_overlap": inside.depth,
            "close_from": int(close),
            "release": int(release), "open_until": int(end), "back_at": int(back), "arm_step": arm_step}
