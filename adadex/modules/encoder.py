"""The point-cloud encoder: a PointNet-style autoencoder whose 64-D code is the object latent.

Paper, "Object latent": an autoencoder trained with the Chamfer distance on object point clouds;
the encoder half maps an object's point cloud to the 64-D latent the tracker and the modulator see.

* :class:`PointCloudAutoencoder` — a shared per-point MLP and a max-pool (order-free), a linear head
  and ``tanh`` to a 64-D latent; an MLP decoder back to a fixed number of points.
* :class:`PointCloudEncoder` — the encoder half as a ``TensorDictModule``:
  ``("object", "points")`` (…, N, 3) → ``("object", "latent")`` (…, 64).
* :func:`chamfer_distance` — the one Chamfer implementation, for training and evaluation.
* :func:`object_latents` / :func:`save_latents` — the per-object latent table the environment reads;
* :func:`train_encoder`, :func:`evaluate_encoder`, :func:`save_encoder` / :func:`load_encoder`,
  :func:`plot_reconstructions` (the paper's Fig. 5: object points beside decoded points).

Units. Clouds are in the object frame in metres. The model centres every cloud on its bounding-box
centre and multiplies by :data:`UNIT_SCALE` (metres → decimetres) so coordinates are O(1); it never
rescales a cloud to unit size, because an object's size matters for grasping and must reach the
latent. Reported metrics are the Chamfer distance in **cm²** and the RMS nearest-neighbour
distance in **mm** (``1000 · sqrt(Chamfer in m²)``, see :func:`chamfer_distance`).

The trained model shipped in ``assets/encoder/encoder.pt`` gives the environment its object latent
through the table ``assets/encoder/latents.npz`` (:func:`object_latents`, read by
:func:`adadex.envs.latent.encoder_latent`). It was made with the default settings,
``adadex encoder train --threads 1 --out outputs/encoder_shipped`` (3000 steps, batch 16, 512 points,
lr 1e-3, seed 0; about 4 min on one core), and ``encoder.pt`` / ``latents.npz`` / ``encoder.json``
copied over; ``assets/encoder/encoder.json`` holds its metrics.

Example
-------
>>> import torch
>>> from tensordict import TensorDict
>>> enc = PointCloudEncoder(PointCloudAutoencoder())
>>> td = TensorDict({"object": {"points": torch.rand(4, 2, 512, 3) * 0.1}}, batch_size=[4, 2])
>>> enc(td)["object", "latent"].shape
torch.Size([4, 2, 64])
>>> a = torch.tensor([[[0.0, 0, 0], [1, 0, 0]]]); b = torch.tensor([[[0.0, 0, 0]]])
>>> chamfer_distance(a, b)      # a→b: (0 + 1) / 2, b→a: 0; mean of the two directions
tensor([0.2500])
"""

from __future__ import annotations

import functools
import io
import json
import time
from collections.abc import Sequence
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch
from tensordict.nn import TensorDictModule
from torch import nn

from adadex.envs.observation import LATENT_DIM, OBJECT_LATENT
from adadex.errors import AdadexError
from adadex.io import atomic_write, atomic_write_bytes, atomic_write_text
from adadex.sim.objects import OBJECT_NAMES, get_object, held_out_objects

#: Structured key of an object's point cloud (object frame, metres), the encoder's input.
OBJECT_POINTS = ("object", "points")
#: Metres → model units (decimetres): objects of 3–25 cm become coordinates of O(1).
UNIT_SCALE = 10.0
#: Points per object in the training bank; every step draws fresh subsets from it.
BANK_POINTS = 4096
#: Surface-sampling seeds: the training bank, evaluation clouds (fresh samples, never trained on),
#: and the cloud each object's latent in the environment's table is computed from.
BANK_SEED, EVAL_SEED, LATENT_SEED = 1, 2, 0
#: Default objects in the reconstruction figure: four training objects, three held-out ones.
PLOT_OBJECTS = ("cube_050", "mug_00", "hammer_00", "wineglass_00", "mug_03", "torus_02", "hammer_03")

_FORMAT = "adadex-point-cloud-autoencoder"
_VERSION = 1


# --------------------------------------------------------------------------------------------
# Chamfer distance


