"""The collector for a run: TorchRL's, chosen by :class:`~adadex.train.config.CollectorConfig`.

* ``backend="local"``, 1 worker — :class:`torchrl.collectors.Collector` (:func:`local_collector`):
  the batched env steps in this process (MuJoCo's own threads do the parallel physics).
* ``backend="local"``, N workers — :class:`torchrl.collectors.MultiSyncCollector`: N processes,
  each with its own batched env and seed; their batches are stacked.
* ``backend="ray"`` — :class:`torchrl.collectors.distributed.RayCollector`: N remote collectors on
  a Ray cluster (started locally unless ``ray_address`` names one, and kept for the process's
  later collectors: :func:`connect_ray`), one CPU each.

Every worker gets its own env factory (:meth:`TrackingEnvFactory.for_workers`): distinct seeds,
so distinct reference draws and randomizations; the factories carry the scenes compiled once in
this process (:meth:`TrackingEnvFactory.with_scenes`), so a worker's start-up is its imports. Local
workers start from a fork server by default (:func:`start_worker_server`): it imports torch, TorchRL,
MuJoCo and the env once, and every worker is forked from it with those imports done. Weights go to
the workers with the collector's ``update_policy_weights_()`` after each update. Every collector is
told where the policy, the env and the batches live (:func:`collector_devices`), so TorchRL moves
no data between steps.
"""

from __future__ import annotations

import multiprocessing
from datetime import timedelta
from multiprocessing import forkserver

import torch
from torchrl.collectors import Collector, MultiSyncCollector

from adadex.errors import ConfigError
from adadex.train.config import START_METHODS, CollectorConfig
from adadex.train.envs import TrackingEnvFactory


#: what a local worker imports before it builds its env; the fork server imports them once
WORKER_PRELOAD = ("torch", "tensordict", "torchrl.collectors", "torchrl.envs", "mujoco", "adadex.train.envs")


#: how long the driver waits for its Ray workers to join TorchRL's weight-sync process group (and, after
#: that, for a weight transfer). TorchRL's own 60 s (``torchrl.weight_update._ray._DIST_TIMEOUT``, read
#: when the group is made) also covers starting the Ray worker process of its rendezvous actor, which
#: imports torch and TorchRL: on 2 cores under 3 × load that took over 60 s and the first weight sync
#: failed (``DistStoreError: wait timeout after 60000ms``).
RAY_SYNC_TIMEOUT = timedelta(minutes=10)


def start_worker_server(method: str = "forkserver") -> None:
    """Make local worker processes start with ``method`` (``CollectorConfig.start_method``).

    TorchRL's collectors start workers with the process-wide ``multiprocessing`` start method, which
    importing TorchRL sets to ``spawn``: each worker is a new interpreter that imports torch, TorchRL
    and MuJoCo again (about 4 s of CPU each, measured; two at once on 2 cores took 7.5 s to their
    first batch). ``forkserver`` sets the start method to a fork server that imports
    :data:`WORKER_PRELOAD` once, started here and now, so it imports while this process goes on
    (compiling the scenes the workers get); every worker is then a fork of it. Workers are still
    handed their env factory by pickle, as with ``spawn``. The start method is process-wide: call
    this before creating a multi-process collector, as :func:`make_collector` does.
    """
    if method not in START_METHODS:
        raise ConfigError(f"worker start method must be one of {START_METHODS}, got {method!r}")
    if method == "forkserver" and method not in multiprocessing.get_all_start_methods():
        method = "spawn"                                          # a platform without fork (Windows)
    if multiprocessing.get_start_method(allow_none=True) != method:
        multiprocessing.set_start_method(method, force=True)
    if method == "forkserver":
        multiprocessing.set_forkserver_preload(list(WORKER_PRELOAD))
        forkserver.ensure_running()


def collector_devices(policy, env_device="cpu") -> dict:
    """``policy_device``, ``env_device`` and ``storing_device`` for a TorchRL collector: the policy's
    own device for the policy, the env's (the CPU where :class:`~adadex.envs.tracking.TrackingEnv`
    runs on the rollout backend; the GPU of the warp backend: :attr:`TrackingEnvFactory.device
    <adadex.train.envs.TrackingEnvFactory.device>`) for the env and the batches, so a GPU env's
    batches never leave the GPU.

    Left unset, TorchRL's ``Collector`` takes the policy's device for unknown: it strips the device
    from the tensordict it carries from step to step (every entry, twice per step) and, before each
    env step, rebuilds that tensordict to move it "to" the env's device — a copy of every entry that
    moves nothing. Named and equal, nothing is cast; the batches hold the same data, their
    ``device`` the CPU instead of ``None``.
    """
    param = next(iter(policy.parameters()), None) if isinstance(policy, torch.nn.Module) else None
    env = torch.device(env_device)
    return {"policy_device": env if param is None else param.device, "env_device": env, "storing_device": env}


