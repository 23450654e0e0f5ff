"""The planned pinch in references: where the hand is, and that replay then carries the object."""

import mujoco
import numpy as np
import pytest

from adadex.data.planned_grasp import MAX_STEP, PlannedGraspError, axis_order, plan_hold, smooth_poses
from adadex.data.retarget import Retargeter
from adadex.data.synth import Synthesizer, make_instruction
from adadex.geometry import compose, inverse
from adadex.sim.ik import solve_arm_ik
from adadex.sim.robot import HOME_QPOS, NUM_JOINTS, TRACKED_SITES
from adadex.sim.scene import build_scene_model


@pytest.fixture(scope="module")
def lift_motion():
    """A noisy synthesized lift of the 5 cm cube and its retargeted joints."""
    m = Synthesizer().synthesize(make_instruction("lift", "cube_050", seed=0), seed=1)
    q = Retargeter().retarget(m.keypoints[None]).joint_pos[0]
    return m, q


def _fk(q):
    model = build_scene_model(None)
    data = mujoco.MjData(model)
    palm, tips = [], []
    for row in q:
        data.qpos[:NUM_JOINTS] = row
        mujoco.mj_kinematics(model, data)
        b = model.body("palm").id
        palm.append(np.concatenate([data.xpos[b], data.xquat[b]]))
        tips.append([data.site(s).xpos.copy() for s in TRACKED_SITES[1:4]])
    return np.array(palm), np.array(tips)


def test_hold_keeps_the_palm_on_the_object_and_blends_gently(lift_motion):
    m, q_ret = lift_motion
    info = {}
    q = plan_hold(q_ret, m.object_pose, "cube_050", m.phases, info=info)
    assert q.shape == q_ret.shape and np.isfinite(q).all()
    lim = build_scene_model(None).jnt_range[:NUM_JOINTS]
    assert (q >= lim[:, 0] - 1e-9).all() and (q <= lim[:, 1] + 1e-9).all()
    # Untouched before the approach blend and after the hand is back on the retargeted retreat.
    np.testing.assert_array_equal(q[: info["approach_from"] + 1], q_ret[: info["approach_from"] + 1])
    np.testing.assert_array_equal(q[info["back_at"]:], q_ret[info["back_at"]:])
    # While held, the palm keeps one pose in the (smoothed) object frame, to IK precision.
    held = slice(info["close_from"] + 1, info["open_until"] + 1)
    palm, tips = _fk(q[held])
    rel = compose(inverse(smooth_poses(m.object_pose)[held]), palm)
    assert np.ptp(rel[:, :3], axis=0).max() < 1e-3
    # The fingers are closed when the object starts to move: the tips inside the 5 cm cube's faces.
    _, tips_lift = _fk(q[m.phases["manipulate"]][None])
    local = np.abs(tips_lift[0] - m.object_pose[m.phases["manipulate"], :3])
    assert (local.max(axis=1) < 0.025 + 0.0095).all()       # half side + fingertip radius
    # No arm joint moves faster than the servos follow from the descent to the release.
    assert info["arm_step"] <= MAX_STEP + 1e-9
    assert np.abs(np.diff(q[info["close_from"]: info["open_until"] + 1, 6:], axis=0)).max() <= MAX_STEP + 1e-9
    assert info["axis"] in axis_order(m.object_pose[m.phases["grasp"]])



def test_a_rest_in_the_other_wrist_branch_is_re_solved_so_the_way_to_the_grasp_stays_short(lift_motion):
    """The hand at rest posed alike from the wrist's other branch (j4, j6 half a turn away): the plan
    re-solves the arm there from the grasp's posture, so the reference's palm and fingers keep their
    poses and its arm reaches the pinch no faster than from the branch the grasp is in."""
    m, q_ret = lift_motion
    model = build_scene_model(None)
    approach = m.phases["approach"]
    info = {}
    plan_hold(q_ret, m.object_pose, "cube_050", m.phases, info=info)
    assert not info["rest_resolved"]               # the retargeted rest is in the grasp's branch already
    other = q_ret.copy()
    data = mujoco.MjData(model)
    for k in range(approach + 1):                  # the same palm poses from the home posture's branch
        data.qpos[:NUM_JOINTS] = q_ret[k]
        mujoco.mj_kinematics(model, data)
        b = model.body("palm").id
        other[k], err = solve_arm_ik(model, "palm", data.xpos[b].copy(), data.xmat[b].reshape(3, 3).copy(),
                                     HOME_QPOS if k == 0 else other[k - 1], tol=1e-7)
        other[k, 6:] = q_ret[k, 6:]
        assert err < 1e-5
    assert np.abs(other[0, 3] - q_ret[0, 3]) > 2.5    # j4 half a turn away
    swapped = {}
    q = plan_hold(other, m.object_pose, "cube_050", m.phases, info=swapped)
    assert swapped["rest_resolved"] and swapped["approach_step"] <= info["approach_step"] + 1e-3
    start = swapped["approach_from"] + 1
    palm, tips = _fk(q[:start])
    palm_ref, tips_ref = _fk(other[:start])
    np.testing.assert_allclose(palm[:, :3], palm_ref[:, :3], atol=1e-4)
    np.testing.assert_allclose(tips, tips_ref, atol=1e-4)
    np.testing.assert_array_equal(q[:start, 6:], other[:start, 6:])

