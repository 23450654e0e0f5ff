"""The settings training collects with (:func:`adadex.train.collectors.local_collector`) change how
fast TorchRL moves the data, never the data."""

from __future__ import annotations

import torch
from torchrl.collectors import Collector

from adadex.envs.tracking import TrackingConfig
from adadex.modules.tracker import Tracker
from adadex.train.collectors import local_collector
from adadex.train.envs import TrackingEnvFactory

TRAJ_IDS = ("collector", "traj_ids")


def _batches(make) -> list:
    torch.manual_seed(0)
    col = make()
    try:
        return [b.clone() for b in col]
    finally:
        col.shutdown()


def test_local_collector_gathers_what_a_default_collector_gathers(tiny_dataset):
    """Same seed: every entry of a batch of :func:`local_collector` equals the default ``Collector``'s,
    episodes ending and worlds restarting in between; only the trajectory ids (unused) are left out."""
    factory = TrackingEnvFactory(str(tiny_dataset), (1, 2, 5), num_worlds=4, seed=0, nthread=1,
                                 config=TrackingConfig(window=16))
    policy = Tracker(hidden=(16,), residual=0.25, init_scale=0.5).sampling_policy()
    n = dict(frames_per_batch=4 * 16, total_frames=4 * 48)
    plain = _batches(lambda: Collector(factory, policy, auto_register_policy_transforms=False, **n))
    tuned = _batches(lambda: local_collector(factory, policy, **n))
    assert any(bool(b["next", "done"].any()) for b in plain)
    for a, b in zip(plain, tuned, strict=True):
        assert b.device == torch.device("cpu")
        assert set(a.keys(True, True)) - set(b.keys(True, True)) == {TRAJ_IDS}
        assert set(b.keys(True, True)) < set(a.keys(True, True))
        for key in b.keys(True, True):
            torch.testing.assert_close(b[key], a[key], rtol=0, atol=0, equal_nan=True, msg=str(key))
