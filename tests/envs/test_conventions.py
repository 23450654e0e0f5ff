"""Env conventions a learner relies on: ending an episode early never pays, ground truth stays out of
what a policy observes, and the env's device is honest."""

from __future__ import annotations

import pytest
import torch
from tensordict.nn import TensorDictModule

from adadex.envs.observation import ERRORS, PRIVILEGED, REFERENCE_INDEX, REWARD_TERMS, STEP, UNSTABLE
from adadex.envs.replay import replay_policy
from adadex.envs.reward import TERM_NAMES
from adadex.envs.tracking import TrackingConfig, TrackingEnv
from adadex.errors import AdadexError


def _returns(env: TrackingEnv, policy) -> tuple[torch.Tensor, torch.Tensor]:
    """Per-world return and episode length over one window, no auto-reset (a done world stops counting)."""
    td = env.reset()
    td = env.rollout(env.config.window - 1, policy, tensordict=td, auto_reset=False, break_when_any_done=False)
    done = td["next", "done"][..., 0]
    alive = (torch.cumsum(done.int(), 1) - done.int()) == 0
    return (td["next", "reward"][..., 0] * alive).sum(1), alive.sum(1)


def _away(obs):
    """Drive the arm: shoulder and elbow up at full speed, so the palm leaves the reference."""
    a = torch.zeros(*obs.shape[:-1], 22)
    a[..., 1] = -0.1
    a[..., 2] = -0.1
    return a


def test_driving_the_palm_away_returns_less_than_replay(tiny_dataset):
    cfg = TrackingConfig()
    assert cfg.terminate_palm_error > 0 and cfg.reward.w_termination > 0      # termination on, as defaults
    env = TrackingEnv(tiny_dataset, num_worlds=3, split=None, references=[1, 2, 5], draw="cycle", config=cfg)
    replay_ret, replay_len = _returns(env, replay_policy())
    away_ret, away_len = _returns(env, TensorDictModule(_away, in_keys=["observation"], out_keys=["action"]))
    env.close()
    assert (away_len < replay_len).all(), (away_len, replay_len)               # the away policy does end early
    assert (away_ret < replay_ret).all(), (away_ret, replay_ret)


def test_eq1_alone_rewards_ending_early(tiny_dataset):
    """The control: without the shaping terms (Eq. 1 as the paper writes it) the away policy's shorter
    episodes do return more than replay — the incentive the shaping removes."""
    from adadex.envs.reward import RewardConfig

    eq1 = RewardConfig(w_alive=0, w_hand_exp=0, w_object_exp=0, w_joint_exp=0, w_termination=0)
    env = TrackingEnv(tiny_dataset, num_worlds=3, split=None, references=[1, 2, 5], draw="cycle",
                      config=TrackingConfig(reward=eq1))
    replay_ret, _ = _returns(env, replay_policy())
    away_ret, _ = _returns(env, TensorDictModule(_away, in_keys=["observation"], out_keys=["action"]))
    env.close()
    assert (away_ret > replay_ret).any(), (away_ret, replay_ret)


def test_privileged_entries_are_apart_and_complete(tiny_dataset):
    env = TrackingEnv(tiny_dataset, num_worlds=2, split=None)
    top = set(env.observation_spec.keys())
    assert "errors" not in top and "unstable" not in top and PRIVILEGED in top
    td = env.rollout(3)
    nxt = td["next"]
    assert set(nxt[ERRORS].keys()) == {"T_o", "R_o", "T_h", "R_h", "E_finger"}
    assert set(nxt[REWARD_TERMS].keys()) == set(TERM_NAMES)
    assert nxt[UNSTABLE].dtype == torch.bool
    assert nxt[STEP][:, 0].tolist() == [1, 1] and td[STEP][:, 2].tolist() == [2, 2]     # steps within the episode
    assert set(td[REFERENCE_INDEX].flatten().tolist()) <= set(env.references)
    # the terms add up to the reward the learner sees
    cfg = env.config.reward
    t = nxt[REWARD_TERMS]
    total = (-cfg.w_track * t["tracking"] + cfg.w_prox * t["proximity"] - cfg.w_goal * t["goal"]
             + cfg.w_bonus * t["bonus"] + t["shaping"] - t["termination"])
    assert torch.allclose(total, nxt["reward"][..., 0], atol=1e-5)
    env.close()


def test_a_non_cpu_device_is_refused_with_a_reason(tiny_dataset):
    with pytest.raises(AdadexError, match="rollout backend runs MuJoCo on the CPU.*backend='warp'"):
        TrackingEnv(tiny_dataset, num_worlds=2, split=None, device="cuda")
    with pytest.raises(AdadexError, match="policy_device"):
        TrackingEnv(tiny_dataset, num_worlds=2, split=None, device="meta")
