"""Training and evaluation of the point-cloud encoder (:mod:`adadex.modules.encoder`), and its figure.

* :func:`train_encoder` — Chamfer training on fresh point subsets of the training objects;
  :class:`TrainSettings` holds its defaults (shared by ``adadex encoder train`` and the recipe);
* :func:`evaluate_encoder`, :func:`resampling_floor`, :func:`summarize_evaluation` — per-object
  reconstruction quality (Chamfer in cm², RMS nearest-neighbour distance in mm) and its means;
* :func:`save_training_run` — a run's checkpoint, latent table, metrics and figure in one folder;
* :func:`plot_reconstructions` — the paper's Fig. 5: object points beside decoded points.

The command line (``adadex encoder train|eval``) is :mod:`adadex.train.encoder_cli`; the Hydra
recipe is ``recipes/train_encoder.py``.

Example
-------
>>> summarize_evaluation({"a": {"split": "train", "chamfer_cm2": 1.0, "rms_mm": 2.0},
...                       "b": {"split": "train", "chamfer_cm2": 3.0, "rms_mm": 4.0}})
{'train': {'chamfer_cm2': 2.0, 'rms_mm': 3.0, 'objects': 2}}
"""

from __future__ import annotations

import io
import json
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from adadex.io import atomic_write_bytes, atomic_write_text
from adadex.modules.encoder import (
    EncoderConfig,
    PointCloudAutoencoder,
    chamfer_distance,
    object_latents,
    save_encoder,
    save_latents,
    surface_clouds,
)
from adadex.sim.objects import OBJECT_NAMES, get_object, held_out_objects

#: Points per object in the training bank; every step draws fresh subsets from it.
BANK_POINTS = 4096
#: Surface-sampling seeds: the training bank, and evaluation clouds (fresh samples, never trained on).
#: (The environment's latent table uses :data:`adadex.modules.encoder.LATENT_SEED`.)
BANK_SEED, EVAL_SEED = 1, 2
#: Default objects in the reconstruction figure: four training objects, three held-out ones.
PLOT_OBJECTS = ("cube_050", "mug_00", "hammer_00", "wineglass_00", "mug_03", "torus_02", "hammer_03")


# --------------------------------------------------------------------------------------------
# Data


def point_bank(objects: Sequence[str], n: int = BANK_POINTS, seed: int = BANK_SEED) -> torch.Tensor:
    """(len(objects), n, 3) float32 surface samples in metres: the pool training subsets come from."""
    return torch.from_numpy(np.stack([get_object(o).point_cloud(n, seed=seed) for o in objects]))


def training_objects() -> tuple[str, ...]:
    """The 75 objects of the training split (the 5 held-out objects are only evaluated)."""
    held = set(held_out_objects())
    return tuple(o for o in OBJECT_NAMES if o not in held)


def _subsets(bank: torch.Tensor, batch_size: int, points: int, g: torch.Generator) -> torch.Tensor:
    """(batch_size, points, 3): random objects (with replacement), each a random point subset."""
    idx = torch.randint(len(bank), (batch_size,), generator=g)
    pick = torch.rand(batch_size, bank.shape[1], generator=g).argsort(1)[:, :points]
    return bank[idx[:, None], pick]


# --------------------------------------------------------------------------------------------
# Evaluation


def _per_object(objects: Sequence[str], chamfer_m2: torch.Tensor) -> dict[str, dict]:
    held = set(held_out_objects())
    return {o: {"split": "held_out" if o in held else "train", "chamfer_cm2": float(c * 1e4),
                "rms_mm": float(c.sqrt() * 1e3)} for o, c in zip(objects, chamfer_m2.double())}


@torch.no_grad()
def evaluate_encoder(model: PointCloudAutoencoder, objects: Sequence[str] | None = None, *,
                     points: int | None = None, seed: int = EVAL_SEED) -> dict[str, dict]:
    """Per-object reconstruction quality: ``{name: {"split", "chamfer_cm2", "rms_mm"}}``.

    Each object's cloud is a fresh surface sample (``seed``, ``points`` = the model's input size), so
    training objects are not measured on the exact points they were trained on. ``chamfer_cm2`` is
    :func:`chamfer_distance` between the cloud and its reconstruction in cm²; ``rms_mm`` its RMS
    nearest-neighbour distance in mm. Default objects: all 80.

    Args:
        model: the autoencoder (left in its training mode afterwards).
        objects: the objects to measure (default: all).
        points: points per cloud (default: the model's ``config.points``).
        seed: the surface sampling seed (default :data:`EVAL_SEED`).
    """
    objects = tuple(objects) if objects is not None else OBJECT_NAMES
    clouds = surface_clouds(objects, points or model.config.points, seed)
    was_training = model.training
    model.eval()
    cd = chamfer_distance(model(clouds), clouds)
    model.train(was_training)
    return _per_object(objects, cd)