def chamfer_distance(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Symmetric Chamfer distance, (B, N, 3) × (B, M, 3) → (B,): mean squared nearest-neighbour distance.

    ``0.5 · (mean_i min_j |a_i − b_j|² + mean_j min_i |a_i − b_j|²)``: the mean of the two directions,
    so ``sqrt`` of it is the RMS nearest-neighbour distance (in the clouds' unit). The neighbours are
    found with ``torch.cdist`` without gradient and the distances recomputed for the matched pairs:
    same value and gradient as differentiating ``cdist(a, b).min(…)²`` (the min passes its gradient
    to the arg-min), at a fraction of the cost, since cdist's backward touches all N × M pairs.
    """
    if a.dim() != 3 or b.dim() != 3 or a.shape[-1] != 3 or b.shape[-1] != 3 or a.shape[0] != b.shape[0]:
        raise ValueError(f"chamfer_distance expects (B, N, 3) and (B, M, 3), got {tuple(a.shape)} and {tuple(b.shape)}")
    with torch.no_grad():
        d = torch.cdist(a, b, compute_mode="donot_use_mm_for_euclid_dist")  # exact: 0 for equal points
        a_to_b, b_to_a = d.argmin(2), d.argmin(1)
    nearest_b = b.gather(1, a_to_b[..., None].expand(-1, -1, 3))
    nearest_a = a.gather(1, b_to_a[..., None].expand(-1, -1, 3))
    return 0.5 * ((a - nearest_b).square().sum(-1).mean(-1) + (b - nearest_a).square().sum(-1).mean(-1))


# --------------------------------------------------------------------------------------------
# Model


@dataclass(frozen=True)
class EncoderConfig:
    """Architecture. ``points``: input points per cloud in training and for the env latent."""

    points: int = 512
    decoded_points: int = 512
    widths: tuple[int, ...] = (64, 128, 256)
    decoder_widths: tuple[int, ...] = (128, 256)
    latent_dim: int = LATENT_DIM
    unit_scale: float = UNIT_SCALE

    @classmethod
    def from_dict(cls, d: dict) -> EncoderConfig:
        return cls(**{k: tuple(v) if isinstance(v, list) else v for k, v in d.items()})


def _mlp(sizes: Sequence[int], *, last_relu: bool) -> nn.Sequential:
    layers: list[nn.Module] = []
    for i, (n_in, n_out) in enumerate(zip(sizes[:-1], sizes[1:])):
        layers.append(nn.Linear(n_in, n_out))
        if last_relu or i < len(sizes) - 2:
            layers.append(nn.ReLU())
    return nn.Sequential(*layers)


class PointCloudAutoencoder(nn.Module):
    """PointNet-style autoencoder of object point clouds; its encoder gives the 64-D object latent.

    Encoder: per-point MLP (3 → 64 → 128 → 256, weights shared by all points) → max-pool over the
    points (so the latent does not depend on point order or count) → linear → ``tanh``. The
    latent is squashed into (−1, 1) like the stand-in latent it replaces because the modulator's O
    channel perturbs the latent within a bounded range: a bounded latent keeps such a perturbation
    meaningful relative to the latent itself and keeps the policy's inputs in a known range.

    Decoder: MLP 64 → 128 → 256 → ``decoded_points`` × 3, in model units (see :meth:`normalise`).

    No batch normalisation: a cloud's latent depends on that cloud alone, the same in training
    and evaluation.
    """

    def __init__(self, config: EncoderConfig | None = None):
        super().__init__()
        self.config = config = config or EncoderConfig()
        self.point_mlp = _mlp((3, *config.widths), last_relu=True)
        self.head = nn.Linear(config.widths[-1], config.latent_dim)
        self.decoder = _mlp((config.latent_dim, *config.decoder_widths, 3 * config.decoded_points), last_relu=False)

    def normalise(self, points: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(…, N, 3) metres → (centred cloud in model units, (…, 1, 3) bounding-box centre in metres).

        Centring on the bounding-box centre (not the mean) makes the frame independent of how
        densely each part of the surface was sampled; there is no per-cloud rescaling.
        """
        centre = 0.5 * (points.amax(-2, keepdim=True) + points.amin(-2, keepdim=True))
        return (points - centre) * self.config.unit_scale, centre

    def encode(self, points: torch.Tensor) -> torch.Tensor:
        """(…, N, 3) points in metres → (…, 64) latent in (−1, 1)."""
        x, _ = self.normalise(points)
        return self.encode_normalised(x)

    def encode_normalised(self, x: torch.Tensor) -> torch.Tensor:
        """(…, N, 3) centred cloud in model units → (…, 64) latent."""
        return torch.tanh(self.head(self.point_mlp(x).amax(-2)))

    def decode(self, latent: torch.Tensor) -> torch.Tensor:
        """(…, 64) latent → (…, M, 3) decoded cloud, centred, in model units."""
        return self.decoder(latent).unflatten(-1, (self.config.decoded_points, 3))

    def forward(self, points: torch.Tensor) -> torch.Tensor:
        """(…, N, 3) points in metres → (…, M, 3) reconstruction in metres, in the input's frame."""
        x, centre = self.normalise(points)
        return self.decode(self.encode_normalised(x)) / self.config.unit_scale + centre

    def loss(self, points: torch.Tensor) -> torch.Tensor:
        """(B,) Chamfer distance of the reconstructions in model units² (dm²), the training loss."""
        x, _ = self.normalise(points)
        return chamfer_distance(self.decode(self.encode_normalised(x)), x)


class _Encode(nn.Module):
    """The encoder half of an autoencoder as a module (the TensorDictModule wraps this)."""

    def __init__(self, autoencoder: PointCloudAutoencoder):
        super().__init__()
        self.autoencoder = autoencoder

    def forward(self, points: torch.Tensor) -> torch.Tensor:
        return self.autoencoder.encode(points)


class PointCloudEncoder(TensorDictModule):
    """The object-latent encoder as a ``TensorDictModule``.

    In: ``("object", "points")`` (…, N, 3) float, object frame, metres; any leading batch dims and
    any N. Out: ``("object", "latent")`` (…, 64) float in (−1, 1).
    """

    def __init__(self, autoencoder: PointCloudAutoencoder | None = None, *,
                 in_key=OBJECT_POINTS, out_key=OBJECT_LATENT):
        super().__init__(_Encode(autoencoder or PointCloudAutoencoder()), in_keys=[in_key], out_keys=[out_key])

    @property
    def autoencoder(self) -> PointCloudAutoencoder:
        return self.module.autoencoder


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


@functools.lru_cache(maxsize=1024)
def _surface(name: str, points: int, seed: int) -> np.ndarray:
    """One object's surface sample, cached: evaluation during training re-uses the same clouds."""
    pts = get_object(name).point_cloud(points, seed=seed)
    pts.setflags(write=False)
    return pts


def _eval_clouds(objects: Sequence[str], points: int, seed: int) -> torch.Tensor:
    return torch.from_numpy(np.stack([_surface(o, points, seed) for o in objects]))


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
    """
    objects = tuple(objects) if objects is not None else OBJECT_NAMES
    clouds = _eval_clouds(objects, points or model.config.points, seed)
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
    cd = chamfer_distance(_eval_clouds(objects, points, seed), _eval_clouds(objects, points, seed + 1))
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


def _check_settings(steps: int, batch_size: int, points: int, lr: float) -> None:
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
    """
    from tqdm.auto import tqdm

    _check_settings(steps, batch_size, points, lr)
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
    bar = tqdm(range(steps), desc="encoder", disable=not progress, dynamic_ncols=True)
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
# Checkpoints


class EncoderCheckpointError(AdadexError, ValueError):
    """A file that is not a readable encoder checkpoint (the message names the file)."""


def save_encoder(path, model: PointCloudAutoencoder, meta: dict | None = None) -> Path:
    """Write ``model`` (config, state_dict) and ``meta`` (JSON-like: seed, steps, metrics, objects) atomically."""
    payload = {"format": _FORMAT, "version": _VERSION, "config": asdict(model.config),
               "state_dict": {k: v.detach().clone() for k, v in model.state_dict().items()},
               "meta": dict(meta or {})}
    return atomic_write(path, lambda f: torch.save(payload, f))


def load_encoder(path) -> tuple[PointCloudAutoencoder, dict]:
    """Read a checkpoint written by :func:`save_encoder` → ``(model in eval mode, meta)``.

    Raises ``FileNotFoundError`` for a missing file and :class:`EncoderCheckpointError` for anything
    that is not a complete checkpoint of this format; both name the file.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"encoder checkpoint {path} does not exist (or is not a file)")
    try:
        payload = torch.load(io.BytesIO(path.read_bytes()), map_location="cpu", weights_only=True)
    except Exception as e:  # noqa: BLE001  (torch raises many types for a damaged file)
        raise EncoderCheckpointError(f"{path} is not a readable encoder checkpoint: {type(e).__name__}: {e}") from e
    if not isinstance(payload, dict) or payload.get("format") != _FORMAT:
        raise EncoderCheckpointError(f"{path} is not an adadex encoder checkpoint (format {_FORMAT!r} expected)")
    if payload.get("version") != _VERSION:
        raise EncoderCheckpointError(f"{path}: unsupported encoder checkpoint version {payload.get('version')!r}")
    try:
        model = PointCloudAutoencoder(EncoderConfig.from_dict(payload["config"]))
        model.load_state_dict(payload["state_dict"])
    except (KeyError, TypeError, RuntimeError) as e:
        raise EncoderCheckpointError(f"{path}: damaged encoder checkpoint: {type(e).__name__}: {e}") from e
    return model.eval(), payload.get("meta", {})


@torch.no_grad()
def object_latents(model: PointCloudAutoencoder, objects: Sequence[str] | None = None) -> dict[str, np.ndarray]:
    """{object: (64,) float32 latent} from each object's surface cloud (``config.points`` points,
    :data:`LATENT_SEED`) — the table the environment reads (:class:`adadex.envs.latent.EncoderLatents`)."""
    names = list(OBJECT_NAMES if objects is None else objects)
    clouds = torch.stack([torch.tensor(_surface(n, model.config.points, LATENT_SEED)) for n in names])
    z = model.eval().encode(clouds).numpy().astype(np.float32)
    return dict(zip(names, z))


def save_latents(path, latents: dict[str, np.ndarray]) -> Path:
    """Write an object-latent table (``names``, ``latents``) as ``.npz``, atomically."""
    names = np.array(list(latents), dtype=str)
    table = np.stack([np.asarray(latents[n], dtype=np.float32) for n in latents])
    return atomic_write(path, lambda f: np.savez(f, names=names, latents=table))


def save_training_run(out, model: PointCloudAutoencoder, history: dict) -> dict[str, Path]:
    """Write a training run's ``encoder.pt``, ``latents.npz`` (every registry object's latent, the
    environment's table), ``encoder.json`` (metrics) and ``reconstructions.png`` to ``out``.

    ``encoder.json`` holds the checkpoint's metadata (settings, objects, train / held-out Chamfer per
    object and means) plus the untrained model's Chamfer, the :func:`resampling_floor` and the
    evaluation curve.
    """
    out = Path(out)
    meta = {**history["meta"], "threads": torch.get_num_threads()}
    floor = summarize_evaluation(resampling_floor(meta["objects"] + meta["held_out"], points=model.config.points))
    report = {**meta, "initial": history["initial"], "resampling_floor": floor, "evals": history["evals"]}
    return {"checkpoint": save_encoder(out / "encoder.pt", model, meta),
            "latents": save_latents(out / "latents.npz", object_latents(model)),
            "metrics": atomic_write_text(out / "encoder.json", json.dumps(report, indent=1, ensure_ascii=False)),
            "figure": plot_reconstructions(model, PLOT_OBJECTS, out / "reconstructions.png")}


# --------------------------------------------------------------------------------------------
# Figure


@torch.no_grad()
def plot_reconstructions(model: PointCloudAutoencoder, objects: Sequence[str] = PLOT_OBJECTS, path="reconstructions.png",
                         *, seed: int = EVAL_SEED) -> Path:
    """Fig. 5 style: each object's points (top row) above its decoded points (bottom row), as a PNG.

    Both clouds of a column share the same axes limits and equal aspect, so size errors show. Held-out
    objects are marked; each reconstruction's RMS nearest-neighbour distance is in its title.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    objects = tuple(objects)
    clouds = _eval_clouds(objects, model.config.points, seed)
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


