"""How fast does PPO train a tracker? Frames (world-steps) per second at B = 64 worlds per env.

Measured in one run, on the same dataset and references:

* ``collection``: TorchRL ``Collector`` on ``TrackingEnv`` with the residual ``Tracker`` sampling
  actions (its ``sampling_policy()``, what PPO collects with), built with the trainer's settings
  (``adadex.train.collectors.local_collector``); the env's physics events are recorded:
  every servo target, and every world restarted (new reference, new scene) or put back;
* ``physics``: ``BatchedSim`` alone (2 MuJoCo threads) replaying that record in a fresh env seeded
  alike — the same scenes and the same motion, contacts included, with nothing else; the timed
  steps are those of the timed batches. ``physics_replay_exact`` says whether the replay ended in
  the recorded state (MuJoCo is deterministic; it should). Physics cost depends on the motion and
  the scenes: worlds holding their start pose step 20–30 % faster than worlds tracking and touching
  objects, so that figure (``physics_static_fps``, the yardstick of the first version of this
  benchmark) would charge the collection for contacts it did not add; replaying the targets on a
  fresh env's first scenes (the second version) ran the motion against objects it was not made
  for. ``physics_in_collection_fps`` (frames over the time spent inside ``BatchedSim.step`` during
  the collection) cross-checks it: it also holds the cost of stepping physics between other work
  (cold caches, threads waking). ``collection_step_ms`` splits one collection step of the B worlds:
  ``physics`` (inside ``BatchedSim.step``), ``env`` (the rest of ``TrackingEnv._step``), ``torchrl_env``
  (the rest of TorchRL's ``step_and_maybe_reset``: partial resets, the ``RewardSum`` transform,
  carrying the next observation over), ``policy`` (the sampling policy's forward) and ``collector``
  (the rest: writing the batch, the exploration context);
* ``ppo``: full PPO iterations (collect + GAE + 4 epochs of minibatch updates + weight sync), the
  trainer of ``adadex.train.ppo``;
* ``multisync_1`` / ``multisync_2``: ``MultiSyncCollector`` with 1 and 2 worker processes, one MuJoCo
  and one torch thread each; ``ray_1`` / ``ray_2``: the same with TorchRL's ``RayCollector`` on a
  local Ray cluster, made by ``make_collector`` as the trainer makes them: the first starts the
  cluster, the second joins it (skipped without the ``ray`` extra);
* worker start-up: seconds from creating a multi-worker collector to its first batch, minus one
  batch's collection time (imports + env construction in the workers; the compiled scenes are
  shipped from the main process). Workers start as the trainer starts them
  (``CollectorConfig.start_method``, ``--start-method``): with ``forkserver``, the default, the fork
  server is started just before the 1-worker collector, whose start-up therefore holds the server's
  imports; the 2-worker collector after it forks both workers from the running server. With
  ``spawn`` every worker imports torch, TorchRL and MuJoCo itself. Before its first batch each
  multi-worker collector runs its first ``update_policy_weights_()``, as the trainer does; that
  sync's seconds are ``*_first_sync_s``, outside the start-up (for Ray, TorchRL starts one more
  actor process there, its weight sync's rendezvous).

``multisync_2_over_physics``: the 2-worker collection (2 processes of B worlds, one thread each)
over ``physics`` (one env of B worlds on 2 threads): what the machine's two cores deliver when one
process's policy and bookkeeping overlap the other's physics. The single-process collection cannot
overlap them: each step's policy waits for that step's physics.

``collection_split``: the same B worlds split over 2 worker processes of B/2 worlds, each stepping
its physics on its own thread (no MuJoCo pool) with one torch thread, made by ``make_collector`` as
the trainer makes them (``collector.workers=2 collector.worlds=B/2 collector.env_threads=0``; before
2026-11-26 the workers handed physics to a 1-thread pool, ``env_threads=1``); ``ppo_split``: PPO iterations
on that collector. Besides overlapping one worker's bookkeeping with the other's physics, the split
may step its physics at another rate than one env on 2 threads (no barrier joins the halves each
step), so it has its own yardstick: ``physics_split_static_fps`` steps B worlds holding still, the
first half in one process and the second in another at once, each on its own thread, against
``physics_static_cycle_fps``, the same B worlds in one env on 2 threads (world ``w`` holds reference
``w`` in both). Their ratio is ``split_physics_speedup``; ``collection_split_over_split_physics``
(``collection_split`` over ``physics`` divided by that ratio) is the split's collection over its own
physics.

``multisync_2_over_own_physics``: the 2-worker MultiSync collection (B worlds per worker) over the
physics of the same arrangement, ``physics_two_envs_static_fps`` (two processes, each stepping B worlds
holding still on one thread, at once) taken relative to ``physics_static_cycle_fps`` the way the split's
is: what TorchRL's multi-process collection keeps of the physics its workers could step, at the batch
size per env of the single-process measurement. It is the collection the trainer runs with
``collector.workers=2 collector.env_threads=1`` (``collector.worlds`` = B).

``collector_floor_ms`` (``collector_floor_half_ms``): one step of the trainer's single-process
collector with the same policy over the same env with ``TrackingEnv``'s own work taken out (its
step hands back a cached output: no physics, no observation or reward computed), B (B/2) worlds —
what TorchRL's transforms and collector and the policy cost alone. ``collection_ceiling`` is the
collection's rate over ``physics`` were ``TrackingEnv`` free and physics as fast inside the
collection as alone: ``physics step / (physics step + floor)``; ``collection_split_ceiling`` the same
for the split (its workers' physics from ``split_physics_speedup``). A ceiling below 0.8 says the
target cannot be met with this collector and policy on this machine, whatever the env does.

Targets: collection ≥ 0.8 × physics; PPO overall ≥ 0.5 × physics; 2 workers ≥ 1.7 × 1 worker.
Writes ``benchmarks/results/train_throughput.json`` with ``collection_over_physics``,
``ppo_over_physics`` and ``two_workers_over_one`` (MultiSync; ``ray_two_workers_over_one`` beside it).

    python benchmarks/train_throughput.py [--dataset DIR] [--worlds 64] [--frames 16384] [--out FILE]

Without ``--dataset`` the ``tiny`` preset is built into a temporary folder first.
"""