@torch.no_grad()
def resampling_floor(objects: Sequence[str] | None = None, *, points: int = EncoderConfig.points,
                     seed: int = EVAL_SEED) -> dict[str, dict]:
    """Chamfer between two independent surface samples of each object, in :func:`evaluate_encoder`'s format.

    The reference point for reconstruction errors: a reconstruction is scored against one random
    sample of ``points`` points, which is itself this far from any other sample of the same surface.
    """
    objects = tuple(objects) if objects is not None else OBJECT_NAMES
    cd = chamfer_distance(surface_clouds(objects, points, seed), surface_clouds(objects, points, seed + 1))
    return _per_object(objects, cd)


def summarize_evaluation(per_object: dict[str, dict]) -> dict[str, dict]:
    """Means over each split of :func:`evaluate_encoder`'s result: ``{split: {chamfer_cm2, rms_mm, objects}}``."""
    out = {}
    for split in ("train", "held_out"):
        rows = [r for r in per_object.values() if r["split"] == split]
        if rows:
            out[split] = {"chamfer_cm2": float(np.mean([r["chamfer_cm2"] for r in rows])),
                          "rms_mm": float(np.mean([r["rms_mm"] for r in rows])), "objects": len(rows)}
    return out


# --------------------------------------------------------------------------------------------
# Training


@dataclass(frozen=True)
class TrainSettings:
    """Defaults of :func:`train_encoder`, shared by the CLI and the Hydra recipe."""

    steps: int = 3000
    batch_size: int = 16
    points: int = 512
    lr: float = 1e-3
    seed: int = 0


def check_settings(steps: int, batch_size: int, points: int, lr: float) -> None:
    """Refuse settings :func:`train_encoder` cannot use (before any work); arguments as there."""
    if steps < 0:
        raise ValueError(f"steps must be ≥ 0, got {steps}")
    if batch_size < 1:
        raise ValueError(f"batch_size must be ≥ 1, got {batch_size}")
    if not 1 <= points <= BANK_POINTS:
        raise ValueError(f"points must be in [1, {BANK_POINTS}], got {points}")
    if not lr > 0:
        raise ValueError(f"lr must be > 0, got {lr}")


