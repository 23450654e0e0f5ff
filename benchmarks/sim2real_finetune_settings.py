"""Does the ``finetuned_identified_real`` row depend on its learner settings? The tracker fine-tuned on a
``recipes/sim2real.py`` run's identified patch with the pipeline trackers' PPO settings (4,096-frame
batches, γ 0.99, λ 0.95) instead of the modulators' (batches spanning whole episodes, γ 0.998, λ 1),
with the same frames and envs, then evaluated on the run's own episodes and draws on the hidden robot
and paired with the run's ``tracker_real`` row.

    python recipes/sim2real.py real=assets/gaps/payload_soft_arm.json out=runs/s2r_s0 preset=small seed=0
    python benchmarks/sim2real_finetune_settings.py runs/s2r_s0 [--out FILE] [--force]

The fine-tune trains in ``RUN/train/finetuned_identified_tracker_settings/``, inside the run's own
output (a finished one is kept). Prints the
row's completion, its paired difference to ``tracker_real`` and the share of the gap it recovers; writes
the JSON (default ``benchmarks/results/sim2real_finetune_settings.json``). Like the oracle row, it reads
the hidden robot's patch for the evaluation rollouts (as ``HiddenRobot.evaluate`` does).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
from pathlib import Path

import numpy as np

from _data import RESULTS, check_result, refuse, write_result

#: the pipeline trackers' learner (``PPOConfig``'s defaults) in place of the preset's
TRACKER_PPO = {"frames_per_batch": 4096, "gamma": 0.99, "lmbda": 0.95}


def main(argv=None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("run", type=Path, help="a recipes/sim2real.py output folder (its sim2real.json, sysid/patch.json)")
    p.add_argument("--out", type=Path, default=RESULTS / "sim2real_finetune_settings.json")
    p.add_argument("--force", action="store_true")
    a = p.parse_args(argv)
    check_result(a.out, name="sim2real_finetune_settings", force=a.force)
    f = a.run / "sim2real.json"
    if not f.is_file():
        raise refuse("sim2real_finetune_settings", f"{f}: no such file "
                         f"(a recipes/sim2real.py output)")
    from adadex.data.reference import ReferenceDataset
    from adadex.envs.randomization import Randomization
    from adadex.envs.tracking import TrackingConfig, episode_references
    from adadex.eval.paired import paired_bootstrap
    from adadex.modules.tracker import Tracker
    from adadex.sim.patch import ModelPatch
    from adadex.train import sim2real as s2r
    from adadex.transforms.policy import make_policy

    from adadex.io import output_kind

    if output_kind(a.run) != s2r.SIM2REAL_RUN:             # it trains inside the run's folder: only a run's
        raise refuse("sim2real_finetune_settings", f"{a.run}: not a recipes/sim2real.py output")
    res = json.loads(f.read_text())
    seed = int(res["seed"])
    p_ = dataclasses.replace(s2r.preset(res["preset"]), **TRACKER_PPO)
    patch = ModelPatch.load(a.run / "sysid" / "patch.json")
    randomization = Randomization.from_patch(patch) if len(patch.active()) else Randomization()
    ck = s2r.finetune_tracker(a.run / "train" / "finetuned_identified_tracker_settings", dataset=res["dataset"],
                              tracker="replay" if res["tracker"] == "replay" else str(a.run / "tracker.pt"), p=p_,
                              randomization=randomization, seed=seed, name="ft_tracker_settings", progress=False)
    ds = ReferenceDataset(res["dataset"])
    refs = episode_references(ds, (p_.split, "test"), p_.window) * p_.eval_repeats
    policy = make_policy(Tracker.load(ck).freeze(), None, channels="none")
    ev = s2r.HiddenRobot(res["real"]).evaluate(policy, ds, refs, max_worlds=64, config=TrackingConfig(window=p_.window),
                                               randomize=Randomization(), seed=20_000 + seed, progress=False,
                                               nthread=2, env_transform=policy.primer)
    base, nominal = res["per_episode"]["tracker_real"], res["per_episode"]["tracker_nominal"]
    if ev["per_episode"]["reference"] != base["reference"]:
        raise refuse("sim2real_finetune_settings",
                     f"{a.run}: the run's episodes were not reproduced (another dataset or code than the run's)")
    a_, b_ = (np.asarray(x["completion"]) * 100 for x in (ev["per_episode"], base))
    d = paired_bootstrap(a_, b_, np.asarray(base["reference"]), seed=seed)
    gap = float(np.mean(np.asarray(nominal["completion"]) * 100 - b_))
    out = {"run": str(a.run), "seed": seed, "settings": TRACKER_PPO, "completion_pct": float(a_.mean()),
           "vs_tracker_real_points": {"estimate": d["estimate"], "ci95": d["ci95"]},
           "recovered_fraction": (float(a_.mean()) - float(b_.mean())) / gap if gap > 0 else None,
           "per_episode": ev["per_episode"]}
    ci = d["ci95"]
    print(f"{a.run} (seed {seed}): fine-tuned with {TRACKER_PPO}: completion {out['completion_pct']:.1f} %, "
          f"vs tracker_real {d['estimate']:+.1f} [{ci[0]:+.1f}, {ci[1]:+.1f}], recovered "
          + ("n/a" if out["recovered_fraction"] is None else f"{out['recovered_fraction']:.2f}"))
    write_result(a.out, out, name="sim2real_finetune_settings", force=a.force)
    print(f"wrote {a.out}")
    return out


if __name__ == "__main__":
    main()
