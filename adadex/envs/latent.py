"""The object latent until a trained point-cloud encoder exists: a fixed 64-D vector per object.

:func:`fixed_object_latent` describes an object's shape with a few deterministic point-cloud
statistics — bounding-box extents, principal spreads, histograms of the points' distance from the
centre and of their height — and maps them to 64 dimensions with a fixed random projection
(seed 0) and ``tanh``. Similar shapes get similar latents, every object gets a distinct one, and
the same object always gets the same one. It is a stand-in, not a learned embedding: the
point-cloud encoder (``adadex.modules``) replaces it as the environment's latent hook.

Example
-------
>>> z = fixed_object_latent("cube_050")
>>> z.shape, bool((abs(z) < 1).all())
((64,), True)
"""

from __future__ import annotations

import functools

import numpy as np

from adadex.envs.observation import LATENT_DIM
from adadex.sim.objects import get_object

_BINS = 16


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
    """(64,) float32, read-only: the stand-in latent of ``object_name`` (see the module docstring)."""
    return _latent(object_name)