from __future__ import annotations

import argparse
import dataclasses
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from _data import RESULTS, dataset_or_tiny, check_result, write_result

from adadex.train.config import START_METHODS



def _physics_fps(factory, recorder: _PhysicsRecorder | None = None, steps: int = 0) -> tuple[float, bool | None]:
    """BatchedSim alone (no env work) in a fresh env from ``factory``: (frames/s, whether the replay
    ended in the recorded state). With a ``recorder``, the fresh env replays its events — the
    restarts (the same draws: the env is seeded alike) and every servo target — so its worlds hold
    the same scenes and make the same motion; only the steps the recorder timed are timed. Without
    one, the worlds hold their start targets for ``steps`` steps."""
    env = factory().base_env
    if recorder is None:
        env.reset()
        targets = env._q_target.copy()
        env.sim.step(targets)
        t0 = time.perf_counter()
        for _ in range(steps):
            env.sim.step(targets)
        fps = steps * env.batch_size[0] / (time.perf_counter() - t0)
        env.close()
        return fps, None
    seconds, n = 0.0, 0
    for kind, value, timed in recorder.events:
        if kind == "start":
            env._start_worlds(value)
        elif kind == "put":
            env._put_at_start(value)
        elif timed:
            t0 = time.perf_counter()
            env.sim.step(value)
            seconds += time.perf_counter() - t0
            n += 1
        else:
            env.sim.step(value)
    exact = bool(np.array_equal(env.sim.readout().object_pose, recorder.final_object_pose))
    env.close()
    return n * env.batch_size[0] / seconds, exact


