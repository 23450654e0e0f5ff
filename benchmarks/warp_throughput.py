"""How fast is the MuJoCo Warp backend on a GPU? Frames (world-steps at 12 Hz) per second against B.

Measured per B (default 256, 1,024, 4,096, 8,192), each part alone and in this order:

* ``physics``: MuJoCo Warp's own ``step`` on one scene (the dataset's first object), ``substeps``
  physics steps per frame captured in one CUDA graph, ctrl held at the home pose: the ceiling of
  everything above it (no readout, nothing leaves the GPU);
* ``sim``: ``BatchedSim(..., backend="warp")`` — the library's backend, per-world scenes of the
  references' objects, ctrl given as a device tensor, each step's readout taken on the device;
* ``env``: ``TrackingEnv(backend="warp")`` stepped as a collector steps it (``step_and_maybe_reset``)
  with kinematic replay's actions (the next reference frame as the target) — observation, errors and
  reward computed on the device, worlds that end reset on the host. A fresh env's worlds all start
  together, so few end within the timed steps: the steady-state reset rate (B / window worlds per
  step) is timed apart, with and without Table 3's randomization, and reported as ``reset_ms`` and
  ``fps_steady`` (= frames per step time plus that reset time);
* ``collect``: TorchRL ``Collector`` on that env with the residual ``Tracker`` sampling (what PPO
  collects with), the policy on the GPU;
* ``ppo``: ``PPOTrainer`` iterations (collect + GAE + minibatch updates) on that env, as the trainer
  builds them (``sim.backend=warp``; ``ppo.device`` the GPU when there is one), nominal physics;
* ``specialist``: a whole ``PPOTrainer.train()`` of 1 M frames (``--specialist-frames``) at B worlds,
  wall time from the trainer's construction to its end (env build included, no evaluation).

``--kernel-profile`` adds to the ``sim`` part the GPU time of each MuJoCo Warp kernel over one
control step (launched one by one, not as the graph), the top ones by time: where the physics goes.

Each part is timed over ``--steps`` frames after one warm-up pass (kernels compile on first use: the
cold compile is reported separately as ``compile_s``). The JSON is rewritten after every part, so a
run cut short keeps what it measured. Targets (issue 46, one H100): ``env`` ≥ 200 k frames/s at
B = 4,096; ``ppo`` ≥ 50 % of it; a specialist's 1 M frames in under a minute.

    python benchmarks/warp_throughput.py [--dataset DIR] [--batches 256,1024,4096,8192] [--steps 60]
        [--parts physics,sim,env,collect,ppo] [--device cuda:0] [--out FILE]

Needs the ``warp`` extra (``pip install "adadex[warp]"``); on a machine without a GPU it runs on Warp's
CPU device (correct, never fast: do not read its figures as timings). See ``benchmarks/device/warp_device.sh``
for running it on a lent GPU machine whose Python holds torch only.
"""

from __future__ import annotations

import argparse
import json
import platform
import sys
import time
from pathlib import Path

import numpy as np
import torch

from _data import RESULTS, check_result, dataset_or_tiny, refuse, write_result

PARTS = ("physics", "sim", "env", "collect", "ppo", "specialist")


def _sync(device: str) -> None:
    import warp as wp

    wp.synchronize_device(device)
    if device.startswith("cuda"):
        torch.cuda.synchronize()


