"""The collector for a run: TorchRL's, chosen by :class:`~adadex.train.config.CollectorConfig`.

* ``backend="local"``, 1 worker — :class:`torchrl.collectors.Collector`: the batched env steps in
  this process (MuJoCo's own threads do the parallel physics).
* ``backend="local"``, N workers — :class:`torchrl.collectors.MultiSyncCollector`: N processes,
  each with its own batched env and seed; their batches are stacked.
* ``backend="ray"`` — :class:`torchrl.collectors.distributed.RayCollector`: N remote collectors on
  a Ray cluster (started locally unless ``ray_address`` names one), one CPU each.

Every worker gets its own env factory (:meth:`TrackingEnvFactory.for_workers`): distinct seeds,
so distinct reference draws and randomizations; the factories carry the scenes compiled once in
this process (:meth:`TrackingEnvFactory.with_scenes`), so a worker's start-up is its imports. Weights go to the workers with the collector's
``update_policy_weights_()`` after each update.
"""

from __future__ import annotations

from torchrl.collectors import Collector, MultiSyncCollector

from adadex.errors import ConfigError
from adadex.train.config import CollectorConfig
from adadex.train.envs import TrackingEnvFactory


def make_collector(factory: TrackingEnvFactory, policy, cfg: CollectorConfig, *, frames_per_batch: int,
                   total_frames: int):
    """A TorchRL collector of ``frames_per_batch`` frames per batch (all workers together)."""
    per_step = factory.num_worlds * cfg.workers
    if frames_per_batch % per_step:
        raise ConfigError(f"frames_per_batch={frames_per_batch} must be a multiple of worlds × workers = {per_step} "
                          f"(one env step of every world)")
    total = -(-total_frames // frames_per_batch) * frames_per_batch    # whole batches
    if cfg.backend == "ray":
        return _ray_collector(factory.with_scenes(), policy, cfg, frames_per_batch, total)
    if cfg.workers == 1:
        return Collector(factory, policy, frames_per_batch=frames_per_batch, total_frames=total,
                         auto_register_policy_transforms=False)
    return MultiSyncCollector(factory.with_scenes().for_workers(cfg.workers), policy,
                              frames_per_batch=frames_per_batch, total_frames=total, cat_results="stack",
                              auto_register_policy_transforms=False)


def _ray_collector(factory, policy, cfg: CollectorConfig, frames_per_batch: int, total: int):
    try:
        import ray  # noqa: F401
        from torchrl.collectors.distributed import RayCollector
    except ImportError as e:
        raise ConfigError("collector.backend=ray needs Ray: pip install -e '.[ray]'") from e
    init = {"address": cfg.ray_address} if cfg.ray_address else {"num_cpus": max(2, cfg.workers),
                                                                   "include_dashboard": False}
    return RayCollector(factory.for_workers(cfg.workers), policy, frames_per_batch=frames_per_batch,
                        total_frames=total, collector_class=Collector, sync=True, ray_init_config=init,
                        collector_kwargs={"auto_register_policy_transforms": False},
                        remote_configs={"num_cpus": 1, "num_gpus": 0, "memory": 2 * 1024 ** 3})
