"""The point-cloud encoder: a PointNet-style autoencoder whose 64-D code is the object latent.

Paper, "Object latent": an autoencoder trained with the Chamfer distance on object point clouds;
the encoder half maps an object's point cloud to the 64-D latent the tracker and the modulator see.

* :class:`PointCloudAutoencoder` — a shared per-point MLP and a max-pool (order-free), a linear head
  and ``tanh`` to a 64-D latent; an MLP decoder back to a fixed number of points.
* :class:`PointCloudEncoder` — the encoder half as a ``TensorDictModule``:
  ``("object", "points")`` (…, N, 3) → ``("object", "latent")`` (…, 64).
* :func:`chamfer_distance` — the one Chamfer implementation, for training and evaluation.
* :func:`save_encoder` / :func:`load_encoder` — checkpoints;
* :func:`object_latents` / :func:`save_latents` — the per-object latent table the environment reads;
* :func:`surface_clouds` — objects' surface samples (cached), the clouds latents and evaluations use.

Training, evaluation, the reconstruction figure and the ``adadex encoder`` command live in the
training layer: :mod:`adadex.train.encoder` and :mod:`adadex.train.encoder_cli`.

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
from collections.abc import Sequence
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch
from tensordict.nn import TensorDictModule
from torch import nn

from adadex.envs.observation import LATENT_DIM, OBJECT_LATENT
from adadex.errors import AdadexError, ArrayError
from adadex.io import atomic_write
from adadex.sim.objects import OBJECT_NAMES, get_object

#: Structured key of an object's point cloud (object frame, metres), the encoder's input.
OBJECT_POINTS = ("object", "points")
#: Metres → model units (decimetres): objects of 3–25 cm become coordinates of O(1).
UNIT_SCALE = 10.0
#: Surface-sampling seed of the cloud each object's latent in the environment's table is computed from.
LATENT_SEED = 0

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

    Args:
        a: (B, N, 3) clouds.
        b: (B, M, 3) clouds, as many as ``a``; other shapes raise :class:`~adadex.errors.ArrayError`.

    Returns:
        (B,) the distance, in the clouds' unit squared.

    Examples:
        >>> a = torch.zeros(1, 2, 3)
        >>> b = torch.tensor([[[0.0, 0.0, 1.0]]])
        >>> chamfer_distance(a, a), chamfer_distance(a, b)
        (tensor([0.]), tensor([1.]))
    """
    if a.dim() != 3 or b.dim() != 3 or a.shape[-1] != 3 or b.shape[-1] != 3 or a.shape[0] != b.shape[0]:
        raise ArrayError(f"chamfer_distance expects (B, N, 3) and (B, M, 3), got {tuple(a.shape)} and {tuple(b.shape)}")
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
    """The point-cloud autoencoder's architecture.

    Attributes:
        points: input points per cloud in training and for the env latent (default 512).
        decoded_points: points of a decoded cloud (default 512).
        widths: the encoder's per-point MLP widths after the 3 inputs (default (64, 128, 256)).
        decoder_widths: the decoder MLP's hidden widths (default (128, 256)).
        latent_dim: size of the latent (default 64, the env's ``LATENT_DIM``).
        unit_scale: model units per metre (default :data:`UNIT_SCALE`, 10: decimetres).
    """

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

    Args:
        config: the architecture (default :class:`EncoderConfig`).

    Examples:
        >>> import torch
        >>> model = PointCloudAutoencoder()
        >>> model.encode(torch.rand(2, 100, 3) * 0.05).shape
        torch.Size([2, 64])
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

    Args:
        autoencoder: the trained :class:`PointCloudAutoencoder` whose encoder half runs (e.g. from
            :func:`load_encoder`); default an untrained one.
        in_key: the point-cloud key read (default ``("object", "points")``).
        out_key: the latent key written (default ``("object", "latent")``).

    Example:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> enc = PointCloudEncoder()
        >>> td = enc(TensorDict({("object", "points"): torch.rand(2, 128, 3) * 0.05}, batch_size=[2]))
        >>> td["object", "latent"].shape
        torch.Size([2, 64])
    """

    def __init__(self, autoencoder: PointCloudAutoencoder | None = None, *,
                 in_key=OBJECT_POINTS, out_key=OBJECT_LATENT):
        super().__init__(_Encode(autoencoder or PointCloudAutoencoder()), in_keys=[in_key], out_keys=[out_key])

    @property
    def autoencoder(self) -> PointCloudAutoencoder:
        return self.module.autoencoder


# --------------------------------------------------------------------------------------------
# Surface samples


@functools.lru_cache(maxsize=1024)
def surface_points(name: str, points: int, seed: int) -> np.ndarray:
    """One object's surface sample (``points`` × 3, metres, read-only), cached: latents and
    evaluations during training re-use the same clouds.

    Args:
        name: a known object's name.
        points: how many surface points.
        seed: the sampling seed.
    """
    pts = get_object(name).point_cloud(points, seed=seed)
    pts.setflags(write=False)
    return pts


def surface_clouds(objects: Sequence[str], points: int, seed: int) -> torch.Tensor:
    """(len(objects), points, 3) float32: :func:`surface_points` of each object, stacked."""
    return torch.from_numpy(np.stack([surface_points(o, points, seed) for o in objects]))


# --------------------------------------------------------------------------------------------
# Checkpoints


class EncoderCheckpointError(AdadexError, ValueError):
    """A file that is not a readable encoder checkpoint (the message names the file)."""


def save_encoder(path, model: PointCloudAutoencoder, meta: dict | None = None) -> Path:
    """Write ``model`` (config, state_dict) and ``meta`` (JSON-like: seed, steps, metrics, objects) atomically.

    Args:
        path: the checkpoint file to write.
        model: the autoencoder.
        meta: free-form information stored with it (default none).

    Returns:
        the path written.

    Examples:
        >>> import tempfile, os
        >>> path = save_encoder(os.path.join(tempfile.mkdtemp(), "encoder.pt"), PointCloudAutoencoder(), {"steps": 0})
        >>> load_encoder(path)[1]
        {'steps': 0}
    """
    payload = {"format": _FORMAT, "version": _VERSION, "config": asdict(model.config),
               "state_dict": {k: v.detach().clone() for k, v in model.state_dict().items()},
               "meta": dict(meta or {})}
    return atomic_write(path, lambda f: torch.save(payload, f))


def load_encoder(path) -> tuple[PointCloudAutoencoder, dict]:
    """Read a checkpoint written by :func:`save_encoder` → ``(model in eval mode, meta)``.

    Raises ``FileNotFoundError`` for a missing file and :class:`EncoderCheckpointError` for anything
    that is not a complete checkpoint of this format; both name the file.

    Args:
        path: the checkpoint file.

    Returns:
        ``(model, meta)``: the :class:`PointCloudAutoencoder` on the CPU, in eval mode, and the
        ``meta`` dict saved with it.
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
    :data:`LATENT_SEED`) — the table the environment reads (:class:`adadex.envs.latent.EncoderLatents`).

    Args:
        model: the autoencoder (put in eval mode).
        objects: object names (default: every known object).
    """
    names = list(OBJECT_NAMES if objects is None else objects)
    clouds = torch.stack([torch.tensor(surface_points(n, model.config.points, LATENT_SEED)) for n in names])
    z = model.eval().encode(clouds).numpy().astype(np.float32)
    return dict(zip(names, z))


def save_latents(path, latents: dict[str, np.ndarray]) -> Path:
    """Write an object-latent table (``names``, ``latents``) as ``.npz``, atomically."""
    names = np.array(list(latents), dtype=str)
    table = np.stack([np.asarray(latents[n], dtype=np.float32) for n in latents])
    return atomic_write(path, lambda f: np.savez(f, names=names, latents=table))
