"""Does the reward want channel A's reach, and where? Forced reach against none around kinematic replay,
paired per episode, by the object's start offset — the cheap check before training A.

Channel A (:class:`adadex.transforms.modulation.AnchorReach`) decides once per episode how far the palm
reaches onto an object Table 3 moved. A modulator can only learn *when* to reach if the reward tells the
cases apart. This runs replay twice on the same episodes (same references, Table 3 draws and env seed):
with A latched at full reach (``w = 1``, the object anchor's whole shift) and at none (``w = 0``, replay
itself), under each ``--weights`` value of ``RewardConfig.w_object_success``; the physics is the same
for every weight, only the returns differ. Printed per weight and per bin of the object's horizontal
start offset: the paired return difference (reach − none) with its standard error, and the completion,
object completion and carried differences; then what choosing per bin by the reward would give (reach
where the bin's mean return difference is positive) against none and against reaching everywhere — the
most a choice by offset can add under that reward, on these episodes.

    python benchmarks/reach_by_offset.py --dataset data/small_pg [--split train] [--weights 1,2] [--seed 777]
        [--modulation reach_lookahead=4]
"""

from __future__ import annotations

import argparse
import dataclasses
import time
from pathlib import Path

import numpy as np

from _data import refuse, result_arguments, settings, write_result
from modulator_quality import OFFSET_BINS, first_step

#: per-episode field → the name printed (each × 100: the fraction of the episode's frames)
FIELDS = {"completion": "completion", "object_completion": "object", "carried": "carried"}


def forced_reach(reach: bool):
    """Channel A alone, untrained, its reach latched at full (``reach``) or none: the head's mean far past
    the clip (``w = clip(0.5 + tanh(±5), 0, 1)``), its weights zero, so every episode latches the same."""
    import torch

    from adadex.modules.modulator import Modulator

    m = Modulator("A", hidden=(8,))
    head = m.actor._sampling_parts[0].heads[0]
    with torch.no_grad():
        head.weight.zero_()
        head.bias.zero_()
        head.bias[0] = 5.0 if reach else -5.0
    return m


