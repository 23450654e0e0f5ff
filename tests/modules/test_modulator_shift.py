"""The modulator's action shifts (adadex.modules.modulator.ActionShift): with ``prior="anchor"`` the
untrained modulator around replay *is* the anchored feed-forward; with ``hold_steps`` the chosen
channels' exploration noise is held for k steps while sampling and is zero deterministically, and
PPO's loss scores each collected action under exactly the distribution it was sampled from."""

import dataclasses

import pytest
import torch
from torchrl.envs import TransformedEnv
from torchrl.envs.utils import ExplorationType, set_exploration_type

from adadex.envs.observation import REF_OBJECT_START
from adadex.envs.randomization import Randomization
from adadex.envs.tracking import TrackingEnv
from adadex.errors import ConfigError
from adadex.modules.modulator import Modulator
from adadex.modules.modulator_view import STEPS
from adadex.modules.nets import stored_bounds_actor
from adadex.modules.tracker import Tracker
from adadex.transforms.modulation import modulation
from adadex.transforms.policy import make_policy

DISPLACED = dataclasses.replace(Randomization.off(), object_xy_std=0.05)


def _rollout(dataset, policy, primer=None, steps=20, mode=ExplorationType.DETERMINISTIC, seed=3):
    env = TrackingEnv(dataset, num_worlds=6, split=None, seed=seed, randomize=DISPLACED)
    if primer is not None:
        env = TransformedEnv(env, primer)
    with set_exploration_type(mode), torch.no_grad():
        td = env.rollout(steps, policy, break_when_any_done=False)
    env.close()
    return td


def test_untrained_anchor_prior_around_replay_is_the_anchored_feed_forward(tiny_dataset, tmp_path):
    anchored = Tracker(hidden=(16,), residual=0.25, anchor=0.05).zero_mean()
    mod = Modulator("C+T", hidden=(16, 16), prior="anchor").zero_mean()
    policy = make_policy(Tracker.replay(), mod)
    a = _rollout(tiny_dataset, anchored.actor)
    b = _rollout(tiny_dataset, policy, policy.primer())
    torch.testing.assert_close(b["action"], a["action"], atol=1e-5, rtol=0)
    torch.testing.assert_close(b["next", "proprio", "joint_target"], a["next", "proprio", "joint_target"],
                               atol=1e-5, rtol=0)
    palm = b["modulation", "sample"][..., :3]
    assert palm.abs().max() > 0.1 and (palm[..., 2] == 0).all()     # it reached, horizontally
    plain = _rollout(tiny_dataset, Tracker.replay().actor)
    assert (plain["action"] - a["action"]).abs().max() > 0.01          # the anchor moved the hand
    # the untrained modulator as built (heads near zero, not zeroed; its T residual acts by up to
    # ~0.005 rad on unnormalized views): near the same, far from plain replay
    loaded = Modulator.load(mod.save(tmp_path / "m.pt"))
    assert loaded.config["prior"] == "anchor" and set(loaded.actor.in_keys) >= {REF_OBJECT_START}
    fresh = make_policy(Tracker.replay(), Modulator("C+T", hidden=(16, 16), prior="anchor"))
    c = _rollout(tiny_dataset, fresh, fresh.primer(), steps=5)
    torch.testing.assert_close(c["action"], a["action"][:, :5], atol=1e-2, rtol=0)


def _prior_as_feed_forward(dataset, steps, **anchor):
    """The untrained C prior with the anchor setting ``anchor`` (``anchor_lookahead`` / ``anchor_reach``, as
    ``prior_lookahead`` / ``prior_reach``) around replay, checked equal to ``Tracker(anchor=0.05, **anchor)``'s
    feed-forward; returns (the modulator, its rollout, the rollout of the prior without the setting)."""
    tracker = Tracker(hidden=(16,), residual=0.25, anchor=0.05, **anchor).zero_mean()
    mod = Modulator("C", hidden=(16, 16), prior="anchor",
                    **{k.replace("anchor_", "prior_"): v for k, v in anchor.items()}).zero_mean()
    policy = make_policy(Tracker.replay(), mod)
    a = _rollout(dataset, tracker.actor, steps=steps)
    b = _rollout(dataset, policy, policy.primer(), steps=steps)
    torch.testing.assert_close(b["action"], a["action"], atol=1e-5, rtol=0)
    plain = make_policy(Tracker.replay(), Modulator("C", hidden=(16, 16), prior="anchor").zero_mean())
    return mod, b, _rollout(dataset, plain, plain.primer(), steps=steps)