# --------------------------------------------------------------------------------------------
# Command line: ``adadex encoder train|eval`` (registered by adadex.cli)


def _summary_line(label: str, summary: dict) -> str:
    parts = [f"{split} {s['chamfer_cm2']:.4f} cm² (RMS {s['rms_mm']:.2f} mm, {s['objects']} objects)"
             for split, s in summary.items()]
    return f"{label}: Chamfer " + "; ".join(parts)


def _cmd_train(a) -> int:
    _check_settings(a.steps, a.batch_size, a.points, a.lr)
    out = Path(a.out)
    if out.exists() and not out.is_dir():
        raise ValueError(f"--out {out} exists and is not a folder")
    if a.threads:
        torch.set_num_threads(a.threads)
    print(f"training the point-cloud encoder: {a.steps} steps, batch {a.batch_size}, {a.points} points, "
          f"lr {a.lr}, seed {a.seed}, {torch.get_num_threads()} threads → {out}")
    model, history = train_encoder(steps=a.steps, batch_size=a.batch_size, points=a.points, lr=a.lr,
                                   seed=a.seed, progress=not a.quiet)
    paths = save_training_run(out, model, history)
    print(f"trained in {history['seconds']:.0f} s")
    print("untrained: Chamfer " + "; ".join(f"{k} {v:.4f} cm²" for k, v in history["initial"].items()))
    print(_summary_line("trained", history["final"]))
    print("wrote " + ", ".join(map(str, paths.values())))
    return 0


