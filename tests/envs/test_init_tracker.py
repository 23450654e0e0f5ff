"""TorchRL 0.14's ``InitTracker`` FutureWarning (issue 45).

A TorchRL user's ``Collector(env, tracker.actor)`` (without ``auto_register_policy_transforms``) warns
that the env lacks the ``InitTracker`` the policy needs: TorchRL 0.14 asks every policy's env for an
``is_init`` entry in its specs, recurrent or not, and from 0.15 appends an ``InitTracker`` transform to
an env without one. The library's own collectors pass ``auto_register_policy_transforms=False``
(:mod:`adadex.train.collectors`); the fix TorchRL intends is an env that publishes ``is_init`` itself
(spec-based detection: nothing to append, nothing to warn about). ``EnvWithInit`` below is that fix,
to be moved into :class:`~adadex.envs.tracking.TrackingEnv`.
"""

from __future__ import annotations

import warnings

import pytest
import torch
from torchrl.collectors import Collector
from torchrl.data import Categorical
from torchrl.envs.utils import check_env_specs

from adadex.envs import TrackingEnv
from adadex.modules import Tracker


class EnvWithInit(TrackingEnv):
    """TrackingEnv plus what ``InitTracker`` would add: ``is_init`` (bool, ``(B, 1)``), True in the worlds
    a reset starts, False after a step."""

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self.observation_spec["is_init"] = Categorical(2, shape=(*self.batch_size, 1), dtype=torch.bool)

    def _reset(self, tensordict=None, **kwargs):
        out = super()._reset(tensordict, **kwargs)
        mask = None if tensordict is None else tensordict.get("_reset", None)
        init = (torch.ones(*self.batch_size, 1, dtype=torch.bool) if mask is None
                else mask.reshape(*self.batch_size, 1).clone())
        return out.set("is_init", init)

    def _step(self, tensordict):
        return super()._step(tensordict).set("is_init", torch.zeros(*self.batch_size, 1, dtype=torch.bool))


def _future_warnings(env) -> list[str]:
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        collector = Collector(env, Tracker().actor, frames_per_batch=4, total_frames=8)
        batches = list(collector)
        collector.shutdown()
    assert len(batches) == 2
    return [str(w.message) for w in caught if issubclass(w.category, FutureWarning)]


def test_an_env_that_publishes_is_init_needs_no_init_tracker(tiny_dataset):
    env = EnvWithInit(tiny_dataset, num_worlds=2, nthread=0)
    check_env_specs(env)
    assert _future_warnings(env) == []


@pytest.mark.xfail(strict=True, reason="issue 45: TrackingEnv does not publish is_init yet (adadex/envs/"
                                       "tracking.py; see EnvWithInit)")
def test_a_users_collector_on_tracking_env_does_not_warn(tiny_dataset):
    assert _future_warnings(TrackingEnv(tiny_dataset, num_worlds=2, nthread=0)) == []
