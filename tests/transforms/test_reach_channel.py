"""Channel A, the object-anchor reach: a full reach around kinematic replay is the anchored
feed-forward, no reach is replay itself, the reach chosen at an episode's first step holds for the
episode (and is chosen again after a reset), the modulator's view shows it, and the policy graph
runs the same as the transformed env."""

import dataclasses

import torch
from torchrl.envs import TransformedEnv
from torchrl.envs.utils import ExplorationType, check_env_specs, set_exploration_type

from adadex.envs.randomization import Randomization
from adadex.envs.tracking import TrackingEnv
from adadex.modules.channels import REACH_STATE, ModulationConfig, ModulationLayout
from adadex.modules.modulator import Modulator
from adadex.modules.tracker import Tracker
from adadex.transforms.modulation import modulation
from adadex.transforms.policy import make_policy
from tests.transforms.scripted import sampled_rollout, scripted

DISPLACED = dataclasses.replace(Randomization.off(), object_xy_std=0.05)


def _rollout(dataset, channels, policy, steps=12, config=ModulationConfig(), seed=3):
    env = TransformedEnv(TrackingEnv(dataset, num_worlds=6, split=None, seed=seed, randomize=DISPLACED),
                         modulation(channels, Tracker.replay().freeze(), config=config))
    check_env_specs(env)
    env.set_seed(seed)
    with torch.no_grad():
        td = env.rollout(steps, policy, break_when_any_done=False)
    env.close()
    return td


def _plain(dataset, policy, steps=12, seed=3):
    env = TrackingEnv(dataset, num_worlds=6, split=None, seed=seed, randomize=DISPLACED)
    env.set_seed(seed)
    with set_exploration_type(ExplorationType.DETERMINISTIC), torch.no_grad():
        td = env.rollout(steps, policy, break_when_any_done=False)
    env.close()
    return td


def test_full_reach_is_the_anchored_feed_forward_and_none_is_replay(tiny_dataset):
    assert ModulationLayout("A").dim == 1 and ModulationLayout("C+A+T").channels == ("C", "A", "T")
    full = _rollout(tiny_dataset, "A", scripted([1.0], 1))
    none = _rollout(tiny_dataset, "A", scripted([-1.0], 1))
    anchored = _plain(tiny_dataset, Tracker(hidden=(16,), residual=0.25, anchor=0.05).zero_mean().actor)
    replay = _plain(tiny_dataset, Tracker.replay().actor)
    torch.testing.assert_close(full["next", "proprio", "joint_target"], anchored["next", "proprio", "joint_target"],
                               atol=1e-5, rtol=0)
    assert torch.equal(none["next", "proprio", "joint_target"], replay["next", "proprio", "joint_target"])
    assert (anchored["action"] - replay["action"]).abs().max() > 0.01          # the anchor moved the hand


def test_the_first_steps_reach_holds_for_the_episode_unless_unlatched(tiny_dataset):
    script = [0.0, 1.0, -1.0, 1.0, -1.0, 0.7, -0.8, 1.0, -1.0, 0.3, 0.9, -0.9]
    latched = _rollout(tiny_dataset, "A", scripted(script, 1))
    constant = _rollout(tiny_dataset, "A", scripted([0.0], 1))
    assert torch.equal(latched["next", "proprio", "joint_target"], constant["next", "proprio", "joint_target"])
    torch.testing.assert_close(latched["next", REACH_STATE], torch.tensor([0.5, 1.0]).expand(6, 12, 2))
    free = _rollout(tiny_dataset, "A", scripted(script, 1), config=ModulationConfig(reach_latched=False))
    assert (free["next", "proprio", "joint_target"] - constant["next", "proprio", "joint_target"]).abs().max() > 1e-3
    assert REACH_STATE not in free["next"].keys(True)


def test_the_smooth_reach_map_gives_every_action_its_own_reach(tiny_dataset):
    """``reach_smooth``: w = (1 + a) / 2 — a = ±1 are the clip map's full and no reach, and the actions
    the clip map flattens (0.5 and 1 both reach fully there) reach differently."""
    smooth = ModulationConfig(reach_smooth=True)
    for a, w in ((0.5, 0.75), (1.0, 1.0), (-1.0, 0.0), (0.0, 0.5)):
        td = _rollout(tiny_dataset, "A", scripted([a], 1), steps=2, config=smooth)
        torch.testing.assert_close(td["next", REACH_STATE][..., 0], torch.full((6, 2), w))
    half = _rollout(tiny_dataset, "A", scripted([0.5], 1), config=smooth)
    full = _rollout(tiny_dataset, "A", scripted([0.5], 1))
    assert (half["next", "proprio", "joint_target"] - full["next", "proprio", "joint_target"]).abs().max() > 1e-3
    torch.testing.assert_close(_rollout(tiny_dataset, "A", scripted([1.0], 1), config=smooth)["next", "proprio",
                                                                                               "joint_target"],
                               _rollout(tiny_dataset, "A", scripted([1.0], 1))["next", "proprio", "joint_target"])


