"""The floor every learned tracker must beat: kinematic replay of the reference on TrackingEnv.

Runs :func:`adadex.envs.replay.replay_policy` once over every reference of a split (default: the
``small`` dataset's unseen-trajectory test part), with the paper's metrics: mean errors and both
success rates (mean-error and completion).

    python benchmarks/replay_floor.py [--dataset DIR] [--split unseen_trajectory] [--part test] [--out FILE]

Without ``--dataset`` the ``small`` preset is built into ``data/small`` first (a few minutes).
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import torch

from adadex.io import atomic_write_text

RESULTS = Path(__file__).resolve().parent / "results"
ROOT = Path(__file__).resolve().parents[1]


def main(argv=None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--dataset", type=Path, default=None)
    p.add_argument("--split", default="unseen_trajectory")
    p.add_argument("--part", default="test")
    p.add_argument("--randomize", action="store_true", help="with Table 3 domain randomization")
    p.add_argument("--out", type=Path, default=RESULTS / "replay_floor.json")
    a = p.parse_args(argv)

    from adadex.data.build import build_dataset
    from adadex.envs.randomization import Randomization
    from adadex.envs.replay import replay_policy
    from adadex.envs.tracking import TrackingEnv
    from adadex.eval.metrics import from_rollout, summarize

    dataset = a.dataset
    if dataset is None:
        dataset = ROOT / "data" / "small"
        if not (dataset / "index.json").exists():
            build_dataset("small", dataset, seed=0)
    env = TrackingEnv(dataset, num_worlds=1, split=(a.split, a.part), draw="cycle")
    n = len(env.references)
    env.close()
    env = TrackingEnv(dataset, num_worlds=n, split=(a.split, a.part), draw="cycle",
                      randomize=Randomization() if a.randomize else None)
    steps = env.config.window - 1
    t0 = time.perf_counter()
    with torch.no_grad():
        td = env.rollout(steps, replay_policy(), break_when_any_done=False)
    wall = time.perf_counter() - t0
    per = from_rollout(td, lengths=torch.full((n,), steps))
    summary = summarize(per)
    result = {"dataset": str(dataset), "split": [a.split, a.part], "references": n, "randomize": a.randomize,
              "steps": steps, "wall_s": wall, "unstable_worlds": env.unstable_count, **summary,
              "per_reference": {name: {"success_mean_error": bool(per["success_mean_error"][i]),
                                       "completion": float(per["completion"][i]), "frames": int(per["frames"][i])}
                                for i, name in enumerate(env.current_references)}}
    env.close()
    atomic_write_text(a.out, json.dumps(result, indent=1))
    print(f"kinematic replay on {n} references of {a.split}/{a.part}"
          f"{' with randomization' if a.randomize else ''} ({wall:.0f} s):")
    print(f"  success: mean-error {summary['success_mean_error_pct']:.1f} %, completion {summary['completion_pct']:.1f} %")
    print(f"  T_o {summary['T_o']:.1f} cm, R_o {summary['R_o']:.2f} rad, T_h {summary['T_h']:.1f} cm, "
          f"R_h {summary['R_h']:.2f} rad, E_finger {summary['E_finger']:.3f} rad")
    print(f"wrote {a.out}")
    return result


if __name__ == "__main__":
    main()
