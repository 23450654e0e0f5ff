"""The sim-to-real loop's rows pooled over training seeds: several ``recipes/sim2real.py`` runs on one
hidden robot (one per ``seed=``), each paired on its own draws, as one table with intervals that resample
references within each seed (``adadex.train.sim2real.pool_seeds``).

    python recipes/sim2real.py real=assets/gaps/payload_soft_arm.json out=runs/s2r_s1 preset=small seed=1
    python benchmarks/sim2real_seeds.py runs/s2r_s0 runs/s2r_s1 runs/s2r_s2 [--out FILE] [--force]

Prints each row's completion with its paired difference to ``tracker_real``, the gap, the recovered
fraction (each seed's and pooled) and identified − Table 3; writes the JSON (default
``benchmarks/results/sim2real_seeds.json``).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from _data import RESULTS, check_result, refuse, write_result


def _ci(ci, fmt="+.1f") -> str:
    return "" if not ci else f"[{ci[0]:{fmt}}, {ci[1]:{fmt}}]"


def main(argv=None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("runs", nargs="+", type=Path, help="sim2real output folders (each holds sim2real.json)")
    p.add_argument("--out", type=Path, default=RESULTS / "sim2real_seeds.json")
    p.add_argument("--force", action="store_true")
    a = p.parse_args(argv)
    check_result(a.out, name="sim2real_seeds", force=a.force)
    from adadex.train.sim2real import CONTRASTS, RECOVERING, Sim2RealError, pool_seeds

    results = []
    for run in a.runs:
        f = run / "sim2real.json"
        if not f.is_file():
            raise refuse("sim2real_seeds", f"{f}: no such file (a recipes/sim2real.py output)")
        results.append(json.loads(f.read_text()))
    try:
        pooled = pool_seeds(results)
    except Sim2RealError as e:
        raise refuse("sim2real_seeds", e) from None
    pooled["runs_from"] = [str(r) for r in a.runs]
    print(f"{pooled['real']}: seeds {pooled['seeds']}, {pooled['paired_episodes']} paired episodes")
    print(f"{'row':28s} {'completion %':>22s} {'vs tracker_real':>20s}")
    for name, row in pooled["rows"].items():
        vs = row.get("vs_tracker_real_completion_points")
        print(f"{name:28s} {row['completion_pct']:6.1f} {_ci(row['completion_pct_ci95'], '5.1f'):>15s} "
              + (f"{vs['estimate']:+6.1f} {_ci(vs['ci95']):>14s}" if vs else ""))
    print(f"gap: {pooled['gap_points']:+.1f} points {_ci(pooled['gap_points_ci95'])}")
    if pooled.get("recovered_fraction") is not None:
        per = ", ".join(f"{x:.2f}" for x in pooled["per_seed_recovered_fraction"] if x is not None)
        print(f"recovered (identified): {pooled['recovered_fraction']:.2f} {_ci(pooled['recovered_fraction_ci95'], '.2f')}"
              f"   per seed: {per}")
    for name in RECOVERING[1:]:
        if pooled.get(f"recovered_fraction_{name}") is not None:
            print(f"recovered ({name}): {pooled[f'recovered_fraction_{name}']:.2f} "
                  f"{_ci(pooled[f'recovered_fraction_{name}_ci95'], '.2f')}")
    for a_row, b_row, key in CONTRASTS:
        if key in pooled:
            d = pooled[key]
            print(f"{a_row} − {b_row}: {d['estimate']:+.1f} points {_ci(d['ci95'])}")
    print(f"verdict: {pooled['verdict']['kind']} — {pooled['verdict']['text']}")
    write_result(a.out, pooled, name="sim2real_seeds", force=a.force)
    print(f"wrote {a.out}")
    return pooled


if __name__ == "__main__":
    sys.exit(0 if main() else 1)