def physics_fps(model, B: int, steps: int, device: str, substeps: int) -> dict:
    """MuJoCo Warp alone: ``substeps`` steps per frame in one captured graph (plain launches on the CPU)."""
    import mujoco
    import mujoco_warp as mjw
    import warp as wp

    from adadex.sim.scene import home_state
    from adadex.sim.warp_backend import DEFAULT_NCONMAX, DEFAULT_NJMAX
    qpos, ctrl = home_state(model)
    mjd = mujoco.MjData(model)
    mjd.qpos[:] = qpos
    mjd.ctrl[:] = ctrl
    mujoco.mj_forward(model, mjd)
    with wp.ScopedDevice(device):
        m = mjw.put_model(model)
        d = mjw.put_data(model, mjd, nworld=B, nconmax=DEFAULT_NCONMAX, njmax=DEFAULT_NJMAX)

        def frame():
            for _ in range(substeps):
                mjw.step(m, d)

        t0 = time.perf_counter()
        frame()                              # compiles the kernels on first use
        _sync(device)
        compile_s = time.perf_counter() - t0
        graph = None
        if device.startswith("cuda"):
            with wp.ScopedCapture() as cap:
                frame()
            graph = cap.graph
        run = (lambda: wp.capture_launch(graph)) if graph is not None else frame
        run()
        _sync(device)
        t0 = time.perf_counter()
        for _ in range(steps):
            run()
        _sync(device)
        dt = time.perf_counter() - t0
        from mujoco_warp._src.types import OverflowType

        flags = np.bitwise_or.reduce(np.asarray(d.overflow.numpy()).reshape(-1))
        solver = int(OverflowType.ITERATIONS | OverflowType.LS_ITERATIONS)
    # capacity: contacts or constraint rows dropped (must be 0); solver: an iteration limit was reached in
    # some world (MuJoCo Warp prints a line for it; the step still completes, as C MuJoCo's would)
    return {"fps": B * steps / dt, "step_ms": dt / steps * 1e3, "compile_s": compile_s,
            "graph": graph is not None, "capacity_overflow": bool(flags & ~solver),
            "solver_iteration_limit": bool(flags & solver)}


def sim_fps(dataset, refs, B: int, steps: int, device: str, kernel_profile: bool = False) -> dict:
    """``BatchedSim(backend="warp")`` over per-world scenes of the references' objects."""
    from adadex.data.reference import ReferenceDataset
    from adadex.sim.batched import BatchedSim
    from adadex.sim.patch import patched_scene
    from adadex.sim.scene import home_state

    ds = ReferenceDataset(dataset)
    objects = [ds.entries[refs[i % len(refs)]]["object"] for i in range(B)]
    scenes = {o: patched_scene(o, None, uniform_layout=True) for o in sorted(set(objects))}
    t0 = time.perf_counter()
    sim = BatchedSim([scenes[o] for o in objects], backend="warp", device=device)
    build_s = time.perf_counter() - t0
    qpos, ctrl = home_state(sim.models[0])
    sim.reset(qpos=qpos)
    c = torch.as_tensor(np.tile(ctrl, (B, 1)), dtype=torch.float32, device=device)
    t0 = time.perf_counter()
    sim.step_device(c)
    _sync(device)
    compile_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    for _ in range(steps):
        r = sim.step_device(c)
    _sync(device)
    dt = time.perf_counter() - t0
    unstable = int(torch.as_tensor(r.unstable).sum())
    # the same worlds' physics alone (the captured graph), the readout alone, the overflow check alone
    parts = {}
    for name, fn in (("physics_ms", sim._physics), ("readout_ms", sim.device_readout),
                     ("overflow_check_ms", sim._check_overflow)):
        _sync(device)
        t0 = time.perf_counter()
        for _ in range(steps):
            fn()
        _sync(device)
        parts[name] = (time.perf_counter() - t0) / steps * 1e3
    out = {"fps": B * steps / dt, "step_ms": dt / steps * 1e3, "build_s": build_s, "compile_s": compile_s,
           "objects": len(scenes), "unstable_worlds": unstable, **parts}
    if kernel_profile:
        out["kernels_ms"] = _kernel_profile(sim, device)
    sim.close()
    return out


