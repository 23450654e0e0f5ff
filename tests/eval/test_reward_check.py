"""The per-episode rank correlation of the return with the metric."""

import math

import pytest
import torch
from tensordict import TensorDict

from adadex.eval.metrics import ERROR_NAMES
from adadex.eval.reward_check import episode_returns, return_metric_spearman, spearman


def _rollout(reward, t_o, done=None):
    B, T = reward.shape
    err = {k: torch.zeros(B, T, 1) for k in ERROR_NAMES}
    err["T_o"] = t_o[..., None]
    done = torch.zeros(B, T, 1, dtype=torch.bool) if done is None else done[..., None]
    return TensorDict({"next": {"done": done, "reward": reward[..., None], "privileged": {"errors": err}}},
                      batch_size=[B, T])


def test_returns_stop_at_the_first_done():
    reward = torch.ones(2, 4)
    done = torch.zeros(2, 4, dtype=torch.bool)
    done[0, 1] = True
    assert episode_returns(_rollout(reward, torch.zeros(2, 4), done)).tolist() == [2.0, 4.0]
    td = _rollout(reward, torch.zeros(2, 4))
    del td["next", "reward"]
    assert episode_returns(td) is None and return_metric_spearman(td) is None


def test_a_reward_that_ranks_as_the_metric_and_one_that_does_not():
    # object error grows at a different rate in each of 6 episodes: completion falls with the rate
    rate = torch.tensor([0.0, 0.5, 1.0, 2.0, 4.0, 8.0])
    t_o = rate[:, None] * torch.arange(10) / 20
    good = return_metric_spearman(_rollout(-t_o, t_o))
    assert good["completion"] == pytest.approx(1.0) and good["episodes"] == 6
    bad = return_metric_spearman(_rollout(t_o, t_o))        # rewards the error: ranks backwards
    assert bad["completion"] == pytest.approx(-1.0)
    # a list of rollouts (an evaluation's chunks) is one set of episodes
    split = return_metric_spearman([_rollout(-t_o[:3], t_o[:3]), _rollout(-t_o[3:], t_o[3:])])
    assert split["completion"] == pytest.approx(1.0) and split["episodes"] == 6


def test_spearman_edge_cases():
    assert spearman([1, 2, 3, 4], [10, 20, 30, 25]) == pytest.approx(0.8)
    assert math.isnan(spearman([1, 2], [1, 2]))                      # too few to rank
    assert math.isnan(spearman([1, 2, 3], [5, 5, 5]))                # a constant metric: no ranking
    assert spearman([1, 2, float("nan"), 3], [1, 2, 0, 3]) == pytest.approx(1.0)
    with pytest.raises(ValueError, match="1-D"):
        spearman([1, 2, 3], [1, 2])
