"""What does the policy graph cost? Frames/s of TrackingEnv (B = 64) driven by the tracker alone
versus by the modulated graph, both ways it can be run.

* ``tracker``: ``env.rollout(N, tracker)`` on a plain TrackingEnv;
* ``transformed env``: ``TransformedEnv(env, modulation("R+O+T", tracker, view=modulator.view))`` driven by the modulator
  (the modulator's training setup);
* ``make_policy``: the same graph as one policy on the plain env (+ its primer).

Networks have the default sizes (512, 256, 128); torch runs on one thread, MuJoCo on two.

    python benchmarks/policy_throughput.py [--dataset DIR] [--worlds 64] [--steps 100] [--out FILE]
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import torch

from _data import RESULTS, dataset_or_tiny, check_result, write_result




def main(argv=None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--dataset", type=Path, default=None)
    p.add_argument("--worlds", type=int, default=64)
    p.add_argument("--steps", type=int, default=100)
    p.add_argument("--channels", default="R+O+T")
    p.add_argument("--out", type=Path, default=RESULTS / "policy_throughput.json")
    p.add_argument("--force", action="store_true",
                   help="replace --out even if it is not an earlier result of this benchmark")
    a = p.parse_args(argv)
    check_result(a.out, name="policy_throughput", force=a.force)      # before any work: refuse a file not ours
    torch.set_num_threads(1)

    from torchrl.envs import TransformedEnv
    from torchrl.envs.utils import ExplorationType, set_exploration_type

    from adadex.envs.tracking import TrackingConfig, TrackingEnv
    from adadex.modules.modulator import Modulator
    from adadex.modules.tracker import Tracker
    from adadex.transforms.modulation import modulation
    from adadex.transforms.policy import make_policy

    torch.manual_seed(0)
    tracker = Tracker().freeze()
    modulator = Modulator(a.channels)
    policy = make_policy(tracker, modulator)
    cfg = TrackingConfig(terminate_object_error=0, terminate_palm_error=0)   # same work in every run
    fps = {}
    with dataset_or_tiny(a.dataset) as dataset:
        runs = {
            "tracker": (lambda: TrackingEnv(dataset, num_worlds=a.worlds, split=None, config=cfg), tracker.actor),
            "transformed env": (lambda: TransformedEnv(TrackingEnv(dataset, num_worlds=a.worlds, split=None, config=cfg),
                                                       modulation(a.channels, tracker, view=modulator.view)), modulator.actor),
            "make_policy": (lambda: TransformedEnv(TrackingEnv(dataset, num_worlds=a.worlds, split=None, config=cfg),
                                                   policy.primer()), policy),
        }
        for name, (make, pol) in runs.items():
            env = make()
            best = float("inf")
            for _ in range(3):
                env.set_seed(0)
                t0 = time.perf_counter()
                with torch.no_grad(), set_exploration_type(ExplorationType.RANDOM):
                    env.rollout(a.steps, pol, break_when_any_done=False)
                best = min(best, time.perf_counter() - t0)
            env.close()
            fps[name] = a.worlds * a.steps / best
    result = {"worlds": a.worlds, "steps": a.steps, "channels": a.channels, "frames_per_s": fps,
              "modulated_over_tracker": {k: v / fps["tracker"] for k, v in fps.items()}}
    write_result(a.out, result, name="policy_throughput", force=a.force, indent=1)
    print(f"B = {a.worlds}, {a.steps} steps, channels {a.channels} (best of 3):")
    for k, v in fps.items():
        print(f"  {k:<16} {v:7.0f} frames/s   {v / fps['tracker']:.2f} × tracker alone")
    print(f"wrote {a.out}")
    return result


if __name__ == "__main__":
    main()
