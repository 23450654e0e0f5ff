"""Which exploration scale should the Table 1 pipeline's specialists train with? The specialist benchmark
(``benchmarks/specialist_quality.py``) run with the pipeline's specialist settings — no object anchor,
the constant learning rate, ``--frames`` per specialist — for each ``--rows`` setting (an exploration
scale, optionally with PPO settings: ``0.05:obs_norm=running``) and each
``--seeds`` training seed, all evaluated on the same Table 3 draws, so every pair of settings compares
episode by episode.

Prints and writes (``--out``) per scale: completion and object completion per seed and pooled, and the
paired difference to the first scale (the pipeline's current one) per seed and pooled over seeds, with a
95 % percentile bootstrap interval over episodes (each episode is its own Table 3 draw; the specialist
benchmark's group has too few references for a bootstrap over references). Each run is kept under
``--runs`` (``is<scale>[_<ppo setting>]_s<seed>/``, with its JSON beside it) and is not run again when its JSON exists.

    nohup python benchmarks/specialist_exploration.py > exploration.log 2>&1 &
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _data import check_result, refuse, write_result  # noqa: E402

RESULTS = Path(__file__).resolve().parent / "results"


def _parse(row: str) -> tuple[float, list[str]]:
    """``"0.05"`` or ``"0.05:obs_norm=running"`` → (the exploration scale, the PPO settings)."""
    scale, _, ppo = row.partition(":")
    return float(scale), [kv for kv in ppo.split(",") if kv]


def _run(a, row: str, seed: int) -> dict:
    import specialist_quality

    scale, ppo = _parse(row)
    tag = f"is{scale:g}" + "".join(f"_{kv.replace('=', '-')}" for kv in ppo) + f"_s{seed}"
    path = a.runs / f"{tag}.json"
    if path.is_file():
        print(f"[skip] {tag}: {path}", flush=True)
        return json.loads(path.read_text(encoding="utf-8"))
    print(f"[run ] {tag}", flush=True)
    return specialist_quality.main([
        "--dataset", str(a.dataset), "--frames", str(a.frames), "--repeats", str(a.repeats), "--skip-ppo",
        "--anchor", "0", "--init-scale", str(scale), "--seed", str(seed), "--ppo", "desired_kl=0",
        "--ppo", "update_threads=1", *(x for kv in ppo for x in ("--ppo", kv)),
        "--runs", str(a.runs / tag), "--out", str(path)])


def _paired(a: list[np.ndarray], b: list[np.ndarray], *, resamples: int = 2000, seed: int = 0) -> dict:
    """Mean over seeds of each seed's mean A − B (points), with a percentile bootstrap over episodes
    resampled within each seed."""
    rng = np.random.default_rng(seed)
    diffs = [100.0 * (x - y) for x, y in zip(a, b)]
    boots = np.mean([[d[rng.integers(0, len(d), len(d))].mean() for _ in range(resamples)] for d in diffs], axis=0)
    return {"diff": float(np.mean([d.mean() for d in diffs])), "ci95": [float(np.percentile(boots, 2.5)),
                                                                         float(np.percentile(boots, 97.5))],
            "per_seed": [float(d.mean()) for d in diffs]}


def main(argv=None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--dataset", type=Path, default=Path("data/small_pg"))
    p.add_argument("--rows", nargs="+", default=["0.05", "0.5"],
                   help="exploration scale, optionally ':' and PPO settings (0.05:obs_norm=running); the first row "
                        "is the baseline")
    p.add_argument("--seeds", default="0,1,2")

    p.add_argument("--frames", type=int, default=250_000, help="PPO frames per specialist (the pipeline's)")
    p.add_argument("--repeats", type=int, default=64, help="Table 3 draws per reference in evaluation")
    p.add_argument("--runs", type=Path, default=Path("runs/specialist_exploration"))
    p.add_argument("--out", type=Path, default=RESULTS / "specialist_exploration.json")
    p.add_argument("--force", action="store_true", help="replace --out even if it is not this benchmark's")
    a = p.parse_args(argv)
    check_result(a.out, name="specialist_exploration", force=a.force)
    scales = list(a.rows)
    seeds = [int(x) for x in a.seeds.split(",")]
    a.runs.mkdir(parents=True, exist_ok=True)
    runs = {(s, k): _run(a, s, k) for k in seeds for s in scales}

    def column(scale, field):
        return [np.asarray(runs[(scale, k)]["specialist"]["per_episode"][field]) for k in seeds]

    offsets = column(scales[0], "offset_m")
    for s in scales[1:]:
        if any(not np.array_equal(o, x) for o, x in zip(offsets, column(s, "offset_m"))):
            raise refuse("specialist_exploration", f"{s}: its evaluation met other draws than {scales[0]}'s; cannot pair")
    replay = [np.asarray(runs[(scales[0], k)]["replay"]["per_episode"]["completion"]) for k in seeds]
    out = {"frames": a.frames, "repeats": a.repeats, "seeds": seeds, "group": runs[(scales[0], seeds[0])]["group"],
           "episodes_per_seed": len(replay[0]), "rows": {}}
    print(f"\ngroup {out['group']}, {out['episodes_per_seed']} episodes per seed, {a.frames} frames, no anchor, "
          f"constant learning rate")
    for s in scales:
        comp = column(s, "completion")
        row = {"completion_pct": [100.0 * float(c.mean()) for c in comp],
               "T_o_cm": [runs[(s, k)]["specialist"]["T_o"] for k in seeds],
               "train_wall_s": [runs[(s, k)]["specialist"]["train_wall_s"] for k in seeds],
               "vs_replay": _paired(comp, replay)}
        if s != scales[0]:
            row[f"vs_{scales[0]}"] = _paired(comp, column(scales[0], "completion"))
        out["rows"][s] = row
        vs = row.get(f"vs_{scales[0]}")
        extra = (f"; vs {scales[0]}: {vs['diff']:+.1f} [{vs['ci95'][0]:+.1f}, {vs['ci95'][1]:+.1f}] "
                 f"(per seed {', '.join(f'{d:+.1f}' for d in vs['per_seed'])})" if vs else "")
        v = row["vs_replay"]
        print(f"init_scale {s}: completion {' / '.join(f'{c:.1f}' for c in row['completion_pct'])} %, vs replay "
              f"{v['diff']:+.1f} [{v['ci95'][0]:+.1f}, {v['ci95'][1]:+.1f}]{extra}", flush=True)
    write_result(a.out, out, name="specialist_exploration", force=a.force, indent=1)
    print(f"wrote {a.out}")
    return out


if __name__ == "__main__":
    main()