def _cmd_eval(a) -> int:
    model, meta = load_encoder(a.checkpoint)
    out = Path(a.out)
    if out.exists() and not out.is_dir():
        raise ValueError(f"--out {out} exists and is not a folder")
    per_object = evaluate_encoder(model)
    summary = summarize_evaluation(per_object)
    floor = summarize_evaluation(resampling_floor(points=model.config.points))
    report = {"checkpoint": str(a.checkpoint), "trained": {k: meta.get(k) for k in ("seed", "steps", "batch_size", "lr")},
              "unit": "chamfer_cm2: Chamfer distance in cm²; rms_mm: RMS nearest-neighbour distance in mm",
              **summary, "resampling_floor": floor, "per_object": per_object}
    atomic_write_text(out / "eval.json", json.dumps(report, indent=1, ensure_ascii=False))
    plot_reconstructions(model, PLOT_OBJECTS, out / "reconstructions.png")
    print(_summary_line(str(a.checkpoint), summary))
    print(_summary_line("resampling floor (two samples of the same surface)", floor))
    worst = sorted(per_object.items(), key=lambda kv: -kv[1]["rms_mm"])[:3]
    print("worst: " + ", ".join(f"{n} {r['rms_mm']:.1f} mm" for n, r in worst))
    print(f"wrote {out / 'eval.json'}, {out / 'reconstructions.png'}")
    return 0