def train_encoder(objects: Sequence[str] | None = None, *, steps: int = TrainSettings.steps,
                  batch_size: int = TrainSettings.batch_size, points: int = TrainSettings.points,
                  lr: float = TrainSettings.lr, seed: int = TrainSettings.seed, progress: bool = True,
                  eval_every: int | None = None) -> tuple[PointCloudAutoencoder, dict]:
    """Train a :class:`PointCloudAutoencoder` with the Chamfer loss; return ``(model, history)``.

    Each step takes ``batch_size`` random objects and a fresh random subset of ``points`` points
    from each one's bank of :data:`BANK_POINTS` surface samples, so the model never sees the same
    cloud twice and learns the surface rather than a point set. Adam, learning rate cosine-annealed
    from ``lr`` to 0. Deterministic: the initial weights and every draw come from ``seed``
    (the global torch RNG is left untouched).

    ``objects``: training objects (default: the 75 not held out); the held-out objects not among them
    are evaluated too, and metrics are split by the registry's split. ``history``: ``"loss"`` (per step,
    cm²), ``"evals"`` (mean train / held-out Chamfer at step 0, every ``eval_every`` steps and at the
    end), ``"initial"`` / ``"final"`` (:func:`summarize_evaluation`), ``"per_object"``
    (:func:`evaluate_encoder` at the end), ``"seconds"`` and ``"meta"`` (what :func:`save_encoder` stores).

    Args:
        objects: training objects (above).
        steps: optimizer steps (default 3000).
        batch_size: objects per step (default 16).
        points: points per cloud, the model's input size (``EncoderConfig.points``; default 512).
        lr: the initial learning rate (default 1e-3).
        seed: seeds the weights and every draw (default 0).
        progress: show a progress bar (default True).
        eval_every: evaluate every this many steps (default None: ``max(steps // 10, 50)``).
    """
    from adadex.progress import progress_bar

    check_settings(steps, batch_size, points, lr)
    objects = tuple(objects) if objects is not None else training_objects()
    if not objects:
        raise ValueError("no training objects")
    held = tuple(o for o in held_out_objects() if o not in objects)
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(seed)
        model = PointCloudAutoencoder(EncoderConfig(points=points))
    g = torch.Generator().manual_seed(seed)
    bank = point_bank(objects)
    opt = torch.optim.Adam(model.parameters(), lr=lr)
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, T_max=max(steps, 1))
    eval_every = eval_every or max(steps // 10, 50)

    def evaluate(step: int) -> dict:
        per_object = evaluate_encoder(model, objects + held, points=points)
        history["evals"].append({"step": step, **{k: v["chamfer_cm2"] for k, v in
                                                  summarize_evaluation(per_object).items()}})
        return per_object

    history: dict = {"loss": [], "evals": []}
    per_object = evaluate(0)
    t0 = time.perf_counter()
    bar = progress_bar(range(steps), desc="encoder", disable=not progress, dynamic_ncols=True)
    for step in bar:
        loss = model.loss(_subsets(bank, batch_size, points, g)).mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
        sched.step()
        history["loss"].append(float(loss.detach()) * 100.0)  # dm² → cm²
        if (step + 1) % eval_every == 0 and step + 1 < steps:
            evaluate(step + 1)
            bar.set_postfix({f"{k} cm²": f"{v:.3f}" for k, v in history["evals"][-1].items() if k != "step"})
    model.eval()
    history["seconds"] = time.perf_counter() - t0
    history["per_object"] = per_object = evaluate(steps) if steps else per_object
    history["final"] = summarize_evaluation(per_object)
    history["initial"] = {k: v for k, v in history["evals"][0].items() if k != "step"}
    history["meta"] = {
        "seed": seed, "steps": steps, "batch_size": batch_size, "points": points, "lr": lr,
        "bank_points": BANK_POINTS, "bank_seed": BANK_SEED, "eval_seed": EVAL_SEED,
        "train_seconds": round(history["seconds"], 2), "objects": list(objects), "held_out": list(held),
        "metrics": {"unit": "chamfer_cm2: Chamfer distance in cm²; rms_mm: RMS nearest-neighbour distance in mm",
                    **history["final"], "per_object": per_object},
    }
    return model, history


# --------------------------------------------------------------------------------------------
# A training run's files


#: The kind of an encoder training run's output folder (the same as the ``train_encoder`` recipe's).
TRAINING_KIND = "encoder training run"


def is_training_output(path) -> bool:
    """``path`` is a folder a training run wrote: its ``encoder.json`` carries :data:`TRAINING_KIND`."""
    d = json.loads((Path(path) / "encoder.json").read_text(encoding="utf-8"))
    return isinstance(d, dict) and d.get("adadex_output") == TRAINING_KIND


def save_training_run(out, model: PointCloudAutoencoder, history: dict) -> dict[str, Path]:
    """Write a training run's ``encoder.pt``, ``latents.npz`` (every registry object's latent, the
    environment's table), ``encoder.json`` (metrics) and ``reconstructions.png`` to ``out``.

    ``encoder.json`` holds the checkpoint's metadata (settings, objects, train / held-out Chamfer per
    object and means) plus the untrained model's Chamfer, the :func:`resampling_floor` and the
    evaluation curve, and the marker ``"adadex_output": TRAINING_KIND`` by which a rerun of ``adadex
    encoder train --out`` recognizes the folder as an earlier output (:func:`is_training_output`).
    """
    out = Path(out)
    meta = {**history["meta"], "threads": torch.get_num_threads()}
    floor = summarize_evaluation(resampling_floor(meta["objects"] + meta["held_out"], points=model.config.points))
    report = {"adadex_output": TRAINING_KIND, **meta, "initial": history["initial"], "resampling_floor": floor,
              "evals": history["evals"]}
    # encoder.json (with the marker) first: a rerun after a run killed while writing the rest recognizes the folder
    metrics = atomic_write_text(out / "encoder.json", json.dumps(report, indent=1, ensure_ascii=False))
    return {"checkpoint": save_encoder(out / "encoder.pt", model, meta),
            "latents": save_latents(out / "latents.npz", object_latents(model)),
            "metrics": metrics,
            "figure": plot_reconstructions(model, PLOT_OBJECTS, out / "reconstructions.png")}



# --------------------------------------------------------------------------------------------
# Figure


@torch.no_grad()
def plot_reconstructions(model: PointCloudAutoencoder, objects: Sequence[str] = PLOT_OBJECTS,
                         path="reconstructions.png", *, seed: int = EVAL_SEED) -> Path:
    """Fig. 5 style: each object's points (top row) above its decoded points (bottom row), as a PNG.

    Both clouds of a column share the same axes limits and equal aspect, so size errors show. Held-out
    objects are marked; each reconstruction's RMS nearest-neighbour distance is in its title.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    objects = tuple(objects)
    clouds = surface_clouds(objects, model.config.points, seed)
    model.eval()
    recon = model(clouds)
    rms_mm = chamfer_distance(recon, clouds).sqrt() * 1e3
    held = set(held_out_objects())
    fig = plt.figure(figsize=(2.4 * len(objects), 5.0))
    for j, name in enumerate(objects):
        half = float(clouds[j].abs().amax()) * 1.05
        for row, (pts, title) in enumerate(((clouds[j], name + (" (held out)" if name in held else "")),
                                            (recon[j], f"decoded, RMS {rms_mm[j]:.1f} mm"))):
            ax = fig.add_subplot(2, len(objects), row * len(objects) + j + 1, projection="3d")
            p = pts.numpy() * 100.0  # cm
            ax.scatter(p[:, 0], p[:, 1], p[:, 2], s=1.5, c=p[:, 2], cmap="viridis" if row == 0 else "plasma")
            for set_lim in (ax.set_xlim, ax.set_ylim, ax.set_zlim):
                set_lim(-half * 100, half * 100)
            ax.set_box_aspect((1, 1, 1))
            ax.set_title(title, fontsize=8)
            ax.tick_params(labelsize=5)
    fig.suptitle("object points (top) and decoded points (bottom), cm", fontsize=10)
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=100)
    plt.close(fig)
    return atomic_write_bytes(path, buf.getvalue())
