import mujoco
import numpy as np
import pytest
import torch

from adadex.sim.kinematics import RobotKinematics
from adadex.sim.robot import (
    ARM_JOINTS,
    HAND_JOINTS,
    HOME_QPOS,
    JOINT_NAMES,
    ROBOT_MJCF,
    TRACKED_SITES,
    UnknownJointError,
    build_robot_spec,
    effort_limits,
    joint_index,
    joint_limits,
)


@pytest.fixture(scope="module")
def model():
    return build_robot_spec().compile()


def test_joint_order_is_the_one_constant(model):
    assert JOINT_NAMES == ARM_JOINTS + HAND_JOINTS
    assert ARM_JOINTS == ("arm_j1", "arm_j2", "arm_j3", "arm_j4", "arm_j5", "arm_j6")
    assert " ".join(HAND_JOINTS) == ("if_mcp if_rot if_pip if_dip mf_mcp mf_rot mf_pip mf_dip "
                                     "rf_mcp rf_rot rf_pip rf_dip th_cmc th_axl th_mcp th_ipl")
    assert [model.joint(i).name for i in range(model.njnt)] == list(JOINT_NAMES)
    # Actuator i drives joint i: ctrl and qpos share the order.
    assert model.nu == 22
    assert list(model.actuator_trnid[:, 0]) == list(range(22))


def test_limits_and_gains_are_in_the_model(model):
    lim = joint_limits()
    np.testing.assert_allclose(model.jnt_range, lim)
    np.testing.assert_allclose(model.actuator_ctrlrange, lim)
    np.testing.assert_allclose(model.actuator_forcerange[:, 1], effort_limits())
    # xArm6 facts (xarm_description): joint-2 range, shoulder effort 50 N·m, wrist 20 N·m.
    assert lim[1].tolist() == pytest.approx([-2.059, 2.0944])
    assert effort_limits()[[0, 5]].tolist() == [50.0, 20.0]
    assert np.all(model.actuator_gainprm[:, 0] > 0)
    assert np.all((HOME_QPOS >= lim[:, 0]) & (HOME_QPOS <= lim[:, 1]))


def test_tracked_sites_and_masses(model):
    for s in TRACKED_SITES:
        assert model.site(s).id >= 0
    palm = model.body("palm").id
    assert 0.4 < model.body_subtreemass[palm] < 1.2      # LEAP hand is ~0.6 kg
    assert 9.0 < model.body_subtreemass[0] < 14.0         # xArm6 ~9.5 kg + hand


def test_exported_mjcf_matches_builder():
    spec = build_robot_spec()
    spec.compile()
    assert ROBOT_MJCF.exists(), "run `adadex sim export` to write assets/robot/robot.xml"
    assert ROBOT_MJCF.read_text() == spec.to_xml(), (
        "assets/robot/robot.xml is out of date with adadex.sim.robot; run `adadex sim export`")


def test_unknown_joint_names_are_rejected_with_a_suggestion():
    assert joint_index(["th_ipl", "arm_j1"]).tolist() == [21, 0]
    with pytest.raises(UnknownJointError, match="if_pip"):
        joint_index(["if_pipp"])


def test_pytorch_kinematics_matches_mujoco_on_200_random_configurations():
    fk = RobotKinematics()
    m = mujoco.MjModel.from_xml_path(str(ROBOT_MJCF))
    d = mujoco.MjData(m)
    lim = joint_limits()
    q = np.random.default_rng(0).uniform(lim[:, 0], lim[:, 1], size=(200, 22))
    pred = fk.link_poses(torch.tensor(q)).numpy()
    ref = np.zeros_like(pred)
    for i in range(len(q)):
        d.qpos[:] = q[i]
        mujoco.mj_kinematics(m, d)
        for j, s in enumerate(TRACKED_SITES):
            ref[i, j, :3] = d.site(s).xpos
            mujoco.mju_mat2Quat(ref[i, j, 3:], d.site(s).xmat)
    assert np.abs(pred[..., :3] - ref[..., :3]).max() < 1e-5
    dot = np.abs((pred[..., 3:] * ref[..., 3:]).sum(-1)).clip(max=1.0)
    angle = 2 * np.arccos(dot)
    assert angle.max() < 1e-5
