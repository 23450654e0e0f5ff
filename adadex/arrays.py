"""Functions that run on torch tensors and numpy arrays alike.

The per-frame quantities of tracking — quaternion differences, the flat observation, the metric
errors, the reward — are each defined once and called both by the policy modules and evaluation (on
torch tensors, with autograd) and by :class:`~adadex.envs.tracking.TrackingEnv`'s step (on the numpy
arrays MuJoCo fills: small numpy ops cost a fraction of torch's dispatch, and the env's step is
dominated by such ops). They pick their namespace with :func:`namespace` and use only names that
torch and numpy share (``concatenate``, ``stack``, ``where``, ``sqrt``, ``arctan2``, ``clip``,
``linalg.vector_norm`` with ``axis=``; methods ``sum``/``mean`` with ``axis=``, ``reshape``).

Example
-------
>>> import numpy as np, torch
>>> namespace(np.zeros(3)) is np, namespace(torch.zeros(3)) is torch
(True, True)
"""

from __future__ import annotations

import numpy as np
import torch


def namespace(x):
    """``torch`` for a tensor, ``numpy`` for anything else."""
    return torch if isinstance(x, torch.Tensor) else np


def to_float(mask, like):
    """A boolean mask as 0/1 numbers of ``like``'s dtype."""
    return mask.to(like.dtype) if isinstance(mask, torch.Tensor) else mask.astype(like.dtype)