def add_parser(sub) -> None:
    """Register ``adadex encoder train|eval`` on the top-level subparsers ``sub``."""
    import argparse

    d = TrainSettings()
    enc = sub.add_parser("encoder", help="point-cloud encoder (object latent): train, eval",
                         description="Train or evaluate the point-cloud autoencoder whose 64-D code is the object "
                                     "latent. Metrics: Chamfer distance in cm², RMS nearest-neighbour distance in mm.",
                         formatter_class=argparse.RawDescriptionHelpFormatter)
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
    t.set_defaults(func=_cmd_train)
    e = esub.add_parser("eval", help="per-object Chamfer of a checkpoint on all 80 objects; eval.json and "
                                     "reconstructions.png")
    e.add_argument("checkpoint", type=Path)
    e.add_argument("--out", default="outputs/encoder_eval", help="output folder (default outputs/encoder_eval)")
    e.set_defaults(func=_cmd_eval)


def run(args) -> int:
    """Run an encoder subcommand, turning user errors into one-line messages (exit status 2)."""
    import sys

    try:
        return args.func(args)
    except (ValueError, FileNotFoundError, KeyError) as e:
        msg = e.args[0] if isinstance(e, KeyError) and e.args else e
        print(f"adadex encoder {args.encoder_command}: error: {msg}", file=sys.stderr)
        return 2
