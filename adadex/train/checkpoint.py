"""Training checkpoints: everything a run needs to continue after ``kill -9``.

One file, ``<out>/checkpoint.pt``, written atomically (temp file + rename) every
``checkpoint_every`` iterations: the policy and critic (with their observation normalizers, which
are module buffers), the optimizer, the frame and iteration counters, the RNG states of torch,
numpy and Python, and the run's config. A kill between two checkpoints loses at most the
iterations since the last one.
"""

from __future__ import annotations

import random
from pathlib import Path

import numpy as np
import torch

from adadex.errors import AdadexError
from adadex.io import atomic_write

CHECKPOINT = "checkpoint.pt"


class CheckpointError(AdadexError, ValueError):
    """A checkpoint that cannot be read or does not belong to this run."""


def rng_state() -> dict:
    return {"torch": torch.get_rng_state(), "numpy": np.random.get_state(), "python": random.getstate()}


def set_rng_state(state: dict) -> None:
    torch.set_rng_state(state["torch"])
    np.random.set_state(state["numpy"])
    random.setstate(state["python"])


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
        blob = torch.load(path, map_location="cpu", weights_only=False)
    except Exception as e:  # torch raises several types for a damaged file
        raise CheckpointError(f"{path}: not a readable training checkpoint ({e})") from e
    if not isinstance(blob, dict) or blob.get("kind") != "adadex-train":
        raise CheckpointError(f"{path}: not an adadex training checkpoint")
    return blob