class _PhysicsRecorder:
    """Wraps one ``TrackingEnv``: the servo targets its ``BatchedSim.step`` receives (and the time
    spent there once ``timing`` is set), and the worlds it restarts or puts back between steps, in
    order, so :func:`_physics_fps` can replay the same physics."""

    def __init__(self, env):
        self.env, self.events, self.seconds, self.steps, self.timing = env, [], 0.0, 0, False
        self.final_object_pose = None
        self._step, self._start, self._put, self._starting = env.sim.step, env._start_worlds, env._put_at_start, False
        env.sim.step, env._start_worlds, env._put_at_start = self._record_step, self._record_start, self._record_put

    def _record_step(self, targets, *args, **kwargs):
        self.events.append(("step", np.array(targets, copy=True), self.timing))
        t0 = time.perf_counter()
        out = self._step(targets, *args, **kwargs)
        if self.timing:
            self.seconds += time.perf_counter() - t0
            self.steps += 1
        self.final_object_pose = out.object_pose.copy()
        return out

    def _record_start(self, worlds):
        self.events.append(("start", np.array(worlds, copy=True), False))
        self._starting = True
        try:
            return self._start(worlds)
        finally:
            self._starting = False

    def _record_put(self, worlds, *args, **kwargs):
        if not self._starting:                      # an unstable world put back during a step
            self.events.append(("put", np.array(worlds, copy=True), False))
        return self._put(worlds, *args, **kwargs)


class _Timer:
    """Time spent in ``obj.name`` (a method replaced on the instance) while ``timing`` is set;
    :meth:`restore` puts the method back (a wrapped policy does not pickle into workers)."""

    def __init__(self, obj, name: str):
        self.obj, self.name, self.seconds, self.timing = obj, name, 0.0, False
        self._orig = getattr(obj, name)

        def timed(*args, **kwargs):
            t0 = time.perf_counter()
            try:
                return self._orig(*args, **kwargs)
            finally:
                if self.timing:
                    self.seconds += time.perf_counter() - t0
        setattr(obj, name, timed)

    def restore(self):
        delattr(self.obj, self.name)


def _collector_fps(make, frames_per_batch: int, batches: int, recorders=(), first_sync: dict | None = None):
    """(frames/s over ``batches`` batches after the first, start-up s: first batch minus one batch).
    ``recorders`` (:class:`_PhysicsRecorder` or :class:`_Timer`, filled when ``make`` builds its envs)
    time the physics, or their method, during the timed batches. With ``first_sync`` (a dict), the
    collector's first ``update_policy_weights_()`` runs before its first batch, as the trainer runs it,
    and its seconds go to ``first_sync["s"]``, not into the start-up."""
    t0 = time.perf_counter()
    col = make()
    sync = 0.0
    if first_sync is not None:
        ts = time.perf_counter()
        col.update_policy_weights_()
        sync = first_sync["s"] = time.perf_counter() - ts
    it = iter(col)
    next(it)
    first = time.perf_counter() - t0 - sync
    for r in recorders:
        r.timing = True
    t1 = time.perf_counter()
    for _ in range(batches):
        next(it)
    per_batch = (time.perf_counter() - t1) / batches
    for r in recorders:
        r.timing = False
    col.shutdown()
    return frames_per_batch / per_batch, max(0.0, first - per_batch)


def _static_steps(dataset: str, references: list[int], nthread: int, steps: int, barrier) -> float:
    """Frames/s of a ``TrackingEnv`` whose world ``w`` holds ``references[w]`` at its start targets, on
    ``nthread`` MuJoCo threads, for ``steps`` steps timed from ``barrier`` (crossed by every process
    measured together)."""
    from adadex.envs.tracking import TrackingEnv

    torch.set_num_threads(1)
    env = TrackingEnv(dataset, num_worlds=len(references), split=None, references=references, draw="cycle",
                      nthread=nthread)
    env.reset()
    targets = env._q_target.copy()
    env.sim.step(targets)
    barrier.wait()
    t0 = time.perf_counter()
    for _ in range(steps):
        env.sim.step(targets)
    fps = steps * len(references) / (time.perf_counter() - t0)
    env.close()
    return fps


