"""Simulator throughput: control steps per second of three ways to step the scene, in one run.

1. a plain single-thread ``mj_step`` loop (one world),
2. ``mujoco.rollout`` open-loop at B worlds with a persistent thread pool, one call per control
   step (the same work BatchedSim does, without its bookkeeping), and one long call for reference,
3. :class:`adadex.sim.BatchedSim` at B worlds (state kept, readouts sliced every control step).

Target: BatchedSim ≥ 0.95 × the per-control-step rollout figure.

    python benchmarks/sim_throughput.py [--worlds 64] [--threads 2] [--steps 60] [--out FILE]
"""

from __future__ import annotations

import argparse
import os
import platform
import time
from pathlib import Path

import mujoco
import numpy as np
from mujoco import rollout as mj_rollout
from tqdm import tqdm

from _data import check_result, write_result
from adadex.sim.batched import CTRL_SPEC, FULLPHYSICS, BatchedSim
from adadex.sim.robot import joint_limits
from adadex.sim.scene import PHYSICS_TIMESTEP, SUBSTEPS, build_scene_model, home_state

RESULTS = Path(__file__).resolve().parent / "results"


def _ctrl_sequence(model, steps: int, worlds: int, seed: int = 0) -> np.ndarray:
    lim = joint_limits()
    _, home = home_state(model)
    noise = np.random.default_rng(seed).normal(0, 0.03, size=(steps, worlds, model.nu))
    return np.clip(home + np.cumsum(noise, axis=0), lim[:, 0], lim[:, 1])


def bench_mj_step(model, ctrls: np.ndarray) -> float:
    d = mujoco.MjData(model)
    d.qpos[:], _ = home_state(model)
    t0 = time.perf_counter()
    for c in ctrls[:, 0]:
        d.ctrl[:] = c
        for _ in range(SUBSTEPS):
            mujoco.mj_step(model, d)
    return len(ctrls) / (time.perf_counter() - t0)


def _initial_states(model, worlds: int) -> np.ndarray:
    d = mujoco.MjData(model)
    d.qpos[:], _ = home_state(model)
    mujoco.mj_forward(model, d)
    s = np.empty(mujoco.mj_stateSize(model, FULLPHYSICS))
    mujoco.mj_getState(model, d, s, FULLPHYSICS)
    return np.tile(s, (worlds, 1))


def bench_rollout_per_step(model, ctrls: np.ndarray, nthread: int) -> float:
    steps, worlds, nu = ctrls.shape
    models = [model] * worlds
    datas = [mujoco.MjData(model) for _ in range(max(1, nthread))]
    state = _initial_states(model, worlds)
    ctrl_buf = np.empty((worlds, SUBSTEPS, nu))
    state_out = np.empty((worlds, SUBSTEPS, state.shape[1]))
    sens_out = np.empty((worlds, SUBSTEPS, model.nsensordata))
    with mj_rollout.Rollout(nthread=nthread) as pool:
        t0 = time.perf_counter()
        for c in ctrls:
            ctrl_buf[:] = c[:, None, :]
            pool.rollout(models, datas, state, ctrl_buf, control_spec=CTRL_SPEC, skip_checks=True,
                         nstep=SUBSTEPS, state=state_out, sensordata=sens_out)
            state[:] = state_out[:, -1]
        dt = time.perf_counter() - t0
    return steps * worlds / dt


def bench_rollout_long(model, ctrls: np.ndarray, nthread: int) -> float:
    steps, worlds, nu = ctrls.shape
    control = np.ascontiguousarray(np.repeat(ctrls.transpose(1, 0, 2), SUBSTEPS, axis=1))
    datas = [mujoco.MjData(model) for _ in range(max(1, nthread))]
    state = _initial_states(model, worlds)
    with mj_rollout.Rollout(nthread=nthread) as pool:
        t0 = time.perf_counter()
        pool.rollout([model] * worlds, datas, state, control, control_spec=CTRL_SPEC)
        dt = time.perf_counter() - t0
    return steps * worlds / dt


def bench_batched(model, ctrls: np.ndarray, nthread: int) -> float:
    steps, worlds, _ = ctrls.shape
    sim = BatchedSim(model, worlds, nthread=nthread)
    sim.reset(qpos=home_state(model)[0])
    t0 = time.perf_counter()
    for c in ctrls:
        sim.step(c)
    dt = time.perf_counter() - t0
    sim.close()
    return steps * worlds / dt


def main(argv=None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--worlds", type=int, default=64)
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--steps", type=int, default=60, help="control steps per measurement")
    p.add_argument("--repeats", type=int, default=5, help="best of N")
    p.add_argument("--object", default="cube_050")
    p.add_argument("--out", type=Path, default=RESULTS / "sim_throughput.json")
    p.add_argument("--force", action="store_true",
                   help="replace --out even if it is not an earlier result of this benchmark")
    a = p.parse_args(argv)
    check_result(a.out, name="sim_throughput", force=a.force)      # before any work: refuse a file not ours

    model = build_scene_model(a.object)
    ctrls = _ctrl_sequence(model, a.steps, a.worlds)
    single = _ctrl_sequence(model, a.steps * 4, 1)
    runs = {
        "mj_step_single_thread": lambda: bench_mj_step(model, single),
        "rollout_per_control_step": lambda: bench_rollout_per_step(model, ctrls, a.threads),
        "rollout_one_long_call": lambda: bench_rollout_long(model, ctrls, a.threads),
        "batched_sim": lambda: bench_batched(model, ctrls, a.threads),
    }
    # Interleaved repeats, best of each: background load then hits all variants alike.
    res = {k: 0.0 for k in runs}
    for _ in tqdm(range(a.repeats), desc="repeats"):
        for k, f in runs.items():
            res[k] = max(res[k], f())
    ratio = res["batched_sim"] / res["rollout_per_control_step"]
    out = {
        "benchmark": "sim_throughput",
        "unit": "control steps per second (all worlds)",
        "worlds": a.worlds, "threads": a.threads, "control_steps": a.steps,
        "physics_timestep": PHYSICS_TIMESTEP, "substeps": SUBSTEPS, "object": a.object,
        "results": res,
        "batched_over_rollout": ratio,
        "target_batched_over_rollout": 0.95,
        "target_met": bool(ratio >= 0.95),
        "machine": {"cpus": os.cpu_count(), "python": platform.python_version(), "mujoco": mujoco.__version__},
    }
    write_result(a.out, out, name="sim_throughput", force=a.force, indent=2)
    print(f"sim throughput, B={a.worlds}, {a.threads} threads, {SUBSTEPS} substeps/control step "
          f"(control steps/s, all worlds):")
    for k, v in res.items():
        print(f"  {k:<28} {v:10.0f}")
    print(f"  BatchedSim / rollout = {ratio:.3f} (target >= 0.95: {'met' if ratio >= 0.95 else 'NOT met'})")
    print(f"wrote {a.out}")
    return out


if __name__ == "__main__":
    main()
