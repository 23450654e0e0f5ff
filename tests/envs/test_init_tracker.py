"""TorchRL 0.14's ``InitTracker`` FutureWarning (issue 45).

A TorchRL user's ``Collector(env, tracker.actor)`` (without ``auto_register_policy_transforms``) warned
that the env lacks the ``InitTracker`` the policy needs: TorchRL 0.14 asks every policy's env for an
``is_init`` entry in its specs, recurrent or not, and from 0.15 appends an ``InitTracker`` transform to
an env without one. :class:`~adadex.envs.tracking.TrackingEnv` publishes ``is_init`` itself (True in the
worlds a reset starts, False after a step): nothing to append, nothing to warn about.
"""

from __future__ import annotations

import warnings

import torch
from torchrl.collectors import Collector
from torchrl.envs.utils import check_env_specs

from adadex.envs import TrackingEnv
from adadex.modules import Tracker


def _future_warnings(env) -> list[str]:
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        collector = Collector(env, Tracker().actor, frames_per_batch=4, total_frames=8)
        batches = list(collector)
        collector.shutdown()
    assert len(batches) == 2
    return [str(w.message) for w in caught if issubclass(w.category, FutureWarning)]


def test_a_users_collector_on_tracking_env_does_not_warn(tiny_dataset):
    env = TrackingEnv(tiny_dataset, num_worlds=2, nthread=0)
    check_env_specs(env)
    assert _future_warnings(env) == []


def test_is_init_marks_the_worlds_a_reset_starts(tiny_dataset):
    env = TrackingEnv(tiny_dataset, num_worlds=3, nthread=0)
    td = env.reset()
    assert td["is_init"].all()
    td = env.step(td.set("action", torch.zeros(3, 22)))["next"]
    assert not td["is_init"].any()
    td = env.reset(td.set("_reset", torch.tensor([[False], [True], [False]])))
    assert td["is_init"].squeeze(-1).tolist() == [False, True, False]
