"""The ``adadex encoder train|eval`` command (registered by :mod:`adadex.cli`): argument handling
and reports over :mod:`adadex.train.encoder`.

``train --out DIR`` is written in place, file by file (:func:`adadex.io.check_output_dir`, before any
work): an existing DIR that is not empty and not an earlier training run's (a folder of the user's
files) is refused unless ``--force``; a file at DIR always is. An earlier run is recognized by the
marker in its ``encoder.json`` (``"adadex_output": "encoder training run"``) or the folder marker the
``train_encoder`` recipe writes, never by its file names.

``eval --out DIR`` is written as one unit (:func:`adadex.io.output_folder`): an existing DIR that is
not an earlier ``encoder eval`` output is refused before any work unless ``--force``. An earlier output
is recognized by the marker the command writes into its ``eval.json`` (``"adadex_output":
"encoder-eval"``), never by the folder's file names.
"""

from __future__ import annotations

import json
from pathlib import Path

import torch

from adadex.errors import ConfigError, check_number
from adadex.io import atomic_write_text, check_output, check_output_dir, output_folder
from adadex.modules.encoder import load_encoder
from adadex.train.encoder import (
    PLOT_OBJECTS,
    TRAINING_KIND,
    TrainSettings,
    check_settings,
    evaluate_encoder,
    plot_reconstructions,
    resampling_floor,
    save_training_run,
    is_training_output,
    summarize_evaluation,
    train_encoder,
)


def _summary_line(label: str, summary: dict) -> str:
    parts = [f"{split} {s['chamfer_cm2']:.4f} cm² (RMS {s['rms_mm']:.2f} mm, {s['objects']} objects)"
             for split, s in summary.items()]
    return f"{label}: Chamfer " + "; ".join(parts)


def _cmd_train(a) -> int:
    try:
        check_settings(a.steps, a.batch_size, a.points, a.lr)
    except ValueError as e:             # its checks of the settings (plain ValueErrors): bad input, one line
        raise ConfigError(str(e)) from None
    if a.threads is not None:
        check_number("--threads", a.threads, low=1, integer=True)
    out = Path(a.out)
    check_output_dir(out, TRAINING_KIND, force=a.force, recognize=is_training_output)     # before any work
    if a.threads:
        torch.set_num_threads(a.threads)
    print(f"training the point-cloud encoder: {a.steps} steps, batch {a.batch_size}, {a.points} points, "
          f"lr {a.lr}, seed {a.seed}, {torch.get_num_threads()} threads → {out}")
    model, history = train_encoder(steps=a.steps, batch_size=a.batch_size, points=a.points, lr=a.lr,
                                   seed=a.seed, progress=not a.quiet)
    check_output_dir(out, TRAINING_KIND, force=a.force, recognize=is_training_output)     # nothing new there since
    paths = save_training_run(out, model, history)
    print(f"trained in {history['seconds']:.0f} s")
    print("untrained: Chamfer " + "; ".join(f"{k} {v:.4f} cm²" for k, v in history["initial"].items()))
    print(_summary_line("trained", history["final"]))
    print("wrote " + ", ".join(map(str, paths.values())))
    return 0


EVAL_KIND = "encoder-eval"


def _is_eval_output(path: Path) -> bool:
    """``path`` is a folder an ``encoder eval`` wrote: its ``eval.json`` carries the command's marker."""
    d = json.loads((path / "eval.json").read_text(encoding="utf-8"))
    return isinstance(d, dict) and d.get("adadex_output") == EVAL_KIND


def _cmd_eval(a) -> int:
    out = Path(a.out)
    check_output(out, EVAL_KIND, force=a.force, recognize=_is_eval_output)        # before any work
    model, meta = load_encoder(a.checkpoint)
    per_object = evaluate_encoder(model)
    summary = summarize_evaluation(per_object)
    floor = summarize_evaluation(resampling_floor(points=model.config.points))
    trained = {k: meta.get(k) for k in ("seed", "steps", "batch_size", "lr")}
    report = {"adadex_output": EVAL_KIND, "checkpoint": str(a.checkpoint), "trained": trained,
              "unit": "chamfer_cm2: Chamfer distance in cm²; rms_mm: RMS nearest-neighbour distance in mm",
              **summary, "resampling_floor": floor, "per_object": per_object}
    with output_folder(out, EVAL_KIND, force=a.force, recognize=_is_eval_output, marker=False) as tmp:
        atomic_write_text(tmp / "eval.json", json.dumps(report, indent=1, ensure_ascii=False))
        plot_reconstructions(model, PLOT_OBJECTS, tmp / "reconstructions.png")
    print(_summary_line(str(a.checkpoint), summary))
    print(_summary_line("resampling floor (two samples of the same surface)", floor))
    worst = sorted(per_object.items(), key=lambda kv: -kv[1]["rms_mm"])[:3]
    print("worst: " + ", ".join(f"{n} {r['rms_mm']:.1f} mm" for n, r in worst))
    print(f"wrote {out / 'eval.json'}, {out / 'reconstructions.png'}")
    return 0


def add_arguments(enc) -> None:
    """Fill the ``adadex encoder`` parser ``enc`` (made by :func:`adadex.cli.build_parser`) with
    ``train`` and ``eval``."""
    import argparse

    d = TrainSettings()
    enc.description = ("Train or evaluate the point-cloud autoencoder whose 64-D code is the object latent. "
                       "Metrics: Chamfer distance in cm², RMS nearest-neighbour distance in mm.")
    enc.formatter_class = argparse.RawDescriptionHelpFormatter
    esub = enc.add_subparsers(dest="encoder_command", required=True)
    t = esub.add_parser("train", help="train on the 75 training objects; write encoder.pt, encoder.json, "
                                      "reconstructions.png")
    t.add_argument("--steps", type=int, default=d.steps, help=f"optimizer steps (default {d.steps})")
    t.add_argument("--seed", type=int, default=d.seed)
    t.add_argument("--out", default="outputs/encoder", help="output folder (default outputs/encoder)")
    t.add_argument("--batch-size", type=int, default=d.batch_size)
    t.add_argument("--points", type=int, default=d.points, help="points per cloud")
    t.add_argument("--lr", type=float, default=d.lr)
    t.add_argument("--threads", type=int, default=None, help="torch threads (default: torch's choice)")
    t.add_argument("--quiet", action="store_true", help="no progress bar")
    t.add_argument("--force", action="store_true", help="write into --out even if it is not an earlier output of "
                   "`adadex encoder train`")
    t.set_defaults(func=_cmd_train)
    e = esub.add_parser("eval", help="per-object Chamfer of a checkpoint on all 80 objects; eval.json and "
                                     "reconstructions.png")
    e.add_argument("checkpoint", type=Path)
    e.add_argument("--out", default="outputs/encoder_eval", help="output folder (default outputs/encoder_eval)")
    e.add_argument("--force", action="store_true", help="replace --out even if it is not an earlier output of "
                   "`adadex encoder eval`")
    e.set_defaults(func=_cmd_eval)


def run(args) -> int:
    """Run an encoder subcommand. Errors are reported by :func:`adadex.cli.main` through the one contract
    (:func:`adadex.errors.report_error`): bad input one line and exit code 2, a bug exit code 1."""
    return args.func(args)