def main(argv=None) -> dict:
    from adadex.data.reference import ReferenceDataset
    from adadex.envs.randomization import Randomization
    from adadex.envs.reward import RewardConfig
    from adadex.envs.tracking import TrackingConfig, episode_references
    from adadex.eval.evaluate import evaluate
    from adadex.modules.tracker import Tracker
    from adadex.transforms.policy import make_policy

    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--dataset", type=Path, required=True)
    p.add_argument("--split", default="train", choices=("train", "test"),
                   help="the unseen-trajectory references' part (default train: what a modulator trains on)")
    p.add_argument("--weights", default="1,2", help="RewardConfig.w_object_success values (default 1,2)")
    p.add_argument("--repeats", type=int, default=4, help="Table 3 draws per reference (default 4)")
    p.add_argument("--seed", type=int, default=777, help="the env seed (default 777)")
    p.add_argument("--modulation", default="", help="ModulationConfig settings k=v,… for channel A, e.g. "
                                                     "'reach_lookahead=4'")
    a = result_arguments(p, "reach_by_offset")(argv)
    try:
        weights = [float(w) for w in a.weights.split(",")]
    except ValueError:
        raise refuse("reach_by_offset", f"--weights must be numbers, got {a.weights!r}") from None
    from adadex.errors import ConfigError
    from adadex.modules.channels import ModulationConfig

    modulation = settings(a.modulation, ModulationConfig(), "--modulation", "reach_by_offset")
    try:
        mconfig = ModulationConfig(**modulation)
    except ConfigError as e:
        raise refuse("reach_by_offset", f"--modulation: {e}") from None
    t0 = time.perf_counter()
    ds = ReferenceDataset(a.dataset)
    tracker = Tracker.replay().freeze()
    episodes = episode_references(ds, ("unseen_trajectory", a.split), TrackingConfig().window) * a.repeats
    result = {"benchmark": "reach_by_offset", "dataset": str(a.dataset), "split": f"unseen_trajectory {a.split}",
              "episodes": len(episodes), "seed": a.seed, "modulation": modulation, "offset_bins_cm": [100 * b for b in OFFSET_BINS[:-1]],
              "weights": {}}
    offset = None
    for w in weights:
        config = dataclasses.replace(TrackingConfig(), reward=RewardConfig(w_object_success=w))
        runs = {}
        for name in ("reach", "none"):
            policy = make_policy(tracker, forced_reach(name == "reach"), config=mconfig)
            res = evaluate(policy, ds, split=None, references=episodes, max_worlds=64, env_transform=policy.primer,
                           config=config, randomize=Randomization(), seed=a.seed, progress=False, nthread=2)
            runs[name] = {k: np.asarray(v, float) for k, v in res["per_episode"].items()
                          if k in ("return", *FIELDS)}
            if offset is None:
                offset = first_step(policy, ds, episodes, config, seed=a.seed)[1]
        diff = {k: runs["reach"][k] - runs["none"][k] for k in ("return", *FIELDS)}
        bins, choice = [], np.zeros(len(episodes), bool)
        print(f"w_object_success={w:g}: return reach − none {diff['return'].mean():+.1f} "
              f"(SE {diff['return'].std() / np.sqrt(len(episodes)):.1f}) over {len(episodes)} episodes", flush=True)
        for lo, hi in zip(OFFSET_BINS[:-1], OFFSET_BINS[1:]):
            m = (offset >= lo) & (offset < hi)
            n = int(m.sum())
            entry = {"offset_cm": [100 * lo, None if hi == float("inf") else 100 * hi], "episodes": n}
            if n:
                entry["return"] = float(diff["return"][m].mean())
                entry["return_se"] = float(diff["return"][m].std() / np.sqrt(n))
                entry.update({FIELDS[k]: float(100 * diff[k][m].mean()) for k in FIELDS})
                choice[m] = entry["return"] > 0
            bins.append(entry)
            print(f"  {100 * lo:3.0f}–{'' if hi == float('inf') else f'{100 * hi:.0f}'} cm  {n:4d} episodes  "
                  + ("" if not n else f"return {entry['return']:+7.1f} (SE {entry['return_se']:5.1f})  "
                     + "  ".join(f"{FIELDS[k]} {entry[FIELDS[k]]:+6.1f}" for k in FIELDS)), flush=True)
        chosen = {k: np.where(choice, runs["reach"][k], runs["none"][k]) for k in FIELDS}
        by_reward = {"reach_fraction": float(choice.mean()),
                     "vs_none": {FIELDS[k]: float(100 * (chosen[k] - runs["none"][k]).mean()) for k in FIELDS},
                     "vs_reach": {FIELDS[k]: float(100 * (chosen[k] - runs["reach"][k]).mean()) for k in FIELDS},
                     "return_vs_reach": float(np.where(choice, 0.0, -diff["return"]).mean())}
        print(f"  choosing per bin by the reward (reach in {by_reward['reach_fraction']:.0%} of episodes): vs none "
              + ", ".join(f"{k} {v:+.1f}" for k, v in by_reward["vs_none"].items()) + "; vs reaching everywhere "
              + ", ".join(f"{k} {v:+.1f}" for k, v in by_reward["vs_reach"].items())
              + f", return {by_reward['return_vs_reach']:+.1f} an episode", flush=True)
        result["weights"][f"{w:g}"] = {"return": float(diff["return"].mean()),
                                       "return_se": float(diff["return"].std() / np.sqrt(len(episodes))),
                                       **{FIELDS[k]: float(100 * diff[k].mean()) for k in FIELDS},
                                       "by_offset": bins, "chosen_by_reward": by_reward}
    result["wall_s"] = time.perf_counter() - t0
    write_result(a.out, result, name="reach_by_offset", force=a.force, indent=1)
    print(f"wrote {a.out} ({result['wall_s'] / 60:.1f} min)")
    return result


if __name__ == "__main__":
    main()
