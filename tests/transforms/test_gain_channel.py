"""Channel K, the feedback gain: no gain is the tracker itself, a gain adds that multiple of each
joint's tracking error (arm and hand apart, within the bound) to the tracker's action, the gains
chosen at an episode's first step hold for the episode, the view shows them, and the policy graph
runs as the transformed env."""

import torch
from torchrl.envs import TransformedEnv
from torchrl.envs.utils import ExplorationType, set_exploration_type

from adadex.envs.observation import JOINT_POS, REF_JOINT_POS
from adadex.envs.randomization import Randomization
from adadex.envs.tracking import TrackingConfig, TrackingEnv
from adadex.modules.channels import GAIN_STATE, ModulationConfig, ModulationLayout
from adadex.modules.modulator import Modulator
from adadex.modules.tracker import Tracker
from adadex.sim.robot import joint_limits
from adadex.transforms.modulation import modulation
from adadex.transforms.policy import make_policy
from tests.transforms.scripted import sampled_rollout, scripted_rollout

WIDE = ModulationConfig(gain_bound=10.0)


def _plain(dataset, worlds=4):
    # actions unclipped by the env (max_action), so the residual shows as it is
    return TrackingEnv(dataset, num_worlds=worlds, split=None, seed=3, randomize=Randomization.off(),
                       config=TrackingConfig(max_action=10.0))


def _env(dataset, channels="K", config=ModulationConfig(), view=None, worlds=4):
    return TransformedEnv(_plain(dataset, worlds), modulation(channels, Tracker.replay().freeze(), config=config,
                                                              view=view))


def _rollout(dataset, script, config=ModulationConfig(), steps=8):
    return scripted_rollout(_env(dataset, config=config), script, 2, steps)


def test_no_gain_is_replay_and_a_gain_adds_the_tracking_error(tiny_dataset):
    assert ModulationLayout("T+K").channels == ("T", "K") and ModulationLayout("K").dim == 2
    env = _plain(tiny_dataset)
    env.set_seed(3)
    with set_exploration_type(ExplorationType.DETERMINISTIC), torch.no_grad():
        replay = env.rollout(8, Tracker.replay().actor, break_when_any_done=False)
    env.close()
    target = ("next", "proprio", "joint_target")
    assert torch.equal(_rollout(tiny_dataset, [[0.0, 0.0]])[target], replay[target])
    # at reset the joints sit on the reference (no error, no correction); at the second step, from the
    # same state as replay's, the correction is g · (reference − position) at that frame
    td = _rollout(tiny_dataset, [[0.5, 0.25]], config=WIDE, steps=2)        # g = 1 (arm), 0.5 (hand)
    assert torch.equal(td[target][:, 0], replay[target][:, 0])
    error = td[REF_JOINT_POS][:, 1, 0] - td[JOINT_POS][:, 1]
    gain = torch.cat([torch.ones(6), torch.full((16,), 0.5)])
    lim = torch.as_tensor(joint_limits(), dtype=torch.float32)               # the env clips targets to them
    expected = torch.maximum(torch.minimum(replay[target][:, 1] + gain * error, lim[:, 1]), lim[:, 0])
    torch.testing.assert_close(td[target][:, 1], expected, atol=1e-5, rtol=0)
    assert error.abs().max() > 1e-3                                            # the servos lag: an error to fix
    bounded = _rollout(tiny_dataset, [[1.0, 1.0]], config=ModulationConfig(gain_bound=1e-4), steps=2)
    assert (bounded[target][:, 1] - replay[target][:, 1]).abs().max() <= 1e-4 + 1e-6


def test_a_negative_gain_softens_only_as_far_as_max_softening_allows(tiny_dataset):
    """``max_softening`` lets K's gain go below 0 (kp × (1 + g)): a = −0.25 is g = 2 · −0.25 = −0.5,
    a = −1 stops at −max_softening; with the default (0) a negative action is the tracker itself."""
    target = ("next", "proprio", "joint_target")
    plain = _rollout(tiny_dataset, [[0.0, 0.0]], config=WIDE, steps=2)
    assert torch.equal(_rollout(tiny_dataset, [[-0.25, -1.0]], config=WIDE, steps=2)[target], plain[target])
    soft = ModulationConfig(gain_bound=10.0, max_softening=0.3)
    td = _rollout(tiny_dataset, [[-0.1, -1.0]], config=soft, steps=2)       # g = −0.2 (arm), −0.3 (hand)
    error = td[REF_JOINT_POS][:, 1, 0] - td[JOINT_POS][:, 1]
    gain = torch.cat([torch.full((6,), -0.2), torch.full((16,), -0.3)])
    lim = torch.as_tensor(joint_limits(), dtype=torch.float32)
    expected = torch.maximum(torch.minimum(plain[target][:, 1] + gain * error, lim[:, 1]), lim[:, 0])
    torch.testing.assert_close(td[target][:, 1], expected, atol=1e-5, rtol=0)
    assert (td[target][:, 1] - plain[target][:, 1]).abs().max() > 1e-4
    torch.testing.assert_close(td["next", GAIN_STATE][:, 0, :2], torch.tensor([-0.2, -0.3]).expand(4, 2))


def test_the_first_steps_gains_hold_for_the_episode_and_the_view_shows_them(tiny_dataset):
    latched = _rollout(tiny_dataset, [[0.5, 0.25], [1.0, 0.0], [0.0, 1.0]])
    torch.testing.assert_close(latched["next", GAIN_STATE], torch.tensor([1.0, 0.5, 1.0]).expand(4, 8, 3))
    constant = _rollout(tiny_dataset, [[0.5, 0.25]])
    assert torch.equal(latched["next", "proprio", "joint_target"], constant["next", "proprio", "joint_target"])
    torch.manual_seed(0)
    mod = Modulator("T+K", hidden=(16, 16))
    part = mod.view.slices()["gain"]
    policy = make_policy(Tracker.replay().freeze(), mod)

    a = sampled_rollout(TransformedEnv(_plain(tiny_dataset, 2), policy.primer()), policy, 5)
    b = sampled_rollout(_env(tiny_dataset, "T+K", view=mod.view, worlds=2), mod.actor, 5)
    assert torch.equal(a["next", "proprio", "joint_pos"], b["next", "proprio", "joint_pos"])
    torch.testing.assert_close(b["next", "modulator", "view"][..., part], b["next", GAIN_STATE][..., :2])
    k = slice(22, 24)                                   # K's entries after T's 22
    assert torch.equal(b["modulator", "loc"][:, 1:, k], torch.zeros(2, 4, 2))
