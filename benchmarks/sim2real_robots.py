"""The sim-to-real loop on several hidden robots, side by side: each robot's rows pooled over seeds
(``benchmarks/sim2real_seeds.py`` outputs), one line per robot — the gap, the share of it each trained row
takes back, the verdict (``adadex.train.sim2real.verdict``) — and one figure
(``adadex.train.sim2real.plot_robots``: every row's completion, the share taken back above each robot).

    python benchmarks/sim2real_robots.py docs/measurements/sim2real_payload_soft_arm_K_group4_3seeds.json \\
        docs/measurements/sim2real_heavy_soft_arm_K_group4_3seeds.json [--out FILE] [--figure FILE.png] [--force]

Each robot is named by its hidden patch's file stem (``real`` in the pooled result); ``NAME=FILE`` names it
yourself. Writes the JSON (default ``benchmarks/results/sim2real_robots.json``) and the figure (default:
``--out`` with ``.png``); each replaces only this benchmark's earlier output, or anything with ``--force``.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from _data import RESULTS, check_result, refuse, write_result

NAME = "sim2real_robots"
#: the trained rows' shares of the gap: column → the pooled result's key
KEYS = {"identified": "recovered_fraction", "table3": "recovered_fraction_modulator_table3_real",
        "finetuned": "recovered_fraction_finetuned_identified_real", "oracle": "recovered_fraction_modulator_oracle_real"}


def _share(res: dict, key: str) -> str:
    from adadex.train.sim2real import format_fraction

    return "—" if res.get(key) is None else format_fraction(res[key], res.get(f"{key}_ci95"))


def load(spec: str) -> tuple[str, dict]:
    """``FILE`` or ``NAME=FILE``: a pooled result and the robot's name."""
    name, _, file = spec.rpartition("=") if "=" in spec else ("", "", spec)
    path = Path(file)
    try:
        res = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError) as e:
        raise refuse(NAME, f"{path}: not readable JSON ({e.__class__.__name__})") from None
    if not isinstance(res, dict) or not isinstance(res.get("rows"), dict) or "gap_points" not in res \
            or not {"tracker_nominal", "tracker_real"} <= set(res["rows"]):
        raise refuse(NAME, f"{path}: not a pooled sim2real result (benchmarks/sim2real_seeds.py writes one: rows "
                           f"with tracker_nominal and tracker_real, gap_points)")
    return name or Path(str(res.get("real") or path.stem)).stem, res


def main(argv=None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("pooled", nargs="+", help="pooled results (FILE or NAME=FILE), one per hidden robot")
    p.add_argument("--out", type=Path, default=RESULTS / f"{NAME}.json")
    p.add_argument("--figure", type=Path, default=None, help="the figure (default: --out with .png)")
    p.add_argument("--force", action="store_true")
    a = p.parse_args(argv)
    check_result(a.out, name=NAME, force=a.force)
    from adadex.errors import AdadexError
    from adadex.io import check_output_file, mark_file
    from adadex.train.sim2real import plot_robots, verdict

    figure = a.figure or a.out.with_suffix(".png")
    try:
        figure = check_output_file(figure, f"{NAME} figure", force=a.force)
    except AdadexError as e:
        raise refuse(NAME, e) from None
    robots = dict(load(spec) for spec in a.pooled)
    if len(robots) != len(a.pooled):
        raise refuse(NAME, "two results name the same robot; name them NAME=FILE")
    robots = {n: {**r, "verdict": r.get("verdict") or verdict(r)} for n, r in robots.items()}   # older results lack it
    summary = {}
    print(f"{'robot':28s} {'gap (points)':>20s} {'identified':>18s} {'table3':>18s} {'finetuned':>18s} "
          f"{'oracle':>18s}  verdict")
    for name, res in robots.items():
        v = res["verdict"]
        gap_ci = res.get("gap_points_ci95") or [float("nan")] * 2
        print(f"{name:28s} {res['gap_points']:+6.1f} [{gap_ci[0]:+.1f}, {gap_ci[1]:+.1f}] "
              + " ".join(f"{_share(res, k):>18s}" for k in KEYS.values()) + f"  {v['kind']}")
        summary[name] = {"real": res.get("real"), "seeds": res.get("seeds"), "gap_points": res["gap_points"],
                         "gap_points_ci95": res.get("gap_points_ci95"), "verdict": v,
                         **{k: res.get(key) for k, key in KEYS.items()},
                         **{f"{k}_ci95": res.get(f"{key}_ci95") for k, key in KEYS.items()},
                         "completion_pct": {r: row["completion_pct"] for r, row in res["rows"].items()}}
    plot_robots(robots, figure)
    mark_file(figure, f"{NAME} figure")
    result = {"robots": summary, "sources": list(a.pooled), "figure": str(figure)}
    write_result(a.out, result, name=NAME, force=a.force)
    print(f"wrote {a.out} and {figure}")
    return result


if __name__ == "__main__":
    from adadex.errors import exit_on_error

    with exit_on_error(f"benchmarks/{NAME}.py"):
        main()