def test_the_reach_lookahead_starts_the_return_earlier_and_is_checked(tiny_dataset):
    """``reach_lookahead=4``: the full reach is the anchored feed-forward whose anchor reads the reference
    object four steps ahead — the same hand while the object rests, back on the path sooner once the
    reference carries it; a lookahead the observation does not hold is refused naming the setting."""
    import pytest

    from adadex.errors import ConfigError

    ahead = _rollout(tiny_dataset, "A", scripted([1.0], 1), steps=80, config=ModulationConfig(reach_lookahead=4))
    next_frame = _rollout(tiny_dataset, "A", scripted([1.0], 1), steps=80)     # the tiny references lift at 57–84
    assert torch.equal(ahead["next", REACH_STATE], next_frame["next", REACH_STATE])
    targets = ahead["next", "proprio", "joint_target"], next_frame["next", "proprio", "joint_target"]
    assert torch.equal(targets[0][:, :50], targets[1][:, :50])                # at rest at t+4 in the first steps
    assert (targets[0] - targets[1]).abs().max() > 1e-3                        # the return began earlier
    for bad in (3, 0, 13):
        with pytest.raises(ConfigError, match=r"ModulationConfig.reach_lookahead must be one of \(1, 2, 4, 12\)"):
            ModulationConfig(reach_lookahead=bad)


def test_a_reset_world_chooses_its_reach_again_and_the_view_shows_it(tiny_dataset):
    torch.manual_seed(0)
    mod = Modulator("A+T", hidden=(16, 16))
    env = TransformedEnv(TrackingEnv(tiny_dataset, num_worlds=3, split=None, seed=3, randomize=DISPLACED),
                         modulation("A+T", Tracker.replay().freeze(), view=mod.view))
    reach = mod.view.slices()["reach"]
    with set_exploration_type(ExplorationType.RANDOM), torch.no_grad():
        td = env.reset()
        assert td[REACH_STATE].abs().max() == 0 and td["modulator", "view"][..., reach].abs().max() == 0
        td = env.rollout(4, mod.actor, tensordict=td, auto_reset=False, break_when_any_done=False)
        first = td["action"][:, 0, 0]
        torch.testing.assert_close(td["next", REACH_STATE][..., 0], (0.5 + first).clamp(0, 1)[:, None].expand(3, 4))
        torch.testing.assert_close(td["next", "modulator", "view"][..., reach][..., 0], td["next", REACH_STATE][..., 0])
        nxt = td[:, -1]["next"].clone()
        nxt["_reset"] = torch.tensor([[True], [False], [False]])
        out = env.reset(nxt)
    assert out[REACH_STATE][0].abs().max() == 0                                  # reset: chosen again
    torch.testing.assert_close(out[REACH_STATE][1:], td["next", REACH_STATE][1:, -1])
    env.close()


def test_reach_channel_in_the_policy_graph_runs_as_in_the_env(tiny_dataset):
    mod = Modulator("C+A+T", hidden=(16, 16))
    policy = make_policy(Tracker.replay().freeze(), mod)

    a = sampled_rollout(TransformedEnv(TrackingEnv(tiny_dataset, num_worlds=2, split=None, seed=3, randomize=DISPLACED),
                                       policy.primer()), policy, 6)
    b = sampled_rollout(TransformedEnv(TrackingEnv(tiny_dataset, num_worlds=2, split=None, seed=3, randomize=DISPLACED),
                                       modulation("C+A+T", Tracker.replay().freeze(), view=mod.view)), mod.actor, 6)
    assert torch.equal(a["next", "proprio", "joint_pos"], b["next", "proprio", "joint_pos"])
    assert torch.equal(a["next", REACH_STATE], b["next", REACH_STATE])


def test_after_the_first_step_the_ignored_reach_carries_no_parameters_log_probability(tiny_dataset):
    """Where the env ignores the reach (latched), the modulator's reach entry is a fixed N(0, 1): its
    samples move neither PPO's ratio nor its gradient; at an episode's first step it is the network's."""
    torch.manual_seed(0)
    mod = Modulator("A+T", hidden=(16, 16))
    env = TransformedEnv(TrackingEnv(tiny_dataset, num_worlds=4, split=None, seed=3, randomize=DISPLACED),
                         modulation("A+T", Tracker.replay().freeze(), view=mod.view))
    with set_exploration_type(ExplorationType.RANDOM), torch.no_grad():
        td = env.rollout(5, mod.sampling_policy(), break_when_any_done=False)
    env.close()
    loc, scale = td["modulator", "loc"][..., 0], td["modulator", "scale"][..., 0]
    assert torch.equal(loc[:, 1:], torch.zeros(4, 4)) and torch.equal(scale[:, 1:], torch.ones(4, 4))
    torch.testing.assert_close(scale[:, 0], torch.full((4,), 1.0), atol=0.05, rtol=0)   # A's init_scale
    later = td[:, 1:].reshape(-1).clone()
    log_prob = mod.actor.get_dist(later).log_prob(later["action"])
    torch.testing.assert_close(log_prob.detach(), later["action_log_prob"], atol=1e-4, rtol=1e-5)
    mod.actor.get_dist(later.clone()).log_prob(later["action"]).sum().backward()
    heads = mod.actor._sampling_parts[0].heads
    assert heads[0].weight.grad.abs().max() == 0 and heads[0].bias.grad.abs().max() == 0      # A: nothing
    assert heads[1].weight.grad.abs().max() > 0                                                 # T: learns
    first = td[:, 0].clone()
    mod.zero_grad()
    mod.actor.get_dist(first).log_prob(first["action"]).sum().backward()
    assert heads[0].weight.grad.abs().max() > 0                    # the first step's reach is the network's
