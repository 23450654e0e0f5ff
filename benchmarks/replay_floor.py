"""The floor every learned tracker must beat: kinematic replay of the reference on TrackingEnv.

Runs :func:`adadex.envs.replay.replay_policy` once over every reference of a split (default: the
``small`` dataset's unseen-trajectory test part), with the paper's metrics: mean errors and both
success rates (mean-error and completion).

    python benchmarks/replay_floor.py [--dataset DIR] [--split unseen_trajectory] [--part test] [--out FILE]
    python benchmarks/replay_floor.py --randomize [--action-noise-scale 10]

``--action-noise-scale`` multiplies Table 3's action-noise standard deviations (the env adds them in
units of the action bound, 0.1 rad; 10 gives the radian reading used before 2026-11-25).

Without ``--dataset`` the ``small`` preset is built into ``data/small`` first (a few minutes).
"""

from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path

from _data import check_result, write_result

RESULTS = Path(__file__).resolve().parent / "results"
ROOT = Path(__file__).resolve().parents[1]


def main(argv=None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--dataset", type=Path, default=None)
    p.add_argument("--split", default="unseen_trajectory")
    p.add_argument("--part", default="test")
    p.add_argument("--randomize", action="store_true", help="with Table 3 domain randomization")
    p.add_argument("--action-noise-scale", type=float, default=1.0,
                   help="with --randomize: multiply Table 3's action-noise stds by this (default 1)")
    p.add_argument("--max-worlds", type=int, default=64, help="worlds stepped together (default 64)")
    p.add_argument("--out", type=Path, default=RESULTS / "replay_floor.json")
    p.add_argument("--force", action="store_true",
                   help="replace --out even if it is not an earlier result of this benchmark")
    a = p.parse_args(argv)
    check_result(a.out, name="replay_floor", force=a.force)      # before any work: refuse a file not ours

    from adadex.data.build import build_dataset
    from adadex.envs.randomization import Randomization
    from adadex.envs.replay import replay_policy
    from adadex.eval.evaluate import evaluate, format_summary

    dataset = a.dataset
    if dataset is None:
        dataset = ROOT / "data" / "small"
        if not (dataset / "index.json").exists():
            build_dataset("small", dataset, seed=0)
    table3 = Randomization()
    scale = a.action_noise_scale
    randomize = dataclasses.replace(table3, action_noise_correlated=scale * table3.action_noise_correlated,
                                    action_noise_uncorrelated=scale * table3.action_noise_uncorrelated)
    res = evaluate(replay_policy(), dataset, split=(a.split, a.part), max_worlds=a.max_worlds,
                   randomize=randomize if a.randomize else None)
    summary = res["summary"]
    result = {"dataset": str(dataset), "split": [a.split, a.part], "references": res["references"],
              "randomize": a.randomize, "action_noise_scale": a.action_noise_scale if a.randomize else None,
              "steps": res["steps"], "wall_s": res["wall_s"], **summary,
              "per_reference": res["per_reference"]}
    write_result(a.out, result, name="replay_floor", force=a.force, indent=1)
    noise = f", action noise × {a.action_noise_scale:g}" if a.randomize and a.action_noise_scale != 1 else ""
    print(f"kinematic replay on {res['references']} references of {a.split}/{a.part}"
          f"{' with randomization' if a.randomize else ''}{noise} ({res['wall_s']:.0f} s):")
    print(format_summary(summary))
    print(f"wrote {a.out}")
    return result


if __name__ == "__main__":
    main()
