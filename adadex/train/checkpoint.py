"""Training checkpoints: everything a run needs to continue after ``kill -9``.

One file, ``<out>/checkpoint.pt``, written atomically (temp file + rename) every
``checkpoint_every`` iterations: the policy and critic (with their observation normalizers, which
are module buffers), the optimizer, the frame and iteration counters, the RNG states of torch,
numpy and Python, and the run's config. A kill between two checkpoints loses at most the
iterations since the last one.

Checkpoints are read with ``torch.load(weights_only=True)``: only tensors and plain data (dicts,
lists, tuples, str, numbers, None) are unpickled, so a crafted ``checkpoint.pt`` cannot run code on
``resume=true``; one holding anything else is refused with one line naming the file. The RNG states
are therefore saved as tensors and plain numbers. Checkpoints written before this (numpy's RNG state
as a numpy array) still load: numpy arrays of plain numeric types are also accepted.
"""

from __future__ import annotations

import pickle
import random
import re
from pathlib import Path

import numpy as np
import torch

from adadex.errors import AdadexError
from adadex.io import atomic_write

CHECKPOINT = "checkpoint.pt"


class CheckpointError(AdadexError, ValueError):
    """A checkpoint that cannot be read or does not belong to this run."""


def rng_state() -> dict:
    """The RNG states of torch, numpy and Python as tensors and plain data (loadable with ``weights_only``)."""
    st = np.random.get_state(legacy=False)
    if st["bit_generator"] != "MT19937":      # the legacy global RandomState is always MT19937
        raise CheckpointError(f"numpy's global RNG is {st['bit_generator']}, expected MT19937")
    numpy_state = {"bit_generator": st["bit_generator"],
                   "key": torch.from_numpy(st["state"]["key"].astype(np.int64)),
                   "pos": int(st["state"]["pos"]), "has_gauss": int(st["has_gauss"]), "gauss": float(st["gauss"])}
    return {"torch": torch.get_rng_state(), "numpy": numpy_state, "python": random.getstate()}


def set_rng_state(state: dict) -> None:
    """Restore what :func:`rng_state` returned (or a checkpoint of before, with numpy's state as a tuple)."""
    torch.set_rng_state(state["torch"])
    st = state["numpy"]
    if isinstance(st, dict):
        key = st["key"].numpy() if isinstance(st["key"], torch.Tensor) else np.asarray(st["key"])
        st = {"bit_generator": st["bit_generator"], "state": {"key": key.astype(np.uint32), "pos": int(st["pos"])},
              "has_gauss": int(st["has_gauss"]), "gauss": float(st["gauss"])}
    np.random.set_state(st)
    random.setstate(_as_tuples(state["python"]))


def _as_tuples(x):
    """Python's RNG state with its lists as tuples, as ``random.setstate`` needs them."""
    return tuple(_as_tuples(v) for v in x) if isinstance(x, (list, tuple)) else x


#: Beyond tensors and plain data, what ``load_checkpoint`` unpickles: numpy arrays of plain numeric
#: types (checkpoints written before the RNG states were stored as tensors hold numpy's as an array).
_NUMPY_GLOBALS = [np._core.multiarray._reconstruct, (np._core.multiarray._reconstruct, "numpy.core.multiarray._reconstruct"),
                  np.ndarray, np.dtype, np.dtypes.UInt32DType, np.dtypes.Int64DType, np.dtypes.Float64DType]


def save_checkpoint(out, *, module: torch.nn.Module, optimizer: torch.optim.Optimizer, iteration: int, frames: int,
                    config: dict, extra: dict | None = None) -> Path:
    blob = {"kind": "adadex-train", "module": module.state_dict(), "optimizer": optimizer.state_dict(),
            "iteration": iteration, "frames": frames, "config": config, "rng": rng_state(), "extra": extra or {}}
    return atomic_write(Path(out) / CHECKPOINT, lambda f: torch.save(blob, f))


def load_checkpoint(out) -> dict | None:
    """The checkpoint in ``out``, or ``None`` when there is none yet."""
    path = Path(out) / CHECKPOINT
    if not path.is_file():
        return None
    try:
        with torch.serialization.safe_globals(_NUMPY_GLOBALS):
            blob = torch.load(path, map_location="cpu", weights_only=True)
    except pickle.UnpicklingError as e:
        found = re.search(r"Unsupported global: GLOBAL (\S+)", str(e))
        if found is None:
            raise CheckpointError(f"{path}: not a readable training checkpoint (UnpicklingError: "
                                  f"{(str(e).strip().splitlines() or [''])[0]})") from None
        raise CheckpointError(f"{path}: refused: the checkpoint holds a Python object ({found.group(1)}) beyond "
                              f"tensors and plain data, and loading it could run code; adadex did not write it"
                              ) from None
    except Exception as e:  # torch raises several types for a damaged file
        first = (str(e).strip().splitlines() or [type(e).__name__])[0]
        raise CheckpointError(f"{path}: not a readable training checkpoint ({type(e).__name__}: {first})") from e
    if not isinstance(blob, dict) or blob.get("kind") != "adadex-train":
        raise CheckpointError(f"{path}: not an adadex training checkpoint")
    return blob