def test_a_tall_object_is_pinched_high_enough_that_the_approach_stays_out_of_it():
    """A bottle pinched through its middle has the palm and the index finger's inner links 2 cm inside
    it (the approach then pins it to the table and flings it); the plan raises the pinch line, and no
    frame from the approach to the close reaches more than MAX_OVERLAP into the bottle."""
    from adadex.data.planned_grasp import DIRECTIONS, MAX_OVERLAP, TOLERANCE, _object_model, _robot_model
    from adadex.sim.grasp import object_overlap, plan_pinch
    from adadex.sim.objects import get_object

    m = Synthesizer().synthesize(make_instruction("lift", "bottle_01", seed=1), seed=1)
    q_ret = Retargeter().retarget(m.keypoints[None]).joint_pos[0]
    scene, grasp = _object_model("bottle_01"), m.phases["grasp"]
    middle = plan_pinch(_robot_model(), get_object("bottle_01").mesh().triangles, m.object_pose[grasp],
                        DIRECTIONS["-x"], q_init=q_ret[grasp], tolerance=TOLERANCE)
    assert object_overlap(scene, middle.open, m.object_pose[grasp]).depth > 0.01
    info = {}
    q = plan_hold(q_ret, m.object_pose, "bottle_01", m.phases, info=info)
    assert info["axis"] == "-x" and info["height"] > 0 and info["approach_overlap"] <= MAX_OVERLAP
    way = slice(info["approach_from"], info["close_from"] + 1)
    assert object_overlap(scene, q[way], m.object_pose[way]).depth <= MAX_OVERLAP + 1e-3
    far = object_overlap(scene, HOME_QPOS, m.object_pose[0])
    assert far.depth == 0.0 and far.body is None


def test_axis_order_puts_the_thumb_nearest_the_robot():
    upright = np.array([0.45, 0.0, 0.03, 1.0, 0.0, 0.0, 0.0])
    assert axis_order(upright)[0] == "+x" and axis_order(upright)[-1] == "-x"
    turned = upright.copy()
    turned[3:] = [np.cos(np.pi / 4), 0.0, 0.0, np.sin(np.pi / 4)]     # 90° about z: body +y points to −x
    assert axis_order(turned)[0] == "-y"


def test_bad_phases_are_refused_by_name(lift_motion):
    m, q = lift_motion
    phases = {k: v for k, v in m.phases.items() if k != "placed"}
    with pytest.raises(PlannedGraspError, match="placed"):
        plan_hold(q, m.object_pose, "cube_050", phases)
    late = dict(m.phases, release=len(q) - 2, placed=len(q) - 2)
    with pytest.raises(PlannedGraspError, match="do not fit"):
        plan_hold(q, m.object_pose, "cube_050", late)


def test_replay_carries_the_object_of_a_planned_reference(tmp_path):
    """Kinematic replay through the PD servos, nominal physics: with the retargeted human grasp the
    cube barely rises; with the planned pinch it follows the reference up."""
    from adadex.data.build import build_dataset
    from adadex.envs.replay import replay_policy
    from adadex.envs.tracking import TrackingEnv

    from adadex.cli import main
    from adadex.data.reference import ReferenceDataset

    rises = {}
    for planned in (False, True):
        out = tmp_path / f"ds_{planned}"
        if planned:   # the command line's flag reaches the build
            assert main(["data", "build", "--preset", "tiny", "--seed", "3", "--limit", "1", "--planned-grasp",
                         "--out", str(out), "--quiet"]) == 0
            assert ReferenceDataset(out)[0].meta["planned_grasp"]["axis"] in ("+x", "-x", "+y", "-y")
        else:
            build_dataset("tiny", out, seed=3, progress=False, limit=1)          # lift the cube 21 cm
        env = TrackingEnv(out, num_worlds=1, split=None, draw="cycle", seed=0)
        td = env.rollout(299, replay_policy(), break_when_any_done=False)
        obj = td["next", "object", "pose"][0, :, 2]
        ref = td["next", "reference", "object_pose"][0, :, 0, 2]
        rises[planned] = (float(obj.max() - obj[0]), float(ref.max() - ref[0]))
        env.close()
    (lift_planned, ref_rise), (lift_retargeted, _) = rises[True], rises[False]
    assert ref_rise > 0.05
    assert lift_planned > 0.5 * ref_rise, rises
    assert lift_planned > lift_retargeted + 0.02, rises
