"""The collectors' sampling path (:class:`adadex.modules.nets.SamplingPolicy`) is the actor's distribution."""

import copy

import pytest
import torch
from tensordict import TensorDict
from torchrl.envs.utils import ExplorationType, set_exploration_type

from adadex.modules.modulator import Modulator
from adadex.modules.nets import SamplingPolicy
from adadex.modules.tracker import Tracker


def _obs(n=256, seed=0):
    g = torch.Generator().manual_seed(seed)
    return TensorDict({"observation": torch.randn(n, 273, generator=g),
                       ("proprio", "joint_target"): 0.3 * torch.randn(n, 22, generator=g)}, batch_size=[n])


@pytest.mark.parametrize("make", [lambda: Tracker(hidden=(32, 32), residual=0.25, init_scale=0.5),
                                  lambda: Tracker(hidden=(32, 32), residual=0.25, init_scale=0.5, loc_bound=5.0),
                                  lambda: Tracker(hidden=(32, 32)),
                                  lambda: Modulator("R+O+T", hidden=(32, 32), inputs="observation"),
                                  lambda: Modulator("R+O+T", hidden=(32, 32), loc_bound=2.0, inputs="observation")],
                         ids=["residual tracker", "bounded mean", "plain tracker", "modulator", "bounded modulator"])
def test_samples_what_the_actor_samples_with_the_losss_log_prob(make):
    policy = make()
    fast = policy.sampling_policy()
    with set_exploration_type(ExplorationType.RANDOM), torch.no_grad():
        torch.manual_seed(3)
        ref = policy.actor(_obs())
        torch.manual_seed(3)
        out = fast(_obs())
        assert set(out.keys(True, True)) == set(ref.keys(True, True))
        for key in ref.keys(True, True):
            if key != "action_log_prob":
                torch.testing.assert_close(out[key], ref[key], rtol=0, atol=0)
        # the log-prob PPO's ratio starts from: the loss rebuilds the distribution from the observation
        fresh = policy.actor.get_dist(out).log_prob(out["action"])
        torch.testing.assert_close(out["action_log_prob"], fresh, rtol=0, atol=1e-6)
        torch.testing.assert_close(out["action_log_prob"], ref["action_log_prob"], rtol=1e-4, atol=1e-3)
        assert out["action"].std() > 0                                      # it does sample


def test_other_exploration_types_run_the_actor():
    tracker = Tracker(hidden=(32, 32), residual=0.25)
    fast = tracker.sampling_policy()
    with torch.no_grad():
        a, b = tracker.actor(_obs())["action"], fast(_obs())["action"]
        torch.testing.assert_close(a, b, rtol=0, atol=0)
        torch.testing.assert_close(fast(_obs())["action"], b, rtol=0, atol=0)     # deterministic


def test_weight_updates_reach_the_sampling_path_also_in_a_copy():
    tracker = Tracker(hidden=(32, 32))
    fast = tracker.sampling_policy()
    worker = copy.deepcopy(fast)                  # what a collector worker holds
    with set_exploration_type(ExplorationType.RANDOM), torch.no_grad():
        before = worker(_obs())[("tracker", "loc")].clone()
        for p in tracker.parameters():
            p.add_(0.05)
        torch.manual_seed(0)
        here = fast(_obs())
        assert not torch.allclose(here[("tracker", "loc")], before)
        fast_weights = dict(fast.named_parameters())
        for name, p in worker.named_parameters():           # a collector's weight sync, by name
            p.copy_(fast_weights[name])
        torch.manual_seed(0)
        there = worker(_obs())
        torch.testing.assert_close(there["action"], here["action"], rtol=0, atol=0)


def test_an_actor_not_built_by_make_actor_is_refused():
    with pytest.raises(TypeError, match="make_actor"):
        SamplingPolicy(torch.nn.Linear(2, 2))


def _push_mean(policy, shift: float):
    """Move every head's pre-tanh mean by ``shift`` (the loc half of the last layer's bias)."""
    net = policy.actor._sampling_parts[0]
    with torch.no_grad():
        for h in net.heads:
            h.bias[: h.out_features // 2] += shift


@pytest.mark.parametrize("loc_bound", [0.0, 5.0])
def test_a_bounded_mean_keeps_log_probs_of_saturated_actions_stable(loc_bound):
    """The failure loc_bound prevents: a mean far past the bounds with a small scale puts actions on the
    bound in float32, and a small weight change then moves their log-probability by tens of nats."""
    policy = Tracker(hidden=(32, 32), residual=0.25, init_scale=0.05, loc_bound=loc_bound)
    _push_mean(policy, 9.0)
    fast = policy.sampling_policy()
    with set_exploration_type(ExplorationType.RANDOM), torch.no_grad():
        torch.manual_seed(0)
        out = fast(_obs())
        _push_mean(policy, -0.05)                                   # one small update's worth
        moved = (policy.actor.get_dist(out).log_prob(out["action"]) - out["action_log_prob"]).abs().max()
    if loc_bound:
        assert moved < 5.0, moved
    else:
        assert moved > 20.0, moved            # the unbounded case this guards against, reproduced
