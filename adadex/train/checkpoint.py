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

The run folder is guarded before any work (:func:`check_run`, the trainers' and recipes' one check):
someone else's files there are refused (:mod:`adadex.io`'s guard; ``force``), a run there is not
replaced without ``force`` nor continued without ``resume``, and a resume may change only the settings
in :data:`RESUME_NEUTRAL` — the one list of what does not change the result.
"""

from __future__ import annotations

import pickle
import random
import re
from pathlib import Path

import numpy as np
import torch

from adadex.errors import CheckpointError
from adadex.io import atomic_write

CHECKPOINT = "checkpoint.pt"


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
    """Write ``out/checkpoint.pt`` atomically: the module's and optimizer's state, the progress, the
    run's settings and the RNG states; return its path.

    Args:
        out: the run folder.
        module: the trained module (its ``state_dict``).
        optimizer: its optimizer (its ``state_dict``).
        iteration: training iterations done.
        frames: environment frames collected.
        config: the run's settings, compared on resume (:func:`check_run`).
        extra: anything else to restore (plain data and tensors only: :func:`load_checkpoint` loads
            with ``weights_only=True``).
    """
    blob = {"kind": "adadex-train", "module": module.state_dict(), "optimizer": optimizer.state_dict(),
            "iteration": iteration, "frames": frames, "config": config, "rng": rng_state(), "extra": extra or {}}
    return atomic_write(Path(out) / CHECKPOINT, lambda f: torch.save(blob, f))


def load_checkpoint(out) -> dict | None:
    """The checkpoint in ``out``, or ``None`` when there is none yet.

    Args:
        out: the run folder.

    Returns:
        the checkpoint's dict (loaded on the CPU, tensors and plain data only), or None.

    Raises:
        CheckpointError: a file that is not a readable adadex training checkpoint, or one holding
            Python objects beyond tensors and plain data.

    Examples:
        >>> import tempfile
        >>> load_checkpoint(tempfile.mkdtemp()) is None
        True
    """
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


# ----------------------------------------------------------------------------------------------
# The run folder: whose it is, whether it may be written, what a resume may change

#: The output kinds of the training commands (the marker in their ``out`` folder, :mod:`adadex.io`).
TRAINING_RUN = "training run"            # PPO: a tracker (specialist, vanilla PPO, IL+RL) or a modulator
DISTILLATION_RUN = "distillation run"

#: THE list of settings a resumed run may change: they do not change what it computes, only how fast,
#: how it reports, where it stops, or where it is. Every other setting (``ppo.lr``, ``policy.hidden``,
#: ``seed``, ``modulator.channels``, the dataset, …) must equal the checkpoint's, or the resume is
#: refused naming it (:func:`changed_settings`). Dotted names of :class:`~adadex.train.config.TrainConfig`
#: and :class:`~adadex.train.distill.DistillConfig` (the pipeline's stages are these runs).
RESUME_NEUTRAL = frozenset({
    # both
    "out", "resume", "progress", "wandb", "checkpoint_every",
    # PPO: how long, and how the steps are spread over threads, processes and machines
    "ppo.total_frames", "ppo.update_threads", "collector.env_threads", "collector.workers", "collector.backend",
    "collector.ray_address", "collector.start_method",
    # … and on which devices: the same computation, rounded as that device rounds (the warp backend's
    # physics agrees with the rollout backend's to 1e-5 rad; tests/sim/test_warp_backend.py)
    "ppo.device", "sim.backend",
    # distillation: how long, threads, how often a metrics row is written
    "steps", "threads", "log_every",
})

#: settings that are paths: the same folder given another way (relative, absolute) is the same setting
_PATH_SETTINGS = frozenset({"dataset", "modulator.tracker", "rollouts"})

_ABSENT = "(not set)"
#: settings added after runs were saved without them, with the value that computes what those runs did:
#: a checkpoint without the setting resumes under this value, and only under it
_BEFORE_ADDED = {"modulator.context_free": [], "ppo.advantage": "gae", "collector.group_size": 1,
                 "policy.anchor_lookahead": 1, "modulator.core": None, "modulator.core_size": 128,
                 "modulator.decide_every": 1}


def _flat(d, prefix: str = "") -> dict:
    """``{"ppo": {"lr": …}}`` → ``{"ppo.lr": …}``, lists for tuples (the stored config went through torch.save)."""
    out = {}
    for k, v in d.items():
        key = f"{prefix}{k}"
        if isinstance(v, dict):
            out.update(_flat(v, f"{key}."))
        else:
            out[key] = list(v) if isinstance(v, tuple) else v
    return out


def _same(key: str, a, b) -> bool:
    if a == b:
        return True
    if key in _PATH_SETTINGS and isinstance(a, str) and isinstance(b, str):
        return Path(a).resolve() == Path(b).resolve()
    return False


def changed_settings(stored: dict, config: dict) -> dict[str, tuple]:
    """The settings (dotted names) in which ``config`` differs from a checkpoint's ``stored`` config, leaving
    out :data:`RESUME_NEUTRAL`: name → (checkpoint's value, this run's). A setting the checkpoint does not
    have (it predates the setting) counts as changed: what the run computed then is not known to match —
    except a setting of :data:`_BEFORE_ADDED` at the value that computes what the run did before it."""
    a, b = _flat(stored), _flat(config)
    a = {**{k: v for k, v in _BEFORE_ADDED.items() if k in b}, **a}
    return {k: (a.get(k, _ABSENT), b.get(k, _ABSENT)) for k in sorted(a.keys() | b.keys())
            if k not in RESUME_NEUTRAL and not _same(k, a.get(k, _ABSENT), b.get(k, _ABSENT))}


def _progress(blob: dict) -> tuple[int, int, str]:
    """(done, total, unit) of the run a checkpoint belongs to."""
    config = blob.get("config") or {}
    if isinstance(config.get("ppo"), dict):
        return int(blob.get("frames", 0)), int(config["ppo"].get("total_frames", 0)), "frames"
    return int(blob.get("iteration", 0)), int(config.get("steps", 0)), "steps"


def _blob_kind(blob: dict) -> str:
    return TRAINING_RUN if isinstance((blob.get("config") or {}).get("ppo"), dict) else DISTILLATION_RUN


def checkpoint_kind(out) -> str | None:
    """The kind of run whose checkpoint is in ``out`` (None: none, or not a readable adadex checkpoint):
    how the folders of runs written before the output marker are recognized."""
    try:
        blob = load_checkpoint(out)
    except CheckpointError:
        return None
    return None if blob is None else _blob_kind(blob)


def check_run(out, kind: str, config: dict, *, resume: bool, force: bool = False, strict: bool = True,
              ignore=()) -> dict | None:
    """Check the folder ``out`` of a training run of ``kind`` (:data:`TRAINING_RUN`, :data:`DISTILLATION_RUN`)
    with settings ``config`` before any work; nothing is written. Returns the checkpoint to continue from
    (``resume``), or ``None`` for a fresh run. Raises one-line :class:`~adadex.errors.AdadexError` s:

    * ``out`` holds files that are not an earlier run of this kind (no marker, no checkpoint of this kind):
      refused unless ``force`` (:func:`adadex.io.check_output_dir`); a file at ``out`` always;
    * without ``resume``, ``out`` holds a run (finished or not, its checkpoint): refused unless ``force``
      (which starts over: :func:`start_run` removes the old checkpoint);
    * with ``resume``: no checkpoint is refused when ``strict`` (the recipes; the pipeline resumes its
      stages with ``strict=False``: a fresh run when there is none); settings that differ from the
      checkpoint's other than :data:`RESUME_NEUTRAL` are refused, naming them. A finished run resumed with
      the same length returns at once (the trainer has nothing to do).

    ``ignore``: names in ``out`` that the running command itself just made (Hydra's ``.hydra/`` and log).
    """
    from adadex.errors import ConfigError
    from adadex.io import OutputExistsError, check_output_dir

    out = Path(out)
    check_output_dir(out, kind, force=force, recognize=lambda p: checkpoint_kind(p) == kind, option="force=true",
                     ignore=ignore)
    blob = load_checkpoint(out) if (out / CHECKPOINT).is_file() and (resume or not force) else None
    if blob is not None and _blob_kind(blob) != kind and not force:
        raise OutputExistsError(f"{out} holds the checkpoint of a {_blob_kind(blob)}, not of a {kind}; choose another "
                                f"out=, or pass force=true to start over there")
    if not resume:
        if blob is None:
            return None
        done, total, unit = _progress(blob)
        what = (f"a finished {kind} ({done} of {total} {unit})" if done >= total else
                f"an unfinished {kind} (its checkpoint at {done} of {total} {unit})")
        raise OutputExistsError(f"{out} holds {what}; pass resume=true to continue it (a larger total to train "
                                f"on), choose another out=, or pass force=true to start over")
    if blob is None:
        if strict:
            raise CheckpointError(f"{out}: resume=true, but there is no checkpoint to resume ({CHECKPOINT} is "
                                  f"missing); leave resume=true out to start a new run")
        return None
    changed = changed_settings(blob.get("config") or {}, config)
    if changed:
        said = ", ".join(f"{k} (checkpoint: {a!r}, now: {b!r})" for k, (a, b) in changed.items())
        raise ConfigError(f"{out}: resume=true with settings that change the result, which differ from the "
                          f"checkpoint's: {said}; resume with the checkpoint's settings, or train in a new out= "
                          f"(force=true starts this one over)")
    return blob


def start_run(out, kind: str, *, fresh: bool) -> Path:
    """Claim ``out`` for a run of ``kind`` that passed :func:`check_run`: make it, mark it, and for a
    ``fresh`` run (``force`` over an earlier one) remove the earlier run's checkpoint, so that a kill
    before the first new checkpoint cannot resume the old run."""
    from adadex.io import mark_output_dir

    out = mark_output_dir(out, kind)
    if fresh:
        (out / CHECKPOINT).unlink(missing_ok=True)
    return out
