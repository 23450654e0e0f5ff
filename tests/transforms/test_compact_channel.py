"""Channel C, the compact reference edit: the visible reference's palm moves by the offset asked for
(through the arm Jacobian, unturned), the fingers close by the grip asked for, nothing else moves, and
it composes with the other channels and the policy graph like any channel."""

import pytest
import torch
from tensordict import TensorDict
from torchrl.envs import TransformedEnv
from torchrl.envs.utils import ExplorationType, check_env_specs, set_exploration_type

from adadex.envs.observation import REF_JOINT_POS, flat_observation
from adadex.envs.tracking import TrackingEnv
from adadex.modules.channels import GRIP, GRIP_JOINTS, PALM, ModulationConfig, ModulationLayout
from adadex.modules.modulator import Modulator
from adadex.modules.tracker import Tracker
from adadex.quat import quat_angle_between
from adadex.sim.kinematics import RobotKinematics
from adadex.sim.robot import JOINT_NAMES
from adadex.transforms.modulation import CompactModulation, modulation
from adadex.transforms.policy import make_policy


def _td(ref_q, palm, grip):
    B = ref_q.shape[0]
    z = torch.zeros
    td = TensorDict({REF_JOINT_POS: ref_q.clone(), ("reference", "object_pose"): z(B, 5, 7),
                     ("proprio", "joint_pos"): z(B, 22), ("proprio", "link_pose"): z(B, 5, 7),
                     ("object", "pose"): z(B, 7), ("object", "latent"): z(B, 64), PALM: palm, GRIP: grip},
                    batch_size=[B])
    td["observation"] = flat_observation(td["proprio", "joint_pos"], td["proprio", "link_pose"], td["object", "pose"],
                                         td["object", "latent"], td[REF_JOINT_POS], td["reference", "object_pose"])
    return td


def test_palm_moves_by_the_offset_unturned_and_fingers_close():
    g = torch.Generator().manual_seed(0)
    B = 6
    ref_q = torch.zeros(B, 5, 22)
    ref_q[..., :6] = torch.tensor([0.0, -0.3, -0.6, 0.0, 1.0, 0.0]) + 0.2 * torch.randn(B, 5, 6, generator=g)
    ref_q[..., 6:] = 0.3
    palm = torch.tensor([[1.0, 0, 0], [0, 1.0, 0], [0, 0, -1.0], [0.5, -0.5, 0.2], [0, 0, 0], [-1.0, 0.3, 0.0]])
    grip = torch.tensor([[1.0, 0, 0, -1.0]]).expand(B, 4)
    cfg = ModulationConfig(lambda_palm=0.05, lambda_grip=0.2)
    out = CompactModulation(cfg)._inv_call(_td(ref_q, palm, grip))
    kin = RobotKinematics()
    before, after = kin.link_poses(ref_q.double()), kin.link_poses(out[REF_JOINT_POS].double())
    moved = (after[..., 0, :3] - before[..., 0, :3]).float()
    torch.testing.assert_close(moved, (0.05 * palm)[:, None].expand(B, 5, 3), atol=2e-3, rtol=0)
    assert quat_angle_between(after[..., 0, 3:], before[..., 0, 3:]).max() < 0.02       # unturned
    dq = out[REF_JOINT_POS] - ref_q
    index = [JOINT_NAMES.index(j) for j in GRIP_JOINTS[0]]
    thumb = [JOINT_NAMES.index(j) for j in GRIP_JOINTS[3]]
    torch.testing.assert_close(dq[..., index], torch.full((B, 5, 3), 0.2))
    torch.testing.assert_close(dq[..., thumb], torch.full((B, 5, 2), -0.2))
    untouched = [i for i in range(6, 22) if i not in index + thumb]
    assert dq[..., untouched].abs().max() == 0
    assert dq[4, :, :6].abs().max() == 0                        # no palm offset, no arm change
    # the 273-D vector the tracker reads is rebuilt from the edited reference
    torch.testing.assert_close(out["observation"][:, 121:143], out[REF_JOINT_POS][:, 1])


def test_compact_channel_in_the_chain_and_the_policy_graph(tiny_dataset):
    torch.manual_seed(0)
    tracker = Tracker.replay()
    assert ModulationLayout("C+T").dim == 7 + 22
    env = TransformedEnv(TrackingEnv(tiny_dataset, num_worlds=2, split=None, seed=3), modulation("R+C+T", tracker))
    check_env_specs(env)
    env.close()
    mod = Modulator("C+T", hidden=(16, 16), init_scale=1.0)
    policy = make_policy(tracker, mod)

    def run(env, pol):
        env.set_seed(7)
        torch.manual_seed(1)
        with set_exploration_type(ExplorationType.RANDOM), torch.no_grad():
            return env.rollout(5, pol, break_when_any_done=False)

    a = run(TransformedEnv(TrackingEnv(tiny_dataset, num_worlds=2, split=None, seed=3), policy.primer()), policy)
    b = run(TransformedEnv(TrackingEnv(tiny_dataset, num_worlds=2, split=None, seed=3),
                           modulation("C+T", tracker, view=mod.view)), mod.actor)
    assert torch.equal(a["next", "proprio", "joint_pos"], b["next", "proprio", "joint_pos"])
    assert a["modulation", "sample"].abs().max() > 0.1


@pytest.mark.parametrize("field", ["lambda_palm", "lambda_grip"])
def test_compact_bounds_are_checked(field):
    with pytest.raises(ValueError, match=field):
        ModulationConfig(**{field: -0.1})
