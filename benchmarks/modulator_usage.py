"""Does a trained modulator edit, and do its edits help? A pipeline run's modulator against an untrained one.

For one row of a finished ``recipes/pipeline.py`` run (default ``ROT``, seed 0), on the first
``--references`` unseen-trajectory test references under Table 3 randomization: how much each channel
is moved (mean |a| of the modulator's action, :func:`adadex.eval.figures.channel_usage`) and the
completion success, for the trained modulator and for a freshly initialised one of the same shape
(its edits are ≈ 0, so it tracks as the frozen tracker does). A trained modulator whose channels move
but whose success falls has learned edits that do not help.

    python benchmarks/modulator_usage.py --run runs/table1 [--row ROT] [--seed 0] [--references 16] [--out FILE]
"""

from __future__ import annotations

import argparse
import json
import tempfile
from pathlib import Path

import torch

from adadex.io import atomic_write_text

RESULTS = Path(__file__).resolve().parent / "results"


def main(argv=None) -> dict:
    from adadex.envs.tracking import episode_references
    from adadex.eval.figures import channel_usage
    from adadex.modules.modulator import Modulator
    from adadex.train.pipeline import MODULATOR_ROWS, Pipeline, PipelineConfig

    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--run", type=Path, required=True, help="the out= folder of a finished pipeline run")
    p.add_argument("--dataset", type=Path, default=None, help="its dataset (default: the one its stages used)")
    p.add_argument("--row", default="ROT", choices=sorted(MODULATOR_ROWS))
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--references", type=int, default=16)
    p.add_argument("--out", type=Path, default=RESULTS / "modulator_usage.json")
    a = p.parse_args(argv)

    root = a.run / f"seed_{a.seed}"
    stage = root / "modulators" / a.row / "stage.json"
    if not stage.is_file():
        raise SystemExit(f"{stage}: no finished {a.row} modulator of seed {a.seed} in {a.run}")
    settings = json.loads(stage.read_text(encoding="utf-8"))["settings"]
    dataset = a.dataset or Path(settings["dataset"])
    pipe = Pipeline(PipelineConfig(out=str(a.run), dataset=str(dataset), progress=False))
    pipe.ds = pipe.dataset()
    refs = episode_references(pipe.ds, ("unseen_trajectory", "test"), pipe.env_config.window)[: a.references]
    channels = MODULATOR_ROWS[a.row]
    m = settings["modulator"]
    torch.manual_seed(a.seed)
    fresh = Modulator(channels, hidden=tuple(m["hidden"]), init_scale=m["init_scale"],
                      loc_bound=m.get("loc_bound", 0.0))
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
    a.out.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_text(a.out, json.dumps(result, indent=1))
    for name in ("untrained", "trained"):
        r = result[name]
        usage = ", ".join(f"{k} {v:.4f}" for k, v in r["channel_usage"].items())
        print(f"{name:9s} mean |a|: {usage}; completion {r['completion_pct']:.1f} %, "
              f"mean-error success {r['mean_error_pct']:.1f} %")
    print(f"wrote {a.out}")
    return result


if __name__ == "__main__":
    main()