def _static_fps(dataset: str, groups: list[list[int]], nthread: int, steps: int) -> float:
    """Frames/s of worlds holding still, one env per group of references (each in its own process,
    all at once, ``nthread`` MuJoCo threads each): the same worlds one env or split over several."""
    import multiprocessing
    from concurrent.futures import ProcessPoolExecutor

    n = len(groups)
    with multiprocessing.Manager() as manager, ProcessPoolExecutor(n) as pool:
        barrier = manager.Barrier(n)
        return sum(pool.map(_static_steps, [dataset] * n, groups, [nthread] * n, [steps] * n, [barrier] * n))


def _floor_env(factory):
    """The collected env with ``TrackingEnv``'s own work taken out: its ``_step`` hands back one real
    step's output (no physics, no observation or reward to compute, no episode ending), so what a
    collector spends per step on it is TorchRL's share alone — the transforms, ``step_mdp``, the
    collector's bookkeeping — plus the policy."""
    env = factory()
    base = env.base_env
    td = env.reset()
    td["action"] = torch.zeros(base.action_spec.shape)
    out = base._step(td)
    for key in ("done", "terminated", "truncated"):
        out[key] = torch.zeros_like(out[key])
    base._step = lambda _: out.clone()
    return env


def _floor_ms(factory, policy, frames_per_batch: int, batches: int) -> float:
    """ms per collection step of ``factory``'s worlds with :func:`_floor_env` (the trainer's collector)."""
    from adadex.train.collectors import local_collector

    fps, _ = _collector_fps(lambda: local_collector(lambda: _floor_env(factory), policy,
                                                    frames_per_batch=frames_per_batch, total_frames=-1),
                            frames_per_batch, batches)
    return factory.num_worlds / fps * 1e3


def _policy_ms(factory, pc, calls: int = 300) -> tuple[float, float]:
    """ms per call of the sampling policy on one batch of the env's observations: the plain residual
    tracker, and the object-anchored one with every world's object 3 cm off its reference start (so
    every world needs the anchor's Jacobian, as under Table 3's displacement before the object moves;
    the collection above runs unrandomized, where the anchor has nothing to do)."""
    from torchrl.envs.utils import ExplorationType, set_exploration_type

    from adadex.envs.observation import OBJECT_START

    env = factory()
    td = env.reset()
    env.close()
    td[OBJECT_START][:, 0] += 0.03
    out = []
    for anchor in (0.0, pc.anchor or 0.05):
        policy = dataclasses.replace(pc, anchor=anchor).tracker().sampling_policy()
        with torch.no_grad(), set_exploration_type(ExplorationType.RANDOM):
            for _ in range(20):
                policy(td.clone())
            t0 = time.perf_counter()
            for _ in range(calls):
                policy(td.clone())
        out.append((time.perf_counter() - t0) / calls * 1e3)
    return out[0], out[1]