def _kernel_profile(sim, device: str, top: int = 25) -> dict:
    """GPU milliseconds of each kernel over one control step of ``sim`` (launched eagerly), top ``top``."""
    import warp as wp

    if not device.startswith("cuda"):
        return {}
    wp.timing_begin(cuda_filter=wp.TIMING_KERNEL)
    with wp.ScopedDevice(sim.device):
        for _ in range(sim.substeps):
            sim._mjw.step(sim._model, sim._data)
    results = wp.timing_end()
    per: dict[str, float] = {}
    for r in results:
        per[r.name] = per.get(r.name, 0.0) + r.elapsed
    total = sum(per.values())
    rows = dict(sorted(per.items(), key=lambda kv: -kv[1])[:top])
    return {"total": total, "launches": len(results), **rows}


def env_fps(dataset, refs, B: int, steps: int, device: str, kernel_profile: bool = False) -> dict:
    """``TrackingEnv(backend="warp")`` stepped with kinematic replay's actions, as a collector steps it;
    the steady-state resets timed apart (see the module docstring)."""
    from adadex.envs.randomization import Randomization
    from adadex.envs.tracking import TrackingEnv

    t0 = time.perf_counter()
    env = TrackingEnv(dataset, num_worlds=B, references=refs, split=None, seed=0, backend="warp", device=device)
    build_s = time.perf_counter() - t0
    bound = env.config.max_action

    def replay(td):
        return (td["reference", "hand_joint_pos"][:, 1] - td["proprio", "joint_target"]).clamp(-bound, bound)

    td = env.reset()
    for _ in range(2):                        # warm-up (kernels compiled by now)
        _, td = env.step_and_maybe_reset(td.set("action", replay(td)))
    _sync(device)
    ended = torch.zeros((), dtype=torch.long, device=env.device)      # summed on the device: no read back
    t0 = time.perf_counter()
    for _ in range(steps):
        out, td = env.step_and_maybe_reset(td.set("action", replay(td)))
        ended += out["next", "done"].sum()
    _sync(device)
    dt = time.perf_counter() - t0
    out = {"fps": B * steps / dt, "step_ms": dt / steps * 1e3, "build_s": build_s, "unstable": env.unstable_count,
           "episodes_ended": int(ended), "device": str(env.device)}
    # the physics alone (the captured graph) from the worlds' states now, mid-episode (hands on objects):
    # what of step_ms is the physics under these actions, the rest being the env's own work
    t0 = time.perf_counter()
    for _ in range(steps):
        env.sim._physics()
    _sync(device)
    out["physics_ms"] = (time.perf_counter() - t0) / steps * 1e3
    if kernel_profile:
        out["kernels_ms"] = _kernel_profile(env.sim, device)
    env.close()
    k = max(1, round(B / env.config.window))  # worlds an env of B resets per step once episodes desynchronize
    for name, rnd in (("", None), ("_randomized", Randomization())):
        env = TrackingEnv(dataset, num_worlds=B, references=refs, split=None, seed=0, backend="warp", device=device,
                          randomize=rnd)
        td = env.reset()
        times = []
        for i in range(8):                    # the first resets meet new scenes and mesh sizes: median
            mask = torch.zeros(B, 1, dtype=torch.bool, device=env.device)
            mask[(i * k) % B:(i * k) % B + k] = True
            _sync(device)
            t0 = time.perf_counter()
            env.reset(td.clone().set("_reset", mask))
            _sync(device)
            times.append(time.perf_counter() - t0)
        env.close()
        reset_ms = float(np.median(times)) * 1e3
        out[f"reset_ms{name}"] = reset_ms
        out[f"fps_steady{name}"] = B / (out["step_ms"] + reset_ms) * 1e3
    out["resets_per_step"] = k
    return out


