"""How fast is the tracking environment? Frames (world-steps) per second at B = 64, 2 threads.

Three measurements on the same dataset and references:

* ``BatchedSim`` alone: physics only — the same worlds, start state and servo targets as the env run;
* ``TrackingEnv``: full observation (structured + 273-D), reward, errors, through ``env.rollout``;
* one world through gymnasium (``gymnasium.make("adadex/Tracking-v0")``) wrapped by TorchRL's
  ``GymEnv`` — the path a user without the batched env would take.

Targets: TrackingEnv ≥ 0.85 × BatchedSim; TrackingEnv ≥ 7 × the GymEnv path.

    python benchmarks/env_throughput.py [--dataset DIR] [--worlds 64] [--steps 150] [--out FILE]

Without ``--dataset`` the ``tiny`` preset is built into a temporary folder first.
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from adadex.io import atomic_write_text

RESULTS = Path(__file__).resolve().parent / "results"


def _best(fn, repeats: int) -> float:
    best = float("inf")
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return best


def main(argv=None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--dataset", type=Path, default=None)
    p.add_argument("--worlds", type=int, default=64)
    p.add_argument("--steps", type=int, default=150)
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--repeats", type=int, default=5)
    p.add_argument("--out", type=Path, default=RESULTS / "env_throughput.json")
    a = p.parse_args(argv)
    torch.set_num_threads(1)

    import gymnasium
    from torchrl.envs import GymEnv

    import adadex.envs  # noqa: F401  (registers adadex/Tracking-v0)
    from adadex.data.build import build_dataset
    from adadex.envs.tracking import TrackingEnv

    with tempfile.TemporaryDirectory() as tmp:
        dataset = a.dataset
        if dataset is None:
            dataset = Path(tmp) / "tiny"
            build_dataset("tiny", dataset, seed=4, progress=False)
        B, N = a.worlds, a.steps
        env = TrackingEnv(dataset, num_worlds=B, split=None, nthread=a.threads, seed=0)
        gen = torch.Generator().manual_seed(0)
        actions = [0.02 * (2 * torch.rand(B, 22, generator=gen) - 1) for _ in range(N)]
        start = env.reset()
        state0 = env.sim.state.copy()
        targets0 = env._q_target.clone()
        ctrls = []

        def run_env():
            env.sim.set_state(state0)
            env._q_target = targets0.clone()
            env._t.zero_()
            td = start.clone()
            ctrls.clear()
            for act in actions:
                td.set("action", act)
                td = env.step(td)["next"].exclude("reward", "done", "terminated", "truncated")
                ctrls.append(env._q_target.numpy().copy())

        sim = env.sim

        def run_sim():   # the same worlds, start state and servo targets: physics alone
            sim.set_state(state0)
            for c in ctrls:
                sim.step(c)

        run_env()
        t_env = t_sim = float("inf")
        for _ in range(a.repeats):   # interleaved, best of each: background load hits both alike
            t_env = min(t_env, _best(run_env, 1))
            t_sim = min(t_sim, _best(run_sim, 1))
        env.close()

        genv = GymEnv("adadex/Tracking-v0", dataset=str(dataset), split=None)
        n_gym = max(N // 3, 20)

        def run_gym():
            genv.rollout(n_gym, break_when_any_done=False)

        t_gym = _best(run_gym, a.repeats)
        genv.close()
        del gymnasium

    env_fps, sim_fps, gym_fps = B * N / t_env, B * N / t_sim, n_gym / t_gym
    result = {
        "worlds": B, "steps": N, "threads": a.threads,
        "tracking_env_frames_per_s": env_fps, "batched_sim_frames_per_s": sim_fps, "gym_env_frames_per_s": gym_fps,
        "env_over_sim": env_fps / sim_fps, "env_over_gym": env_fps / gym_fps,
        "targets": {"env_over_sim": 0.85, "env_over_gym": 7.0},
    }
    atomic_write_text(a.out, json.dumps(result, indent=1))
    print(f"B = {B}, {a.threads} threads, {N} steps (best of {a.repeats}):")
    print(f"  BatchedSim (physics only) {sim_fps:9.0f} frames/s")
    print(f"  TrackingEnv               {env_fps:9.0f} frames/s   {env_fps / sim_fps:.2f} × BatchedSim (target 0.85)")
    print(f"  gymnasium + GymEnv, B = 1 {gym_fps:9.0f} frames/s   TrackingEnv is {env_fps / gym_fps:.1f} × (target 7)")
    print(f"wrote {a.out}")
    return result


if __name__ == "__main__":
    np.set_printoptions(precision=3)
    main()