def test_anchor_prior_reads_the_reference_as_far_ahead_as_told(tiny_dataset, tmp_path):
    """prior_lookahead=4: the untrained prior around replay is the anchored feed-forward reading t+4
    (``Tracker(anchor_lookahead=4)``), which starts bringing the object back earlier than at t+1."""
    mod, b, c = _prior_as_feed_forward(tiny_dataset, 120, anchor_lookahead=4)
    assert (c["action"] - b["action"]).abs().max() > 1e-3                  # the timing changed the hand
    loaded = Modulator.load(mod.save(tmp_path / "m.pt"))
    assert loaded.config["prior_lookahead"] == 4
    assert "prior_lookahead" not in Modulator("C", hidden=(16,), prior="anchor").config
    with pytest.raises(ConfigError, match=r"prior_lookahead must be one of .*\(1, 2, 4, 12\), got 3"):
        Modulator("C", hidden=(16,), prior="anchor", prior_lookahead=3)


def test_anchor_prior_with_a_reach_leaves_far_objects_where_they_lie(tiny_dataset, tmp_path):
    """prior_reach=M: the untrained prior around replay is ``Tracker(anchor_reach=M)``'s feed-forward —
    worlds whose object lies M or farther off keep replay's palm, the others reach as without the limit."""
    reach = 0.06
    mod, b, c = _prior_as_feed_forward(tiny_dataset, 8, anchor_reach=reach)
    offset = (b["object", "start_pose"][:, 0, :2] - b["object", "reference_start"][:, 0, :2]).norm(dim=-1)
    far, palm = offset >= reach, b["modulation", "sample"][..., :3].abs().amax(dim=(-2, -1))
    assert far.any() and (~far).any()                                  # both kinds among the worlds
    assert (palm[far] == 0).all() and (palm[~far] > 0).all()
    moved = (c["action"] - b["action"]).abs().amax(dim=(-2, -1))
    assert (moved[far] > 1e-3).all() and (moved[~far] < 1e-5).all()   # only the far worlds differ
    assert Modulator.load(mod.save(tmp_path / "m.pt")).config["prior_reach"] == reach
    assert "prior_reach" not in Modulator("C", hidden=(16,), prior="anchor").config
    with pytest.raises(ConfigError, match=r"prior_reach=0.1\) limits the anchor prior, which is off"):
        Modulator("C", hidden=(16,), prior_reach=0.1)


def test_anchor_prior_follows_objects_past_lambda_palm_and_its_own_lambda(tiny_dataset):
    """The prior is in C's units: with λ_palm halved the palm action doubles (past 1: C's palm entry
    takes ±2) and the joints stay the anchored feed-forward's."""
    from adadex.modules.channels import ModulationConfig

    anchored = Tracker(hidden=(16,), residual=0.25, anchor=0.05).zero_mean()
    a = _rollout(tiny_dataset, anchored.actor, steps=6)
    mod = Modulator("C", hidden=(16, 16), prior="anchor", lambda_palm=0.05).zero_mean()
    policy = make_policy(Tracker.replay(), mod, config=ModulationConfig(lambda_palm=0.05))
    b = _rollout(tiny_dataset, policy, policy.primer(), steps=6)
    assert b["modulation", "sample"][..., :3].abs().max() > 1.0
    torch.testing.assert_close(b["action"], a["action"], atol=1e-5, rtol=0)


