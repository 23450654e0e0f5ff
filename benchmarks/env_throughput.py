"""How fast is the tracking environment? Frames (world-steps) per second at B = 64, 2 threads.

Three measurements on the same dataset and references:

* ``BatchedSim`` alone: physics only — the same worlds, start state and servo targets as the env run;
* ``TrackingEnv``: full observation (structured + 273-D), reward, errors, through ``env.step``;
* one world through gymnasium (``gymnasium.make("adadex/Tracking-v0")``) wrapped by TorchRL's
  ``GymEnv``, through ``rollout`` — the path a user without the batched env would take.

All three run the same precomputed actions (no policy or random sampling is timed) over one
episode window from a reset state.

Targets: TrackingEnv ≥ 0.85 × BatchedSim; TrackingEnv ≥ 7 × the GymEnv path. The three are timed back
to back in each of ``--repeats`` interleaved repeats; a ratio is the median over repeats of the ratio
within a repeat (background load on a shared machine moves all three alike within a repeat, and
by ±10 % between repeats). Resets are timed in none of the three paths. The JSON also holds
``sim_over_gym``, BatchedSim alone over the GymEnv path: the ceiling of ``env_over_gym``.

    python benchmarks/env_throughput.py [--dataset DIR] [--worlds 64] [--steps 60] [--repeats 30] [--out FILE]

Without ``--dataset`` the ``tiny`` preset is built into a temporary folder first.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
import torch

from _data import RESULTS, dataset_or_tiny, check_result, write_result




def main(argv=None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--dataset", type=Path, default=None)
    p.add_argument("--worlds", type=int, default=64)
    p.add_argument("--steps", type=int, default=60)     # one episode window
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--repeats", type=int, default=30)
    p.add_argument("--out", type=Path, default=RESULTS / "env_throughput.json")
    p.add_argument("--force", action="store_true",
                   help="replace --out even if it is not an earlier result of this benchmark")
    a = p.parse_args(argv)
    check_result(a.out, name="env_throughput", force=a.force)      # before any work: refuse a file not ours
    torch.set_num_threads(1)

    from torchrl.envs import GymEnv

    import adadex.envs  # noqa: F401  (registers adadex/Tracking-v0)
    from adadex.envs.tracking import TrackingEnv

    with dataset_or_tiny(a.dataset) as dataset:
        B, N = a.worlds, a.steps
        env = TrackingEnv(dataset, num_worlds=B, split=None, nthread=a.threads, seed=0)
        gen = torch.Generator().manual_seed(0)
        actions = [0.02 * (2 * torch.rand(B, 22, generator=gen) - 1) for _ in range(N)]
        start = env.reset()
        state0 = env.sim.state.copy()
        targets0 = env._q_target.copy()
        ctrls = []

        def run_env():
            env.sim.set_state(state0)
            env._q_target[:] = targets0
            env._t[:] = 0
            td = start.clone()
            ctrls.clear()
            for act in actions:
                td.set("action", act)
                td = env.step(td)["next"].exclude("reward", "done", "terminated", "truncated")
                ctrls.append(env._q_target.copy())

        sim = env.sim

        def run_sim():   # the same worlds, start state and servo targets: physics alone
            sim.set_state(state0)
            for c in ctrls:
                sim.step(c)

        genv = GymEnv("adadex/Tracking-v0", dataset=str(dataset), split=None)
        gym_start = genv.reset()
        gym_actions = [act[:1] for act in actions]

        def run_gym():   # one world from a reset state, precomputed actions as above (resets untimed)
            it = iter(gym_actions)
            genv.rollout(N, policy=lambda td: td.set("action", next(it)), break_when_any_done=False,
                         auto_reset=False, tensordict=gym_start.clone())

        def timed(fn) -> float:
            t0 = time.perf_counter()
            fn()
            return time.perf_counter() - t0

        run_env(), run_sim(), run_gym()   # warm-up
        # Interleaved repeats: each repeat times the three paths back to back, so a ratio compares
        # runs made under the same background load; the targets are judged on the median ratio.
        t = np.array([[timed(run_env), timed(run_sim), timed(run_gym)] for _ in range(a.repeats)])
        env.close()
        genv.close()

    fps = np.stack([B * N / t[:, 0], B * N / t[:, 1], N / t[:, 2]], axis=1)
    over_sim, over_gym = fps[:, 0] / fps[:, 1], fps[:, 0] / fps[:, 2]
    ceiling = fps[:, 1] / fps[:, 2]   # what an env with no overhead at all would reach over the GymEnv path
    best = fps.max(axis=0)
    result = {
        "worlds": B, "steps": N, "threads": a.threads, "repeats": a.repeats,
        "tracking_env_frames_per_s": float(best[0]), "batched_sim_frames_per_s": float(best[1]),
        "gym_env_frames_per_s": float(best[2]),
        "env_over_sim": float(np.median(over_sim)), "env_over_gym": float(np.median(over_gym)),
        "env_over_sim_range": [float(over_sim.min()), float(over_sim.max())],
        "env_over_gym_range": [float(over_gym.min()), float(over_gym.max())],
        "sim_over_gym": float(np.median(ceiling)),
        "per_repeat_frames_per_s": fps.round(1).tolist(),
        "targets": {"env_over_sim": 0.85, "env_over_gym": 7.0},
    }
    write_result(a.out, result, name="env_throughput", force=a.force, indent=1)
    print(f"B = {B}, {a.threads} threads, {N} steps; {a.repeats} interleaved repeats (best frames/s; median ratio "
          f"over repeats, range in brackets):")
    print(f"  BatchedSim (physics only) {best[1]:9.0f} frames/s")
    print(f"  TrackingEnv               {best[0]:9.0f} frames/s   {np.median(over_sim):.2f} × BatchedSim "
          f"[{over_sim.min():.2f}–{over_sim.max():.2f}] (target 0.85)")
    print(f"  gymnasium + GymEnv, B = 1 {best[2]:9.0f} frames/s   TrackingEnv is {np.median(over_gym):.1f} × "
          f"[{over_gym.min():.1f}–{over_gym.max():.1f}] (target 7)")
    print(f"  (BatchedSim alone is {np.median(ceiling):.1f} × the GymEnv path: the most any env over it can reach)")
    print(f"wrote {a.out}")
    return result


if __name__ == "__main__":
    np.set_printoptions(precision=3)
    main()
