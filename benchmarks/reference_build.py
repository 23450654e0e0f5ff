"""How fast are references built? The ``small`` preset end to end, stage by stage.

Reports references built per second (accepted references over the whole build's wall clock),
candidates synthesized per second, retargeted frames per second (in the build, including the
re-tracking of sequences that lost the fit, and for one plain pass over 64 sequences), the
acceptance rate and the rejection reasons, and the retargeting residuals of accepted references.

    python benchmarks/reference_build.py [--preset small] [--limit N] [--seed 0] [--out FILE]
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np

from adadex.data.build import PRESETS, build_dataset
from adadex.data.reference import ReferenceDataset
from adadex.data.retarget import Retargeter
from _data import check_result, write_result

RESULTS = Path(__file__).resolve().parent / "results"


def main(argv=None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--preset", choices=sorted(PRESETS), default="small")
    p.add_argument("--limit", type=int, default=None, help="only the first N base instructions")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", type=Path, default=RESULTS / "reference_build.json")
    p.add_argument("--force", action="store_true",
                   help="replace --out even if it is not an earlier result of this benchmark")
    a = p.parse_args(argv)
    check_result(a.out, name="reference_build", force=a.force)      # before any work: refuse a file not ours
    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.perf_counter()
        report = build_dataset(a.preset, Path(tmp) / "ds", seed=a.seed, limit=a.limit)
        wall = time.perf_counter() - t0
        ds = ReferenceDataset(report.path)
        residual = np.concatenate([r.retarget_residual for r in ds])
        tip = np.array([e["meta"]["retarget_tip_error_max"] for e in ds.entries])
        # Retargeting alone (first pass, no re-tracking), 64 sequences of the built references at once.
        kp = np.stack([r.human_keypoints for r in ds[:64]])
        t_rt = time.perf_counter()
        Retargeter(retry_above=np.inf).retarget(kp)
        retarget_only = kp.shape[0] * kp.shape[1] / (time.perf_counter() - t_rt)
        t_open = time.perf_counter()
        ReferenceDataset(report.path)[len(ds) // 2]
        open_read = time.perf_counter() - t_open
    result = {
        "preset": a.preset, "limit": a.limit, "seed": a.seed,
        "candidates": report.candidates, "accepted": report.accepted,
        "acceptance_rate": report.accepted / report.candidates, "rejected": dict(report.rejected),
        "wall_s": wall, "stage_s": report.seconds,
        "references_per_s": report.accepted / wall,
        "candidates_per_s": report.candidates / wall,
        "synthesized_per_s": report.candidates / report.seconds["synthesize"],
        "retargeted_frames_per_s": report.retargeted_frames / report.seconds["retarget"],
        "retargeted_frames": report.retargeted_frames,
        "retarget_first_pass_frames_per_s": retarget_only,
        "residual_m": {"median": float(np.median(residual)), "p95": float(np.percentile(residual, 95))},
        "max_tip_error_m_median": float(np.median(tip)),
        "open_and_read_one_s": open_read,
    }
    write_result(a.out, result, name="reference_build", force=a.force, indent=1)
    print(f"{a.preset}: {report.accepted}/{report.candidates} accepted ({100 * result['acceptance_rate']:.0f} %), "
          f"rejected {dict(report.rejected)}")
    print(f"  {result['references_per_s']:.2f} references/s over {wall:.0f} s; "
          f"{result['retargeted_frames_per_s']:.0f} retargeted frames/s in the build (with re-tracking), "
          f"{retarget_only:.0f} frames/s for one pass at B={kp.shape[0]}; "
          f"synthesis {result['synthesized_per_s']:.1f} motions/s")
    print(f"  retargeting residual median {1000 * result['residual_m']['median']:.1f} mm, "
          f"p95 {1000 * result['residual_m']['p95']:.1f} mm; open + read one reference {1000 * open_read:.0f} ms")
    print(f"wrote {a.out}")
    return result


if __name__ == "__main__":
    main()
