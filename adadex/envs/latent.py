"""The object latent hook of the environment: object name → fixed 64-D vector.

Two latents, both deterministic, bounded in (−1, 1), (64,) float32 and read-only:

* :func:`encoder_latent` (the default ``latent_fn`` of :class:`~adadex.envs.tracking.TrackingEnv`):
  the paper's object latent — the trained point-cloud encoder
  (:class:`adadex.modules.encoder.PointCloudAutoencoder`, shipped as ``assets/encoder/encoder.pt``)
  applied to each object's surface point cloud (fixed sampling seed), read from the table
  ``assets/encoder/latents.npz`` written with the checkpoint. :class:`EncoderLatents` reads the
  table of any other training run (``EncoderLatents("run/latents.npz")`` is a ``latent_fn``).
* :func:`fixed_object_latent`: the stand-in used before (and without) a trained encoder. It
  describes an object's shape with a few deterministic point-cloud statistics — bounding-box
  extents, principal spreads, histograms of the points' distance from the centre and of their
  height — and maps them to 64 dimensions with a fixed random projection (seed 0) and ``tanh``.
  Similar shapes get similar latents and every object a distinct one, but it is not learned.

Example
-------
>>> z = encoder_latent("cube_050")
>>> z.shape, z.dtype, bool((abs(z) < 1).all()), z.flags.writeable
((64,), dtype('float32'), True, False)
>>> fixed_object_latent("cube_050").shape
(64,)
"""

from __future__ import annotations

import functools
from pathlib import Path

import numpy as np

from adadex.envs.observation import LATENT_DIM
from adadex.errors import ArrayError, ConfigError, UnknownKeyError
from adadex.resources import asset
from adadex.sim.objects import get_object

_BINS = 16

#: The trained encoder shipped with adadex (see ``adadex encoder train``) and its latent table.
SHIPPED_ENCODER = asset("encoder", "encoder.pt")
SHIPPED_LATENTS = SHIPPED_ENCODER.with_name("latents.npz")


def shape_features(points: np.ndarray) -> np.ndarray:
    """(38,) statistics of an (N, 3) point cloud: extents, principal spreads, radial and height histograms."""
    p = np.asarray(points, dtype=np.float64)
    c = p - p.mean(0)
    extents = p.max(0) - p.min(0)
    spreads = np.sqrt(np.sort(np.linalg.eigvalsh(np.cov(c.T)))[::-1])
    r = np.linalg.norm(c, axis=1)
    radial = np.histogram(r / max(r.max(), 1e-9), bins=_BINS, range=(0, 1))[0] / len(p)
    z = (p[:, 2] - p[:, 2].min()) / max(extents[2], 1e-9)
    height = np.histogram(z, bins=_BINS, range=(0, 1))[0] / len(p)
    return np.concatenate([10 * extents, 10 * spreads, radial, height])


@functools.lru_cache(maxsize=1)
def _projection() -> np.ndarray:
    rng = np.random.default_rng(0)
    return rng.normal(0, 1.0, (LATENT_DIM, 6 + 2 * _BINS)) / np.sqrt(6 + 2 * _BINS)


@functools.lru_cache(maxsize=None)
def _latent(object_name: str) -> np.ndarray:
    feats = shape_features(get_object(object_name).point_cloud(2048, seed=0))
    out = np.tanh(2.0 * _projection() @ (feats - 0.5)).astype(np.float32)
    out.setflags(write=False)
    return out


def fixed_object_latent(object_name: str) -> np.ndarray:
    """(64,) float32, read-only: the stand-in latent of ``object_name``, used before/without a trained
    encoder (see the module docstring).

    Args:
        object_name: a known object's name.
    """
    return _latent(object_name)


class EncoderLatents:
    """``latent_fn`` from a table of trained-encoder latents: object name → (64,) float32, read-only.

    The table (``latents.npz``: ``names`` (N,), ``latents`` (N, 64)) is written next to the
    checkpoint by ``adadex encoder train`` (:func:`adadex.modules.encoder.object_latents`, point
    clouds sampled with a fixed seed) and read here on first use. Reading a table rather than
    running the network keeps the environment free of the model code (lower layers never import
    upper ones) and makes the latent of each object a fixed, inspectable number.

    Args:
        path: the ``latents.npz`` table (default: the shipped encoder's). Calling the instance with
            an object name returns its latent; a table without that object raises
            :class:`~adadex.errors.UnknownKeyError`.
    """

    def __init__(self, path=SHIPPED_LATENTS):
        self.path = Path(path)
        self._table: dict[str, np.ndarray] | None = None

    @property
    def table(self) -> dict[str, np.ndarray]:
        if self._table is None:
            if not self.path.is_file():
                raise FileNotFoundError(f"{self.path}: no latent table there (adadex encoder train writes latents.npz)")
            try:
                with np.load(self.path, allow_pickle=False) as f:
                    names, latents = [str(n) for n in f["names"]], np.asarray(f["latents"], dtype=np.float32)
            except (OSError, KeyError, ValueError) as e:
                raise ConfigError(f"{self.path}: not a latent table ({type(e).__name__}: {e})") from e
            if latents.shape != (len(names), LATENT_DIM) or not np.isfinite(latents).all():
                raise ArrayError(f"{self.path}: latents must be finite with shape ({len(names)}, {LATENT_DIM}), "
                                 f"got {latents.shape}")
            latents.setflags(write=False)
            self._table = dict(zip(names, latents))
        return self._table

    def __call__(self, object_name: str) -> np.ndarray:
        z = self.table.get(object_name)
        if z is None:
            get_object(object_name)   # an unknown object is named as such
            raise UnknownKeyError(f"{self.path}: no latent for {object_name!r} "
                                  "(retrain or re-export the encoder's latents)")
        return z

    def __repr__(self) -> str:
        return f"EncoderLatents({str(self.path)!r})"


_shipped = EncoderLatents()


def encoder_latent(object_name: str) -> np.ndarray:
    """(64,) float32, read-only: ``object_name``'s latent from the shipped encoder (cached).

    Args:
        object_name: a known object's name.
    """
    return _shipped(object_name)
