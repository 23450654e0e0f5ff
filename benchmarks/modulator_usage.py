"""Can a modulator setting learn, and does a trained modulator help? Two checks, paired on the same draws.

``--init-check`` — the cheap check before a long run: per channel set and exploration scale, an
*untrained* modulator around a frozen tracker (kinematic replay by default, ``Tracker.replay()``;
or ``--tracker PATH``), run deterministically and sampled as the collectors sample it, against the
tracker alone, on the unseen-trajectory test references under Table 3 (``--repeats`` draws each,
the same draws for every row). A setting whose *sampled* modulator costs the tracker more than a
point wrecks the episodes PPO learns from (the issue that sized ``CHANNELS[c].init_scale``).
Printed per row: completion and object completion, the paired difference to the tracker with its
bootstrap interval over references (:func:`adadex.eval.paired.paired_bootstrap`), and the edit size
(mean |a| per action entry)::

    python benchmarks/modulator_usage.py --init-check --dataset data/small_pg [--channels R,T,O,R+O+T]
        [--scales default,0.05,0.5] [--modes deterministic,sampled] [--repeats 4] [--references 0]
        [--tracker PATH] [--out FILE]

A channel set may carry :class:`~adadex.modules.modulator.Modulator` settings, ``C+T:prior=anchor``
(C's palm around the object anchor's shift: deterministic and untrained, it is the anchored
feed-forward) or ``C:hold=10:hold_C=0.5`` (C's exploration noise held for 10 steps at scale 0.5).

Without it: one row of a finished ``recipes/pipeline.py`` run (default ``ROT``, seed 0) — how much the
trained modulator moves each channel and its completion, against a freshly initialised one of the
same shape::

    python benchmarks/modulator_usage.py --run runs/table1 [--row ROT] [--seed 0] [--references 16] [--out FILE]
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from _data import check_result, refuse, write_result

RESULTS = Path(__file__).resolve().parent / "results"


def _paired(row: dict, base: dict, metric: str) -> dict:
    from adadex.eval.paired import paired_bootstrap

    a, b = row["per_episode"], base["per_episode"]
    assert a["reference"] == b["reference"] and a["repeat"] == b["repeat"]
    d = paired_bootstrap(100.0 * np.asarray(a[metric], float), 100.0 * np.asarray(b[metric], float),
                         a["reference"], None)
    return {"diff": d["estimate"], "ci95": d["ci95"]}


def modulator_options(spec: str) -> tuple[str, dict]:
    """``CHANNELS[:option=value …]`` → (channels, Modulator settings): ``prior=anchor`` (with
    ``prior_reach=M`` and ``prior_lookahead=N``), ``hold=K`` (``hold_steps``), ``hold_X=scale``
    (channel X's ``hold_scale``), ``decide=K`` (``decide_every``)."""
    channels, *options = spec.split(":")
    out = {}
    for option in options:
        key, _, value = option.partition("=")
        try:
            if key == "prior":
                out["prior"] = value
            elif key == "prior_reach":
                out["prior_reach"] = float(value)
            elif key == "prior_lookahead":
                out["prior_lookahead"] = int(value)
            elif key == "hold":
                out["hold_steps"] = int(value)
            elif key.startswith("hold_"):
                out.setdefault("hold_scale", {})[key[5:]] = float(value)
            elif key == "decide":
                out["decide_every"] = int(value)
            else:
                raise refuse("modulator_usage", f"--channels: unknown option {key!r} in {spec!r} "
                                                "(prior=, prior_reach=, prior_lookahead=, hold=, hold_X=, decide=K)")
        except ValueError:
            raise refuse("modulator_usage", f"--channels: {option!r} in {spec!r} needs a number") from None
    return channels, out


def init_check(a) -> dict:
    from adadex.data.reference import ReferenceDataset
    from adadex.envs.randomization import Randomization
    from adadex.envs.tracking import TrackingConfig, episode_references
    from adadex.eval.evaluate import evaluate
    from adadex.eval.figures import channel_usage
    from adadex.modules.channels import ModulationLayout
    from adadex.modules.modulator import Modulator, channel_scales
    from adadex.modules.tracker import Tracker
    from adadex.transforms.policy import make_policy

    specs = [(spec, *modulator_options(spec)) for spec in a.channels.split(",")]     # bad input: before any work
    ds = ReferenceDataset(a.dataset)
    config = TrackingConfig()
    refs = episode_references(ds, ("unseen_trajectory", "test"), config.window)
    if a.references:
        refs = refs[: a.references]
    tracker = Tracker.load(a.tracker).freeze() if a.tracker else Tracker.replay()
    episodes = refs * a.repeats

    def run(policy, sample=False, seed=0):
        torch.manual_seed(seed)
        return evaluate(policy, ds, split=None, references=episodes, max_worlds=a.worlds,
                        env_transform=policy.primer, config=config, randomize=Randomization(), seed=a.seed,
                        progress=False, keep_rollouts=True, sample=sample, nthread=2)

    def summary(res):
        s = res["summary"]
        return {k: s[k] for k in ("completion_pct", "object_completion_pct", "carried_pct", "T_o")}

    t0 = time.perf_counter()
    base = run(make_policy(tracker, None, channels="none"))
    result = {"benchmark": "modulator_usage --init-check", "dataset": str(a.dataset),
              "tracker": a.tracker or "replay", "episodes": len(episodes), "references": len(refs),
              "repeats": a.repeats, "seed": a.seed, "condition": "unseen_trajectory test, Table 3",
              "tracker_alone": summary(base), "rows": []}
    print(f"tracker alone ({result['tracker']}): completion {base['summary']['completion_pct']:.1f} %, "
          f"object completion {base['summary']['object_completion_pct']:.1f} % ({len(episodes)} episodes)",
          flush=True)
    for spec, channels, options in specs:
        layout = ModulationLayout(channels)
        for scale in a.scales.split(","):
            init = None if scale == "default" else float(scale)
            torch.manual_seed(a.seed)
            mod = Modulator(channels, hidden=(256, 256, 128), init_scale=init, **options)
            policy = make_policy(tracker, mod, channels=channels)
            modes = (("deterministic", False), ("sampled", True)) if scale == a.scales.split(",")[0] else \
                (("sampled", True),)
            modes = tuple(m for m in modes if m[0] in a.modes.split(","))
            for mode, sample in modes:
                res = run(policy, sample=sample, seed=a.seed)
                row = {"channels": layout.name, "options": options, "init_scale": channel_scales(layout, init), "mode": mode,
                       **summary(res), "channel_usage": channel_usage(res["rollouts"], channels)}
                for metric in ("completion", "object_completion"):
                    row[f"{metric}_vs_tracker"] = _paired(res, base, metric)
                result["rows"].append(row)
                c, o = row["completion_vs_tracker"], row["object_completion_vs_tracker"]
                usage = ", ".join(f"{k} {v:.3f}" for k, v in row["channel_usage"].items())
                scales = ", ".join(f"{k} {v:g}" for k, v in row["init_scale"].items())
                print(f"{spec:6s} {mode:13s} scale {scales:22s} completion {row['completion_pct']:5.1f} % "
                      f"({c['diff']:+.1f} [{c['ci95'][0]:+.1f}, {c['ci95'][1]:+.1f}]), object "
                      f"{row['object_completion_pct']:5.1f} % ({o['diff']:+.1f} [{o['ci95'][0]:+.1f}, "
                      f"{o['ci95'][1]:+.1f}]); mean |a|: {usage}", flush=True)
    result["wall_s"] = time.perf_counter() - t0
    return result


def trained_vs_untrained(a) -> dict:
    from adadex.envs.tracking import episode_references
    from adadex.eval.figures import channel_usage
    from adadex.modules.modulator import Modulator
    from adadex.train.pipeline import MODULATOR_ROWS, Pipeline, PipelineConfig

    root = a.run / f"seed_{a.seed}"
    stage = root / "modulators" / a.row / "stage.json"
    if not stage.is_file():
        raise refuse("modulator_usage", f"{stage}: no finished {a.row} modulator of seed {a.seed} in {a.run}")
    settings = json.loads(stage.read_text(encoding="utf-8"))["settings"]
    dataset = a.dataset or Path(settings["dataset"])
    pipe = Pipeline(PipelineConfig(out=str(a.run), dataset=str(dataset), progress=False))
    pipe.ds = pipe.dataset()
    refs = episode_references(pipe.ds, ("unseen_trajectory", "test"), pipe.env_config.window)[: a.references or 16]
    channels = MODULATOR_ROWS[a.row]
    m = settings["modulator"]
    torch.manual_seed(a.seed)
    fresh = Modulator(channels, hidden=tuple(m["hidden"]), init_scale=m["init_scale"],
                      loc_bound=m.get("loc_bound", 0.0), inputs=m.get("inputs", "observation"),
                      history=m.get("history", 3))
    paths = {"tracker": str(root / "generalist" / "tracker.pt")}
    result = {"benchmark": "modulator_usage", "run": str(a.run), "row": a.row, "seed": a.seed,
              "references": len(refs), "condition": "unseen_trajectory, randomized"}
    with tempfile.TemporaryDirectory() as tmp:
        untrained = fresh.save(Path(tmp) / "untrained.pt")
        for name, path in (("trained", root / "modulators" / a.row / "modulator.pt"), ("untrained", untrained)):
            res = pipe.evaluate(pipe.policy(a.row, {**paths, a.row: str(path)}), "unseen_trajectory", "randomized",
                                20_000 + a.seed, references=refs, keep_rollouts=True)
            result[name] = {"channel_usage": channel_usage(res["rollouts"], channels),
                            "completion_pct": res["summary"]["completion_pct"],
                            "mean_error_pct": res["summary"]["success_mean_error_pct"]}
    for name in ("untrained", "trained"):
        r = result[name]
        usage = ", ".join(f"{k} {v:.4f}" for k, v in r["channel_usage"].items())
        print(f"{name:9s} mean |a|: {usage}; completion {r['completion_pct']:.1f} %, "
              f"mean-error success {r['mean_error_pct']:.1f} %")
    return result


def main(argv=None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--init-check", action="store_true", help="untrained modulators against the tracker alone")
    p.add_argument("--run", type=Path, default=None, help="the out= folder of a finished pipeline run")
    p.add_argument("--dataset", type=Path, default=None, help="the dataset (--init-check: required)")
    p.add_argument("--tracker", default=None, help="--init-check: a tracker checkpoint (default: kinematic replay)")
    p.add_argument("--channels", default="R,T,O,R+O+T", help="--init-check: channel sets, comma-separated")
    p.add_argument("--scales", default="default,0.5",
                   help="--init-check: exploration scales, comma-separated; 'default' is each channel's own")
    p.add_argument("--repeats", type=int, default=4, help="--init-check: Table 3 draws per test reference")
    p.add_argument("--modes", default="deterministic,sampled",
                   help="--init-check: which runs of each row (the deterministic one: the first scale only)")
    p.add_argument("--worlds", type=int, default=64)
    p.add_argument("--row", default="ROT")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--references", type=int, default=0, help="first N test references (0: all; trained: 16)")
    p.add_argument("--out", type=Path, default=None)
    p.add_argument("--force", action="store_true",
                   help="replace --out even if it is not an earlier result of this benchmark")
    a = p.parse_args(argv)
    if a.init_check and a.dataset is None:
        p.error("--init-check needs --dataset")
    if not a.init_check and a.run is None:
        p.error("give --run (a finished pipeline run) or --init-check")
    out = a.out or RESULTS / ("modulator_init_check.json" if a.init_check else "modulator_usage.json")
    check_result(out, name="modulator_usage", force=a.force)      # before any work: refuse a file not ours
    result = init_check(a) if a.init_check else trained_vs_untrained(a)
    write_result(out, result, name="modulator_usage", force=a.force, indent=1)
    print(f"wrote {out}")
    return result


if __name__ == "__main__":
    sys.exit(0 if main() else 1)