def local_collector(create_env_fn, policy, *, frames_per_batch: int, total_frames: int) -> Collector:
    """TorchRL's ``Collector`` stepping the env of ``create_env_fn`` in this process, as training runs it.

    Besides :func:`collector_devices`, it keeps no trajectory ids (``track_traj_ids=False``): nothing
    here reads ``("collector", "traj_ids")`` (GAE reads the done flags, PPO's buffer samples steps),
    and keeping them costs TorchRL an update of every world's id and a copy of the entry at each step.
    The batches are otherwise the default ``Collector``'s, entry for entry (tested). Together the two
    settings take about 0.3 ms off each step of 64 worlds (measured, paired batches), 2 % of a step.
    The policy is not given the env's transforms (``auto_register_policy_transforms=False``): the
    policies here read the env's entries as they are.

    Args:
        create_env_fn: a zero-argument env factory (e.g. a :class:`TrackingEnvFactory`); its
            ``device`` attribute, if any, is the env's device (default CPU).
        policy: the policy the collector runs.
        frames_per_batch: frames per batch.
        total_frames: frames to collect.
    """
    return Collector(create_env_fn, policy, frames_per_batch=frames_per_batch, total_frames=total_frames,
                     track_traj_ids=False, auto_register_policy_transforms=False,
                     **collector_devices(policy, getattr(create_env_fn, "device", "cpu")))


def make_collector(factory: TrackingEnvFactory, policy, cfg: CollectorConfig, *, frames_per_batch: int,
                   total_frames: int):
    """A TorchRL collector of ``frames_per_batch`` frames per batch (all workers together).

    One worker: :func:`local_collector`; several: a ``MultiSyncCollector`` of worker processes (or
    Ray actors with ``cfg.backend == "ray"``), the factory carrying its compiled scenes.

    Args:
        factory: the env factory (one worker's; :meth:`~TrackingEnvFactory.for_workers` seeds the rest).
        policy: the policy the collector runs.
        cfg: the collector settings (``workers``, ``backend``, ``start_method``).
        frames_per_batch: frames per batch; a multiple of ``num_worlds × workers`` (else
            :class:`~adadex.errors.ConfigError`).
        total_frames: frames to collect, rounded up to whole batches.
    """
    per_step = factory.num_worlds * cfg.workers
    if frames_per_batch % per_step:
        raise ConfigError(f"frames_per_batch={frames_per_batch} must be a multiple of worlds × workers = {per_step} "
                          f"(one env step of every world)")
    total = -(-total_frames // frames_per_batch) * frames_per_batch    # whole batches
    if cfg.backend == "ray":
        return _ray_collector(factory.with_scenes(), policy, cfg, frames_per_batch, total)
    if cfg.workers == 1:
        return local_collector(factory, policy, frames_per_batch=frames_per_batch, total_frames=total)
    start_worker_server(cfg.start_method)
    return MultiSyncCollector(factory.with_scenes().for_workers(cfg.workers), policy,
                              frames_per_batch=frames_per_batch, total_frames=total, cat_results="stack",
                              auto_register_policy_transforms=False, **collector_devices(policy, factory.device))


def connect_ray(cfg: CollectorConfig) -> None:
    """Join the Ray cluster at ``cfg.ray_address``, or start a local one, once per process.

    TorchRL's ``RayCollector`` shuts down a Ray runtime it started itself when the collector is shut
    down, so every collector after the first would start a local cluster again (3.3 s of its start-up
    here, measured). Started here instead, the cluster lives until this process exits (Ray shuts it
    down then) and every collector joins it. A running cluster with fewer CPUs than ``cfg.workers``
    is refused: its actors would wait for CPUs forever.
    """
    import ray

    if not ray.is_initialized():
        if cfg.ray_address:
            ray.init(address=cfg.ray_address)
        else:
            ray.init(num_cpus=max(2, cfg.workers), include_dashboard=False)
    cpus = ray.cluster_resources().get("CPU", 0)
    if cpus < cfg.workers:
        raise ConfigError(f"collector.workers={cfg.workers} needs {cfg.workers} CPUs, but the Ray cluster "
                          f"this process is connected to has {cpus:g}; ray.shutdown() first to start a larger "
                          f"local one, or set collector.ray_address to a larger cluster")


class RayWorkerCollector(Collector):
    """TorchRL's :class:`~torchrl.collectors.Collector` as a Ray actor, with a one-line ``repr``.

    Ray names an actor's log lines after its ``repr``, which the worker writes to its log when the
    actor starts; the ``Collector``'s spans the env, the whole policy and a tensordict, and every
    line past the first reached the driver's console as a log line of its own (about 80 per worker).
    """

    def __repr__(self) -> str:
        return f"{type(self).__name__}(frames_per_batch={getattr(self, 'frames_per_batch', '?')})"


def _ray_collector(factory, policy, cfg: CollectorConfig, frames_per_batch: int, total: int):
    try:
        import ray  # noqa: F401
        from torchrl.collectors.distributed import RayCollector
    except ImportError as e:
        raise ConfigError("collector.backend=ray needs Ray: pip install -e '.[ray]'") from e
    import torchrl.weight_update._ray as ray_sync

    connect_ray(cfg)
    ray_sync._DIST_TIMEOUT = max(ray_sync._DIST_TIMEOUT, RAY_SYNC_TIMEOUT)
    return RayCollector(factory.for_workers(cfg.workers), policy, frames_per_batch=frames_per_batch,
                        total_frames=total, collector_class=RayWorkerCollector, sync=True,
                        collector_kwargs={"auto_register_policy_transforms": False},
                        **collector_devices(policy, factory.device),
                        remote_configs={"num_cpus": 1, "num_gpus": 0, "memory": 2 * 1024 ** 3})
