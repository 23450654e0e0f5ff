"""How good and how fast is the point-cloud encoder? Reconstruction Chamfer and per-object encode latency.

For a checkpoint (default: the shipped ``assets/encoder/encoder.pt``):

* reconstruction quality on all 80 objects — mean Chamfer distance (cm²) and RMS nearest-neighbour
  distance (mm) over the 75 training and the 5 held-out objects, each on a fresh surface sample —
  next to the resampling floor (two independent samples of the same surface are this far apart)
  and an untrained model of the same architecture;
* latency of encoding one object's cloud (the env's latent hook does this once per object and
  caches it), at 1 thread, best of ``--repeats``; and of all 80 objects in one batch.

    python benchmarks/encoder_quality.py [--checkpoint PATH] [--repeats 50] [--out FILE]
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import torch

from _data import check_result, write_result

RESULTS = Path(__file__).resolve().parent / "results"


def _best_ms(fn, repeats: int) -> float:
    best = float("inf")
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return best * 1e3


def main(argv=None) -> dict:
    from adadex.envs.latent import SHIPPED_ENCODER
    from adadex.modules.encoder import PointCloudAutoencoder, load_encoder
    from adadex.sim.objects import OBJECT_NAMES, get_object
    from adadex.train.encoder import evaluate_encoder, resampling_floor, summarize_evaluation

    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--checkpoint", type=Path, default=SHIPPED_ENCODER)
    p.add_argument("--repeats", type=int, default=50)
    p.add_argument("--out", type=Path, default=RESULTS / "encoder_quality.json")
    p.add_argument("--force", action="store_true",
                   help="replace --out even if it is not an earlier result of this benchmark")
    a = p.parse_args(argv)
    check_result(a.out, name="encoder_quality", force=a.force)      # before any work: refuse a file not ours

    model, meta = load_encoder(a.checkpoint)
    per_object = evaluate_encoder(model)
    with torch.random.fork_rng():
        torch.manual_seed(meta.get("seed", 0))
        untrained = PointCloudAutoencoder(model.config).eval()
    n = model.config.points
    clouds = torch.stack([torch.from_numpy(get_object(o).point_cloud(n, seed=0)) for o in OBJECT_NAMES])

    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    with torch.no_grad():
        one_ms = _best_ms(lambda: model.encode(clouds[0]), a.repeats)
        all_ms = _best_ms(lambda: model.encode(clouds), max(a.repeats // 10, 3))
    torch.set_num_threads(threads)

    result = {
        "checkpoint": str(a.checkpoint),
        "trained": {k: meta.get(k) for k in ("seed", "steps", "batch_size", "points", "lr", "train_seconds")},
        "unit": "chamfer_cm2: Chamfer distance in cm²; rms_mm: RMS nearest-neighbour distance in mm",
        "trained_model": summarize_evaluation(per_object),
        "resampling_floor": summarize_evaluation(resampling_floor(points=n)),
        "untrained_model": summarize_evaluation(evaluate_encoder(untrained)),
        "latency_ms": {"encode_one_object": one_ms, "encode_80_objects_batched": all_ms,
                       "points_per_object": n, "threads": 1},
        "per_object": per_object,
    }
    write_result(a.out, result, name="encoder_quality", force=a.force, indent=1, ensure_ascii=False)

    print(f"encoder {a.checkpoint} ({meta.get('steps')} steps, seed {meta.get('seed')})")
    print(f"{'':<18}{'train cm²':>10}{'RMS mm':>8}{'held-out cm²':>14}{'RMS mm':>8}")
    for label in ("trained_model", "resampling_floor", "untrained_model"):
        s = result[label]
        print(f"{label.replace('_', ' '):<18}{s['train']['chamfer_cm2']:>10.4f}{s['train']['rms_mm']:>8.2f}"
              f"{s['held_out']['chamfer_cm2']:>14.4f}{s['held_out']['rms_mm']:>8.2f}")
    print(f"encode latency (1 thread, {n} points): one object {one_ms:.2f} ms, 80 objects batched {all_ms:.1f} ms")
    print(f"wrote {a.out}")
    return result


if __name__ == "__main__":
    main()