def collect_fps(dataset, refs, B: int, steps: int, device: str) -> dict:
    """TorchRL ``Collector`` with the sampling ``Tracker`` on the GPU, over the warp env."""
    from adadex.train.collectors import local_collector
    from adadex.train.config import PolicyConfig
    from adadex.train.envs import TrackingEnvFactory

    pc = PolicyConfig()
    policy = pc.tracker().sampling_policy().to(device if device.startswith("cuda") else "cpu")
    factory = TrackingEnvFactory(str(dataset), tuple(refs), num_worlds=B, seed=0, backend="warp")
    fpb = B * steps
    col = local_collector(factory, policy, frames_per_batch=fpb, total_frames=-1)
    it = iter(col)
    t0 = time.perf_counter()
    next(it)                                  # warm-up batch: env build, compile, first resets
    first_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    batch = next(it)
    dt = time.perf_counter() - t0
    col.shutdown()
    return {"fps": batch.numel() / dt, "batch_s": dt, "first_batch_s": first_s, "frames_per_batch": fpb}


def ppo_fps(dataset, B: int, steps: int, device: str, iterations: int = 3, total_frames: int | None = None,
            minibatches: int = 4) -> dict:
    """PPO iterations as the trainer runs them, its env on the warp backend (``total_frames``: a whole
    run of that many frames instead, ``steps`` per batch), each epoch in ``minibatches`` minibatches (as
    GPU PPO runs: 4 × B·T / 4 frames; the trainer's default of 1,024 frames would be hundreds of small
    updates per batch)."""
    import tempfile

    from adadex.train.config import CollectorConfig, PolicyConfig, PPOConfig, SimConfig, TrainConfig
    from adadex.train.ppo import PPOTrainer

    fpb = B * steps
    total = total_frames if total_frames is not None else fpb * (iterations + 1)
    with tempfile.TemporaryDirectory() as tmp:
        cfg = TrainConfig(dataset=str(dataset), out=str(Path(tmp) / "ppo"), randomize=False, wandb=False,
                          progress=False, eval_max_references=0, checkpoint_every=10 ** 6,
                          ppo=PPOConfig(total_frames=total, frames_per_batch=fpb, minibatch_size=fpb // minibatches,
                                        device=device if device.startswith("cuda") else "cpu"),
                          collector=CollectorConfig(worlds=B), sim=SimConfig(backend="warp"),
                          policy=PolicyConfig())
        t0 = time.perf_counter()
        result = PPOTrainer(cfg).train()
        wall = time.perf_counter() - t0
        rows = list(__import__("csv").DictReader(open(Path(cfg.out) / "metrics.csv")))
    rows = [r for r in rows if r.get("fps")][1:]          # the first iteration fits the normalizers
    fps = [float(r["fps"]) for r in rows]
    col = [float(r["collect_fps"]) for r in rows if r.get("collect_fps")]
    return {"fps": float(np.median(fps)) if fps else None, "collect_fps": float(np.median(col)) if col else None,
            "timed_iterations": len(rows), "total_s": wall, "frames": result["frames"], "frames_per_batch": fpb,
            "minibatch_size": fpb // minibatches}


def _device_info(device: str) -> dict:
    import warp as wp

    info = {"python": platform.python_version(), "torch": torch.__version__, "warp": wp.__version__,
            "device": device}
    try:
        import mujoco_warp

        info["mujoco_warp"] = getattr(mujoco_warp, "__version__", None)
    except ImportError:
        pass
    if device.startswith("cuda") and torch.cuda.is_available():
        info["gpu"] = torch.cuda.get_device_name(0)
    return info


def main(argv=None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--dataset", type=Path, default=None)
    p.add_argument("--batches", default="256,1024,4096,8192")
    p.add_argument("--steps", type=int, default=60)
    p.add_argument("--parts", default=",".join(PARTS))
    p.add_argument("--device", default=None, help="Warp device (default: cuda:0 when there is one, else cpu)")
    p.add_argument("--out", type=Path, default=RESULTS / "warp_throughput.json")
    p.add_argument("--ppo-batches", default="1024,4096", help="the B at which the ppo part runs (it is slow)")
    p.add_argument("--specialist-batch", type=int, default=4096, help="B of the specialist part")
    p.add_argument("--specialist-frames", type=int, default=1_000_000)
    p.add_argument("--kernel-profile", action="store_true", help="GPU time per kernel in the sim part")
    p.add_argument("--minibatches", type=int, default=4, help="PPO minibatches per epoch (ppo, specialist)")
    p.add_argument("--budget-s", type=float, default=None,
                   help="start no new measurement after this many seconds (the JSON keeps what was measured)")
    p.add_argument("--force", action="store_true")
    a = p.parse_args(argv)
    check_result(a.out, name="warp_throughput", force=a.force)
    parts = [s for s in a.parts.split(",") if s]
    bad = [s for s in parts if s not in PARTS]
    if bad:
        raise refuse("warp_throughput", f"--parts: unknown {bad}; choose from {PARTS}")
    batches = [int(b) for b in a.batches.split(",")]
    ppo_batches = [int(b) for b in a.ppo_batches.split(",")]
    t_start = time.perf_counter()
    try:
        import warp as wp
    except ImportError:
        raise SystemExit('benchmarks/warp_throughput.py: error: needs the warp extra: pip install "adadex[warp]"')
    wp.config.log_level = wp.LOG_WARNING     # no line per compiled module
    device = a.device or ("cuda:0" if wp.get_cuda_device_count() > 0 else "cpu")
    wp.set_device(device)            # the backend runs on Warp's default device

    from adadex.data.reference import ReferenceDataset
    from adadex.envs.tracking import episode_references
    from adadex.sim.patch import patched_scene
    from adadex.sim.scene import CONTROL_HZ

    result = {"info": _device_info(device), "steps": a.steps, "batches": batches, "parts": {}}
    with dataset_or_tiny(a.dataset) as dataset:
        ds = ReferenceDataset(dataset)
        refs = episode_references(ds, None)
        model = patched_scene(ds.entries[refs[0]]["object"], None, uniform_layout=True)
        substeps = max(1, int(round(1.0 / (CONTROL_HZ * model.opt.timestep))))
        result["substeps"] = substeps
        for part in parts:
            rows = result["parts"].setdefault(part, {})
            for B in {"ppo": ppo_batches, "specialist": [a.specialist_batch]}.get(part, batches):
                if a.budget_s is not None and time.perf_counter() - t_start > a.budget_s:
                    rows[str(B)] = {"skipped": f"--budget-s {a.budget_s:g} spent"}
                    continue
                t0 = time.perf_counter()
                try:
                    if part == "physics":
                        r = physics_fps(model, B, a.steps, device, substeps)
                    elif part == "sim":
                        r = sim_fps(dataset, refs, B, a.steps, device, kernel_profile=a.kernel_profile)
                    elif part == "env":
                        r = env_fps(dataset, refs, B, a.steps, device, kernel_profile=a.kernel_profile)
                    elif part == "collect":
                        r = collect_fps(dataset, refs, B, a.steps, device)
                    elif part == "ppo":
                        r = ppo_fps(dataset, B, a.steps, device, iterations=2, minibatches=a.minibatches)
                    else:
                        r = ppo_fps(dataset, B, 32, device, total_frames=a.specialist_frames, minibatches=a.minibatches)
                except Exception as e:          # a part that fails is recorded, the others still run
                    r = {"error": f"{type(e).__name__}: {e}"[:500]}
                r["wall_s"] = time.perf_counter() - t0
                rows[str(B)] = r
                fps = r.get("fps")
                print(f"{part:8s} B={B:5d}  " + (f"{fps:12,.0f} frames/s" if fps else r.get("error", ""))
                      + f"   ({r['wall_s']:.0f} s)", flush=True)
                write_result(a.out, result, name="warp_throughput", force=a.force)
    print(json.dumps(result["info"]))
    print(f"wrote {a.out}")
    return result


if __name__ == "__main__":
    sys.exit(0 if main() else 1)