def test_held_noise_is_held_for_k_steps_while_sampling_and_off_deterministically(tiny_dataset):
    k = 4
    mod = Modulator("C+T", hidden=(16, 16), hold_steps=k, hold_scale={"C": 0.5})
    shift = mod.actor._sampling_parts[1]
    env = TransformedEnv(TrackingEnv(tiny_dataset, num_worlds=3, split=None, seed=3),
                         modulation("C+T", Tracker.replay(), view=mod.view))

    def collect(seed, mode=ExplorationType.RANDOM):
        env.set_seed(7)
        torch.manual_seed(seed)
        shift.module._held = None
        with set_exploration_type(mode), torch.no_grad():
            return env.rollout(11, mod.sampling_policy(), break_when_any_done=False)

    td = collect(0)
    centre = (td["modulator", "low"] + td["modulator", "high"]) / 2
    steps = td[STEPS][..., 0].long()
    assert (centre[..., 7:] == 0).all()                          # T holds no noise
    c = centre[..., :7]
    for t in range(1, 11):
        same = (c[:, t] == c[:, t - 1]).all(-1)
        assert bool((same == (steps[:, t] % k != 0)).all()), t     # redrawn exactly at steps 0, k, 2k …
    assert 0.2 < c.std() < 1.0                                    # scale 0.5
    assert torch.equal(collect(0)["modulator", "low"], td["modulator", "low"])     # seeded
    assert not torch.equal(collect(1)["modulator", "low"], td["modulator", "low"])
    det = collect(0, ExplorationType.DETERMINISTIC)
    assert ((det["modulator", "low"] + det["modulator", "high"]) == 0).all()       # evaluation: no held noise
    env.close()


def test_ppo_scores_held_and_anchored_actions_under_the_distribution_they_were_sampled_from(tiny_dataset):
    """The loss's actor reads the collected bounds: at the collecting parameters its log-probability
    of every collected action is the one the collector wrote (ratio 1). Recomputing the bounds
    instead (the held noise drawn again) would not give it."""
    mod = Modulator("C+T", hidden=(16, 16), prior="anchor", hold_steps=5, hold_scale={"C": 0.5})
    env = TransformedEnv(TrackingEnv(tiny_dataset, num_worlds=4, split=None, seed=3, randomize=DISPLACED),
                         modulation("C+T", Tracker.replay(), view=mod.view))
    torch.manual_seed(0)
    with set_exploration_type(ExplorationType.RANDOM), torch.no_grad():
        td = env.rollout(12, mod.sampling_policy(), break_when_any_done=False).reshape(-1)
    env.close()
    reading = stored_bounds_actor(mod.actor)
    assert ("modulator", "low") in reading.in_keys and REF_OBJECT_START not in reading.in_keys
    with torch.no_grad():
        log_prob = reading.get_dist(td.clone()).log_prob(td["action"])
        torch.testing.assert_close(log_prob, td["action_log_prob"], atol=1e-4, rtol=1e-5)
        with set_exploration_type(ExplorationType.RANDOM):
            redrawn = mod.actor.get_dist(td.clone()).log_prob(td["action"])
    assert (redrawn - td["action_log_prob"]).abs().max() > 1.0


def test_shift_settings_are_checked_and_old_configs_unchanged(tmp_path):
    with pytest.raises(ConfigError, match="lacks"):
        Modulator("R+T", hidden=(16,), prior="anchor")
    with pytest.raises(ConfigError, match="prior must be one of"):
        Modulator("C", hidden=(16,), prior="object")
    with pytest.raises(ConfigError, match="go together"):
        Modulator("C", hidden=(16,), hold_steps=5)
    with pytest.raises(ConfigError, match="go together"):
        Modulator("C", hidden=(16,), hold_scale=0.5)
    with pytest.raises(ConfigError, match="neither channels"):
        Modulator("C", hidden=(16,), hold_steps=5, hold_scale={"T": 0.5})
    with pytest.raises(ConfigError, match="inputs='view'"):
        Modulator("C", hidden=(16,), prior="anchor", inputs="observation")
    plain = Modulator("C+T", hidden=(16,))
    assert "prior" not in plain.config and plain.actor._sampling_parts[1] is None
    held = Modulator.load(Modulator("C+T", hidden=(16,), hold_steps=3, hold_scale=0.2).save(tmp_path / "h.pt"))
    assert held.config["hold_steps"] == 3 and held.config["hold_scale"] == {"C": 0.2, "T": 0.2}
    palm = Modulator("C+T", hidden=(16,), hold_steps=3, hold_scale={"palm": 0.3, "C": 0.1})
    scale = palm.actor._sampling_parts[1].module._hold_scale          # an entry's own before its channel's
    torch.testing.assert_close(scale[:7], torch.tensor([0.3] * 3 + [0.1] * 4))
    assert (scale[7:] == 0).all()
