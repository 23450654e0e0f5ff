"""Does the reward rank episodes as the metric does? Per-episode Spearman correlation of the return with
completion (and object completion).

The reward is what training climbs; completion is what the tables report. If a change that raises
completion does not raise the return, training can not find it. :func:`return_metric_spearman`
measures the agreement on one evaluation: over its episodes, the Spearman rank correlation between
each episode's return (the sum of its rewards up to and including its first ``done``) and its
completion / object completion. It only reports; it changes no reward.

Example
-------
>>> import torch
>>> from tensordict import TensorDict
>>> from adadex.eval.metrics import ERROR_NAMES
>>> B, T = 4, 5
>>> err = {k: torch.zeros(B, T, 1) for k in ERROR_NAMES}
>>> err["T_o"][:, :, 0] = torch.tensor([0.0, 1.0, 2.0, 4.0])[:, None] * torch.arange(T) / 10
>>> reward = -err["T_o"]                        # the further off, the lower the return
>>> td = TensorDict({"next": {"done": torch.zeros(B, T, 1, dtype=torch.bool), "reward": reward,
...                          "privileged": {"errors": err}}}, batch_size=[B, T])
>>> rho = return_metric_spearman(td)
>>> round(rho["completion"], 3), rho["episodes"]
(1.0, 4)
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Sequence

import numpy as np
import torch

from adadex.errors import ArrayError
from adadex.eval.metrics import from_rollout

#: metrics the return is correlated with (keys of :func:`adadex.eval.metrics.trajectory_metrics`)
METRICS = ("completion", "object_completion")


def episode_returns(td, reward_key=("next", "reward")) -> torch.Tensor | None:
    """(N,) float64 return of each trajectory of a rollout of batch shape ``[..., T]`` (rows as
    :func:`~adadex.eval.metrics.from_rollout` orders them): its rewards summed up to and including
    its first ``("next", "done")``. ``None`` when the rollout holds no rewards."""
    if td.batch_dims < 2:
        raise ArrayError(f"expected a rollout of batch shape [..., T] with time last, got {list(td.batch_size)}")
    if reward_key not in td.keys(include_nested=True):
        return None
    if td.batch_dims > 2:
        td = td.reshape(-1, td.batch_size[-1])
    reward = td.get(reward_key).reshape(td.batch_size).to(torch.float64)
    done = td.get(("next", "done")).reshape(td.batch_size).to(torch.bool)
    after_done = torch.cumsum(done.int(), dim=1) - done.int() > 0
    return torch.where(after_done, 0.0, reward).sum(1)


def spearman(x, y) -> float:
    """Spearman's ρ of two equally long sequences (average ranks for ties); NaN for fewer than three
    pairs or a constant sequence (no ranking to compare). Pairs with a NaN are left out."""
    from scipy import stats

    x, y = np.asarray(x, dtype=np.float64), np.asarray(y, dtype=np.float64)
    if x.shape != y.shape or x.ndim != 1:
        raise ArrayError(f"spearman: expected two 1-D sequences of one length, got {x.shape} and {y.shape}")
    keep = np.isfinite(x) & np.isfinite(y)
    x, y = x[keep], y[keep]
    if len(x) < 3 or np.all(x == x[0]) or np.all(y == y[0]):
        return math.nan
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return float(stats.spearmanr(x, y).statistic)


def spearman_by_episode(returns, per_episode: dict, metrics: Sequence[str] = METRICS) -> dict:
    """``{metric: ρ(return, metric)}`` over episodes, plus ``"episodes"``: how many were ranked."""
    r = np.asarray(returns, dtype=np.float64)
    out = {m: spearman(r, np.asarray(per_episode[m], dtype=np.float64)) for m in metrics if m in per_episode}
    return out | {"episodes": int(np.isfinite(r).sum())}


def return_metric_spearman(rollouts, per_traj: dict | None = None, *, metrics: Sequence[str] = METRICS,
                           **from_rollout_kwargs) -> dict | None:
    """Per-episode Spearman ρ between the return and each of ``metrics``, over the episodes of one
    rollout or a list of rollouts (one per chunk of an evaluation), as ``{metric: ρ, "episodes": n}``.

    Args:
        rollouts: a rollout TensorDict or a list of them, holding ``("next", "reward")``.
        per_traj: the rollouts' :func:`~adadex.eval.metrics.from_rollout` results (concatenated in
            the same order) when already computed; otherwise computed here with ``from_rollout_kwargs``.
        metrics: the per-trajectory metrics to correlate (default ``("completion", "object_completion")``).
        **from_rollout_kwargs: passed to :func:`~adadex.eval.metrics.from_rollout`.

    Returns ``None`` when a rollout holds no rewards.
    """
    rollouts = [rollouts] if not isinstance(rollouts, (list, tuple)) else list(rollouts)
    returns = [episode_returns(td) for td in rollouts]
    if any(r is None for r in returns):
        return None
    if per_traj is None:
        parts = [from_rollout(td, **from_rollout_kwargs) for td in rollouts]
        per_traj = {m: torch.cat([p[m] for p in parts]) for m in metrics if m in parts[0]}
    return spearman_by_episode(torch.cat(returns).numpy(), {m: per_traj[m].double().numpy()
                                                            for m in metrics if m in per_traj}, metrics)
