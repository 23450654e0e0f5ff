"""The folded revolute chain against pytorch-kinematics' own Jacobian and end pose."""

import numpy as np
import pytest
import pytorch_kinematics as pk
import torch

from adadex.sim.kinematics import RevoluteChainJacobian, RobotKinematics
from adadex.sim.robot import ARM_JOINTS, TRACKED_SITES, joint_limits


@pytest.mark.parametrize("dtype, tol", [(torch.float64, 1e-10), (torch.float32, 1e-5)])
def test_palm_jacobian_and_pose_equal_pytorch_kinematics(dtype, tol):
    palm = pk.SerialChain(RobotKinematics(dtype=dtype).chain, TRACKED_SITES[0], dtype=dtype)
    lim = joint_limits()[:len(ARM_JOINTS)]
    q = torch.tensor(np.random.default_rng(0).uniform(lim[:, 0], lim[:, 1], size=(200, len(ARM_JOINTS))), dtype=dtype)
    want_jac, want_pose = palm.jacobian(q, ret_eef_pose=True)
    jac, pose = RevoluteChainJacobian(palm)(q)
    assert jac.shape == (200, 6, len(ARM_JOINTS)) and pose.shape == (200, 4, 4)
    assert (jac - want_jac).abs().max() < tol
    assert (pose - want_pose).abs().max() < tol
    with pytest.raises(ValueError, match="size 6"):
        RevoluteChainJacobian(palm)(q[:, :5])


def test_the_jacobian_is_the_derivative_of_the_pose():
    palm = pk.SerialChain(RobotKinematics(dtype=torch.float64).chain, TRACKED_SITES[0], dtype=torch.float64)
    kin = RevoluteChainJacobian(palm)
    q = torch.tensor([[0.3, -0.4, 0.5, 0.2, 0.9, -0.7]], dtype=torch.float64)
    jac, pose = kin(q)
    h = 1e-6
    for j in range(6):
        dq = torch.zeros_like(q)
        dq[0, j] = h
        _, moved = kin(q + dq)
        assert torch.allclose((moved[0, :3, 3] - pose[0, :3, 3]) / h, jac[0, :3, j], atol=1e-5)
        turn = moved[0, :3, :3] @ pose[0, :3, :3].T                  # small rotation ≈ I + [ω]× h
        omega = torch.stack([turn[2, 1] - turn[1, 2], turn[0, 2] - turn[2, 0], turn[1, 0] - turn[0, 1]]) / (2 * h)
        assert torch.allclose(omega, jac[0, 3:, j], atol=1e-5)


def test_a_chain_with_a_sliding_joint_is_refused():
    chain = pk.build_chain_from_mjcf("""
<mujoco><worldbody><body name="a"><joint name="s" type="slide" axis="1 0 0"/><geom size="0.1"/>
<body name="b" pos="0 0 0.1"><joint name="r" type="hinge" axis="0 0 1"/><geom size="0.1"/></body></body>
</worldbody></mujoco>""")
    with pytest.raises(ValueError, match="revolute joints only"):
        RevoluteChainJacobian(pk.SerialChain(chain, "b"))