def main(argv=None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--dataset", type=Path, default=None)
    p.add_argument("--worlds", type=int, default=64)
    p.add_argument("--frames", type=int, default=16384, help="frames per measurement")
    p.add_argument("--out", type=Path, default=RESULTS / "train_throughput.json")
    p.add_argument("--no-ray", action="store_true")
    p.add_argument("--start-method", choices=START_METHODS, default="forkserver",
                   help="how local MultiSync workers start (CollectorConfig.start_method)")
    p.add_argument("--force", action="store_true",
                   help="replace --out even if it is not an earlier result of this benchmark")
    a = p.parse_args(argv)
    check_result(a.out, name="train_throughput", force=a.force)      # before any work: refuse a file not ours
    torch.set_num_threads(1)

    from torchrl.collectors import MultiSyncCollector

    from adadex.data.reference import ReferenceDataset
    from adadex.envs.tracking import episode_references
    from adadex.train.collectors import collector_devices, local_collector, make_collector, start_worker_server
    from adadex.train.config import CollectorConfig, PolicyConfig, PPOConfig, TrainConfig
    from adadex.train.envs import TrackingEnvFactory
    from adadex.train.ppo import PPOTrainer

    with dataset_or_tiny(a.dataset) as dataset, tempfile.TemporaryDirectory() as tmp:
        ds = ReferenceDataset(dataset)
        refs = tuple(episode_references(ds, ("unseen_trajectory", "train")))
        B, fpb = a.worlds, a.worlds * 64
        batches = max(1, a.frames // fpb)
        factory = TrackingEnvFactory(str(dataset), refs, num_worlds=B, seed=0, nthread=2)
        pc = PolicyConfig()
        policy = pc.tracker().sampling_policy()
        res = {"worlds": B, "frames_per_batch": fpb, "batches": batches, "references": len(refs)}

        recorders, timers = [], {"policy": _Timer(policy, "forward")}
        watched = [timers["policy"]]             # filled as the collector builds its env

        def recorded_env():
            env = factory()
            recorders.append(_PhysicsRecorder(env.base_env))
            timers["env_step"] = _Timer(env.base_env, "_step")
            timers["torchrl_step"] = _Timer(env, "step_and_maybe_reset")
            watched.extend([recorders[-1], timers["env_step"], timers["torchrl_step"]])
            return env

        res["collection_fps"], _ = _collector_fps(
            lambda: local_collector(recorded_env, policy, frames_per_batch=fpb, total_frames=-1),
            fpb, batches, watched)
        timers["policy"].restore()
        rec = recorders[-1]
        res["physics_in_collection_fps"] = rec.steps * B / rec.seconds
        ms = {k: t.seconds / rec.steps * 1e3 for k, t in timers.items()}
        step_ms = B / res["collection_fps"] * 1e3
        res["collection_step_ms"] = {        # one step of the B worlds, where its time goes
            "total": step_ms, "physics": rec.seconds / rec.steps * 1e3,
            "env": ms["env_step"] - rec.seconds / rec.steps * 1e3,        # TrackingEnv._step besides physics
            "torchrl_env": ms["torchrl_step"] - ms["env_step"],           # TorchRL's step, reset and transforms
            "policy": ms["policy"],
            "collector": step_ms - ms["torchrl_step"] - ms["policy"]}
        res["physics_fps"], res["physics_replay_exact"] = _physics_fps(factory, rec)
        res["physics_static_fps"], _ = _physics_fps(factory, steps=rec.steps)
        res["policy_ms"], res["policy_anchored_ms"] = _policy_ms(factory, pc)
        res["collector_floor_ms"] = _floor_ms(factory, policy, fpb, batches)
        res["collector_floor_half_ms"] = _floor_ms(dataclasses.replace(factory, num_worlds=B // 2, nthread=0),
                                                   policy, fpb // 2, batches)

        cfg = TrainConfig(dataset=str(dataset), out=str(Path(tmp) / "ppo"), randomize=False, wandb=False,
                          progress=False, eval_max_references=0, checkpoint_every=10 ** 6,
                          ppo=PPOConfig(total_frames=fpb * (batches + 1), frames_per_batch=fpb),
                          collector=CollectorConfig(worlds=B), policy=PolicyConfig())
        trainer = PPOTrainer(cfg)                                   # eval_max_references=0: the iterations only
        trainer.train()
        rows = trainer_rows(Path(cfg.out) / "metrics.csv")
        res["ppo_fps"] = float(np.median([r["fps"] for r in rows[1:]]))      # the first fits normalizers

        one = factory.with_scenes()
        w1 = dataclasses.replace(one, nthread=1)
        res["start_method"] = a.start_method
        start_worker_server(a.start_method)
        for n in (1, 2):
            sync = {}
            res[f"multisync_{n}_fps"], res[f"multisync_{n}_startup_s"] = _collector_fps(
                lambda n=n: MultiSyncCollector(w1.for_workers(n), policy, frames_per_batch=fpb * n, total_frames=-1,
                                               cat_results="stack", num_sub_threads=1,
                                               auto_register_policy_transforms=False,
                                               **collector_devices(policy)), fpb * n, batches, first_sync=sync)
            res[f"multisync_{n}_first_sync_s"] = sync["s"]
        split = CollectorConfig(workers=2, worlds=B // 2, env_threads=0, start_method=a.start_method)
        half = dataclasses.replace(one, num_worlds=B // 2, nthread=split.env_threads)
        res["collection_split_fps"], res["collection_split_startup_s"] = _collector_fps(
            lambda: make_collector(half, policy, split, frames_per_batch=fpb, total_frames=fpb * (batches + 2)),
            fpb, batches)
        worlds = [refs[i % len(refs)] for i in range(B)]            # the same worlds, one env or two
        res["physics_static_cycle_fps"] = _static_fps(str(dataset), [worlds], 2, rec.steps)
        res["physics_split_static_fps"] = _static_fps(str(dataset), [worlds[:B // 2], worlds[B // 2:]],
                                                      split.env_threads, rec.steps)
        res["physics_two_envs_static_fps"] = _static_fps(str(dataset), [worlds, worlds], 1, rec.steps)
        cfg = dataclasses.replace(cfg, out=str(Path(tmp) / "ppo_split"), collector=split)
        trainer = PPOTrainer(cfg)
        trainer.train()
        res["ppo_split_fps"] = float(np.median([r["fps"] for r in trainer_rows(Path(cfg.out) / "metrics.csv")[1:]]))
        if not a.no_ray:
            try:
                import ray
            except ImportError:
                ray = None
            if ray is not None:              # as the trainer makes them: the second joins the first's cluster
                for n in (1, 2):
                    sync = {}
                    res[f"ray_{n}_fps"], res[f"ray_{n}_startup_s"] = _collector_fps(
                        lambda n=n: make_collector(w1, policy, CollectorConfig(workers=n, backend="ray", worlds=B),
                                                   frames_per_batch=fpb * n, total_frames=fpb * n * (batches + 2)),
                        fpb * n, batches, first_sync=sync)
                    res[f"ray_{n}_first_sync_s"] = sync["s"]
                ray.shutdown()

    res["collection_over_physics"] = res["collection_fps"] / res["physics_fps"]
    res["ppo_over_physics"] = res["ppo_fps"] / res["physics_fps"]
    res["collection_over_static_physics"] = res["collection_fps"] / res["physics_static_fps"]
    res["two_workers_over_one"] = res["multisync_2_fps"] / res["multisync_1_fps"]
    res["multisync_2_over_physics"] = res["multisync_2_fps"] / res["physics_fps"]
    res["two_envs_physics_speedup"] = res["physics_two_envs_static_fps"] / res["physics_static_cycle_fps"]
    res["multisync_2_over_own_physics"] = res["multisync_2_over_physics"] / res["two_envs_physics_speedup"]
    res["collection_split_over_physics"] = res["collection_split_fps"] / res["physics_fps"]
    res["ppo_split_over_physics"] = res["ppo_split_fps"] / res["physics_fps"]
    res["split_physics_speedup"] = res["physics_split_static_fps"] / res["physics_static_cycle_fps"]
    res["collection_split_over_split_physics"] = res["collection_split_over_physics"] / res["split_physics_speedup"]
    if "ray_2_fps" in res:
        res["ray_two_workers_over_one"] = res["ray_2_fps"] / res["ray_1_fps"]
    physics_ms = res["worlds"] / res["physics_fps"] * 1e3          # one step of all worlds, physics alone
    res["collection_ceiling"] = physics_ms / (physics_ms + res["collector_floor_ms"])
    split_ms = physics_ms / res["split_physics_speedup"]             # one step of a split worker, physics alone
    res["collection_split_ceiling"] = res["split_physics_speedup"] * split_ms / (split_ms + res["collector_floor_half_ms"])
    write_result(a.out, res, name="train_throughput", force=a.force, indent=1)
    print(f"physics of the collected motion {res['physics_fps']:.0f} frames/s (replayed exactly: "
          f"{res['physics_replay_exact']}; inside the collection {res['physics_in_collection_fps']:.0f}; "
          f"worlds holding still {res['physics_static_fps']:.0f})")
    print(f"collection {res['collection_fps']:.0f} ({res['collection_over_physics']:.2f} × physics, target ≥ 0.8; "
          f"{res['collection_over_static_physics']:.2f} × the still worlds) | PPO {res['ppo_fps']:.0f} "
          f"({res['ppo_over_physics']:.2f} ×, target ≥ 0.5)")
    c = res["collection_step_ms"]
    print(f"one collection step of {res['worlds']} worlds, {c['total']:.2f} ms: physics {c['physics']:.2f}, env "
          f"{c['env']:.2f}, TorchRL env {c['torchrl_env']:.2f}, policy {c['policy']:.2f}, collector {c['collector']:.2f} "
          f"(physics alone: {res['worlds'] / res['physics_fps'] * 1e3:.2f})")
    print(f"the same {res['worlds']} worlds split over 2 workers (trainer: collector.workers=2 collector.worlds="
          f"{res['worlds'] // 2} collector.env_threads=0): collection {res['collection_split_fps']:.0f} "
          f"({res['collection_split_over_physics']:.2f} × physics), PPO {res['ppo_split_fps']:.0f} "
          f"({res['ppo_split_over_physics']:.2f} ×); split, the physics of the same worlds holding still runs at "
          f"{res['split_physics_speedup']:.2f} × one env's, so the split collects at "
          f"{res['collection_split_over_split_physics']:.2f} × its own physics")
    print(f"MultiSync 1 worker {res['multisync_1_fps']:.0f}, 2 workers {res['multisync_2_fps']:.0f} frames/s: "
          f"{res['two_workers_over_one']:.2f} × (target ≥ 1.7); start-up "
          f"{res['multisync_1_startup_s']:.1f} / {res['multisync_2_startup_s']:.1f} s ({a.start_method}); "
          f"2 workers over the physics of 2 threads: {res['multisync_2_over_physics']:.2f} ×; two envs of "
          f"{res['worlds']} worlds step their physics at {res['two_envs_physics_speedup']:.2f} × one env's on 2 threads, "
          f"so 2 workers collect at {res['multisync_2_over_own_physics']:.2f} × their own physics (target ≥ 0.8)")
    if "ray_2_fps" in res:
        print(f"Ray 1 worker {res['ray_1_fps']:.0f}, 2 workers {res['ray_2_fps']:.0f} frames/s: "
              f"{res['ray_two_workers_over_one']:.2f} ×; start-up {res['ray_1_startup_s']:.1f} / "
              f"{res['ray_2_startup_s']:.1f} s, then the first weight sync {res['ray_1_first_sync_s']:.1f} / "
              f"{res['ray_2_first_sync_s']:.1f} s (TorchRL starts its rendezvous actor)")
    print(f"TorchRL's floor (the trainer's collector and policy on an env doing no work): "
          f"{res['collector_floor_ms']:.2f} ms per step of {res['worlds']} worlds, "
          f"{res['collector_floor_half_ms']:.2f} of {res['worlds'] // 2}; were TrackingEnv free and physics as fast "
          f"as alone, collection would reach {res['collection_ceiling']:.2f} × physics (one process), "
          f"{res['collection_split_ceiling']:.2f} × (the split)")
    print(f"policy (sampling, B = {res['worlds']}): {res['policy_ms']:.2f} ms per step; object-anchored with every "
          f"object displaced {res['policy_anchored_ms']:.2f} ms")
    print(f"wrote {a.out}")
    return res


def trainer_rows(path: Path) -> list[dict]:
    import csv

    with path.open(newline="") as f:
        return [{k: float(v) for k, v in r.items() if v not in ("", None)} for r in csv.DictReader(f)
                if r.get("fps")]


if __name__ == "__main__":
    main()
