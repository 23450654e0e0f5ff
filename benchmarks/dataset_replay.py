"""What a change to the reference datasets does to kinematic replay: two builds, paired by reference name.

Replays every reference both builds hold (the same name, each with an episode window), in name order,
``--repeats`` times, on the same env seed, so episode k meets the same draws in both (the env draws start
states and noise independently of the actions and of the reference's joints); prints each build's summary
and the paired differences (after − before) with 95 % bootstrap intervals over references.

    python benchmarks/dataset_replay.py --before data/small_pg --after data/small_pg_new
    python benchmarks/dataset_replay.py --before data/small_pg --after data/small_pg_new --randomize --repeats 4 --seed 777

Made for the planned grasp's approach fix (2026-12-07, docs/references.md): whether a new build's references
are easier to follow, on the references the builds share, and no other.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from _data import check_result, refuse, write_result

NAME = "dataset_replay"
RESULTS = Path(__file__).resolve().parent / "results"
#: per-episode fields compared (in %, except T_h in cm and R_h in rad)
FIELDS = ("completion", "object_completion", "carried", "ended_early", "ended_palm", "T_h", "R_h")
SCALE = {"T_h": 100.0, "R_h": 1.0}


def main(argv=None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--before", type=Path, required=True, help="the earlier build (a dataset folder)")
    p.add_argument("--after", type=Path, required=True, help="the later build (a dataset folder)")
    p.add_argument("--randomize", action="store_true", help="with Table 3 domain randomization")
    p.add_argument("--repeats", type=int, default=1, help="episodes per reference, one draw each (default 1)")
    p.add_argument("--seed", type=int, default=0, help="the env seed (default 0)")
    p.add_argument("--max-worlds", type=int, default=64, help="worlds stepped together (default 64)")
    p.add_argument("--out", type=Path, default=RESULTS / "dataset_replay.json")
    p.add_argument("--force", action="store_true",
                   help="replace --out even if it is not an earlier result of this benchmark")
    a = p.parse_args(argv)
    check_result(a.out, name=NAME, force=a.force)
    if a.repeats < 1:
        raise refuse(NAME, f"--repeats must be ≥ 1, got {a.repeats}")

    from adadex.data.reference import ReferenceDataset
    from adadex.envs.randomization import Randomization
    from adadex.envs.replay import replay_policy
    from adadex.envs.tracking import TrackingConfig, episode_references
    from adadex.errors import AdadexError
    from adadex.eval.evaluate import evaluate, format_summary
    from adadex.eval.paired import paired_bootstrap

    builds = {}
    for flag, path in (("--before", a.before), ("--after", a.after)):
        try:
            ds = ReferenceDataset(path)
        except (AdadexError, OSError) as e:
            raise refuse(NAME, f"{flag} {path}: {e}") from None
        builds[flag] = (ds, {ds.entries[i]["name"]: i for i in episode_references(ds, None, TrackingConfig().window)})
    names = sorted(set(builds["--before"][1]) & set(builds["--after"][1]))
    if not names:
        raise refuse(NAME, f"--before {a.before} and --after {a.after} share no reference (by name) with an "
                           f"episode window")
    result = {"before": str(a.before), "after": str(a.after), "references": len(names), "repeats": a.repeats,
              "seed": a.seed, "randomize": a.randomize, "names": names}
    episodes = {}
    for flag, key in (("--before", "before"), ("--after", "after")):
        ds, index = builds[flag]
        res = evaluate(replay_policy(), ds, split=None, references=[index[n] for n in names] * a.repeats,
                       randomize=Randomization() if a.randomize else None, seed=a.seed, max_worlds=a.max_worlds)
        episodes[key] = res["per_episode"]
        result[f"{key}_summary"] = res["summary"]
        print(f"replay on {key} ({ds.path}, {len(names)} references × {a.repeats}"
              f"{', Table 3' if a.randomize else ', nominal'}, {res['wall_s']:.0f} s):")
        print(format_summary(res["summary"]))
    groups = np.asarray(names * a.repeats)
    result["diff"] = {}
    for f in FIELDS:
        scale = SCALE.get(f, 100.0)
        d = paired_bootstrap(scale * np.asarray(episodes["after"][f], float),
                             scale * np.asarray(episodes["before"][f], float), groups)
        result["diff"][f] = {"diff": d["estimate"], "ci95": d["ci95"]}
    print(f"after − before, paired over {len(groups)} episodes: " + ", ".join(
        f"{f} {v['diff']:+.2f} [{v['ci95'][0]:+.2f}, {v['ci95'][1]:+.2f}]" for f, v in result["diff"].items()))
    result["per_episode"] = {"name": list(groups), **{f"{k}_{f}": episodes[k][f] for k in episodes for f in FIELDS}}
    write_result(a.out, result, name=NAME, force=a.force)
    print(f"wrote {a.out}")
    return result


if __name__ == "__main__":
    main()
