"""Teacher rollouts: the specialists' successful trajectories as an on-disk TorchRL replay buffer.

Each specialist (a :class:`~adadex.modules.tracker.Tracker`) is rolled out deterministically on the
references of its semantic group, ``episodes_per_reference`` times each, under Table 3 domain
randomization (:class:`~adadex.envs.randomization.Randomization`), so one reference gives several
different episodes. Only the trajectories that *succeed* by the paper's criterion
(:mod:`adadex.eval.metrics`) are kept — the generalist imitates what worked (paper Sec. 3.2). The
criterion is a parameter: ``"mean_error"`` (the trajectory's mean errors within the thresholds and
tracked to its end) or ``"completion>=x"`` (at least a fraction ``x`` of its frames within them).

Each kept step is one row of a :class:`~torchrl.data.TensorDictReplayBuffer` with
:class:`~torchrl.data.LazyMemmapStorage`:

=====================================  ============================================================
``"observation"``                      the flat 273-D observation the teacher read
``("proprio", …)``, ``("object", …)``  the structured entries (by default; ``keys``), among them
                                       ``("proprio", "joint_target")`` that a residual tracker reads
``"action"``                           the teacher's (deterministic) action
``"reference"``                        dataset index of the reference
``"t"``                                time step within the episode (0 = the reset observation)
``"teacher"``                          index into ``rollouts.json["teachers"]`` (name, path, config)
``"episode"``                          running episode number (episodes of one reference differ)
=====================================  ============================================================

The output folder (written as one unit with :func:`adadex.io.output_folder`: a killed run leaves
no half-written buffer)::

    out/buffer/         the buffer, written by its own ``dumps`` (reload: :func:`load_rollouts`)
    out/rollouts.json   per reference: episodes tried and kept, success rate, frames stored; the
                        teachers (name, checkpoint, Tracker config, references); the settings

Episodes run in chunks of at most ``max_worlds`` worlds by the loop evaluation runs too
(:func:`adadex.envs.chunked.chunked_rollouts`, one call per teacher). The ``k``-th chunk (counted
over all teachers in order) uses env seed ``seed + k`` — not evaluation's
:func:`~adadex.envs.chunked.chunk_seed`; kept so that existing rollouts stay reproducible — so
``evaluate(teacher.actor, ds, references=chunk, seed=seed + k, randomize=Randomization())``
reproduces its episodes exactly.

:func:`teacher_action_table` turns the buffer into the dense (reference, t) → teacher action lookup
the DexTrack-style imitation baseline uses.
"""

from __future__ import annotations

import json
import math
import re
import shutil
from collections.abc import Mapping, Sequence
from pathlib import Path

import torch
from torchrl.data import LazyMemmapStorage, ReplayBuffer, TensorDictReplayBuffer
from torchrl.data.replay_buffers.samplers import SamplerWithoutReplacement

from adadex.data.reference import ReferenceDataset
from adadex.envs.chunked import chunked_rollouts
from adadex.envs.observation import JOINT_POS, JOINT_TARGET, LINK_POSE, OBJECT_LATENT, OBJECT_POSE, OBSERVATION
from adadex.envs.randomization import Randomization
from adadex.envs.tracking import TrackingConfig, episode_references
from adadex.errors import AdadexError, ConfigError, check_number
from adadex.eval.metrics import Thresholds, from_rollout
from adadex.io import atomic_write_text, output_folder
from adadex.modules.tracker import Tracker
from adadex.progress import progress_bar
from adadex.sim.robot import NUM_JOINTS

KIND = "teacher-rollouts"
BUFFER = "buffer"
INFO = "rollouts.json"
TRACKER_FILE = "tracker.pt"
#: What each stored step keeps besides the action and the indices: what a tracker reads.
DEFAULT_KEYS = (OBSERVATION, JOINT_POS, JOINT_TARGET, LINK_POSE, OBJECT_POSE, OBJECT_LATENT)
INDEX_KEYS = ("reference", "t", "teacher", "episode")


class RolloutsError(AdadexError, ValueError):
    """Teacher rollouts that cannot be made or read (no folder, no buffer, nothing succeeded)."""


class NoSuccessfulRollouts(RolloutsError):
    """Every teacher episode failed the success criterion: there is nothing to imitate."""


def success_criterion(spec: str):
    """``"mean_error"`` or ``"completion>=x"`` (0 < x ≤ 1) → a function of :func:`from_rollout`'s
    per-trajectory metrics returning which trajectories succeeded.

    >>> import torch
    >>> success_criterion("completion>=0.5")({"completion": torch.tensor([0.4, 0.9])}).tolist()
    [False, True]
    >>> success_criterion("best")
    Traceback (most recent call last):
    ...
    adadex.errors.ConfigError: success criterion must be 'mean_error' or 'completion>=x' with 0 < x <= 1, got 'best'
    """
    if spec == "mean_error":
        return lambda m: m["success_mean_error"].to(torch.bool)
    match = re.fullmatch(r"completion\s*>=\s*([0-9.eE+-]+)", str(spec).strip())
    x = float("nan")
    if match:
        try:
            x = float(match.group(1))
        except ValueError:
            pass
    if not (math.isfinite(x) and 0 < x <= 1):
        raise ConfigError(f"success criterion must be 'mean_error' or 'completion>=x' with 0 < x <= 1, got {spec!r}")
    return lambda m: m["completion"] >= x


def _teacher(key, i: int) -> tuple[str, str | None, Tracker]:
    """(name, checkpoint path or None, tracker) of one ``teachers`` key."""
    if isinstance(key, Tracker):
        return f"teacher{i}", None, key
    path = Path(key)
    if path.is_dir():
        path = path / TRACKER_FILE
    if not path.is_file():
        raise RolloutsError(f"{path}: no tracker checkpoint there (a specialist run folder holds {TRACKER_FILE})")
    try:
        tracker = Tracker.load(path)
    except (ValueError, OSError) as e:
        raise RolloutsError(f"{path}: cannot load the teacher ({e})") from e
    return path.parent.name, str(path), tracker


def _episode_list(refs: Sequence[int], episodes: int) -> list[int]:
    """Each reference ``episodes`` times, round-robin (each chunk mixes references)."""
    return [r for _ in range(episodes) for r in refs]


def _consecutive_seeds(seed: int, chunk: int) -> int:
    """The env seed of chunk ``chunk`` of a teacher whose first chunk is seeded ``seed`` (the
    module docstring's ``seed + k``, numbered over all teachers)."""
    return seed + chunk


def teacher_rollouts(teachers: Mapping, dataset, out, *, episodes_per_reference: int = 4,
                     randomize: Randomization | bool | None = True, seed: int = 0, max_worlds: int = 64,
                     criterion: str = "mean_error", thresholds: Thresholds = Thresholds(),
                     config: TrackingConfig = TrackingConfig(), keys: Sequence = DEFAULT_KEYS, nthread: int = 2,
                     force: bool = False, progress: bool = True, backend: str = "rollout") -> dict:
    """Roll out each teacher on its references; store the successful trajectories' steps in ``out``.

    Args:
        teachers: teacher → the dataset indices it is the specialist for. A teacher is a Tracker
            checkpoint (``tracker.pt``, or a run folder holding one) or a :class:`Tracker`.
        dataset: the reference dataset (folder or :class:`ReferenceDataset`).
        out: the output folder (see the module docstring); an existing rollouts folder is replaced,
            anything else is refused unless ``force``.
        episodes_per_reference: randomized episodes per reference.
        randomize: ``True`` for Table 3 (:class:`Randomization`), a :class:`Randomization`, or
            ``None``/``False`` for the nominal env (then all episodes of a reference are alike).
        seed: env seed of the first chunk (chunk ``k`` uses ``seed + k``).
        max_worlds: worlds stepped together.
        criterion: ``"mean_error"`` or ``"completion>=x"`` (:func:`success_criterion`).
        thresholds: the success thresholds the criterion uses.
        config: the episode settings (:class:`TrackingConfig`).
        keys: observation entries stored per step (the flat ``"observation"`` and every entry a teacher's
            actor reads, always).
        nthread: the physics rollout's threads (default 2).
        force: replace whatever is at ``out`` (default False).
        progress: show a progress bar (default True).
        backend: the envs' physics (``"rollout"``, default, or ``"warp"``: :class:`~adadex.train.config.SimConfig`).

    Returns the content of ``rollouts.json`` (a dict). Raises :class:`NoSuccessfulRollouts` when no
    episode succeeded (``out`` is then left as it was).
    """
    check_number("episodes_per_reference", episodes_per_reference, low=1, integer=True)
    check_number("max_worlds", max_worlds, low=1, integer=True)
    check_number("seed", seed, integer=True)
    succeeded = success_criterion(criterion)
    if randomize is True:
        randomize = Randomization()
    elif randomize is False:
        randomize = None
    ds = dataset if isinstance(dataset, ReferenceDataset) else ReferenceDataset(dataset)
    keys = list(dict.fromkeys([OBSERVATION, *[k if isinstance(k, str) else tuple(k) for k in keys]]))
    if not teachers:
        raise RolloutsError("teacher_rollouts: no teachers given")
    usable = set(episode_references(ds, None, config.window))
    plan = []
    for i, (key, refs) in enumerate(teachers.items()):
        name, path, tracker = _teacher(key, i)
        refs = [int(r) for r in refs]
        bad = [r for r in refs if r not in usable]
        if not refs or bad:
            raise RolloutsError(f"{ds.path}: teacher {name} needs a non-empty list of dataset indices with a "
                                f"{config.window}-frame episode window; not usable: {bad[:10]}")
        plan.append((name, path, tracker.eval(), refs))
    # whatever a teacher reads, its student reads too (an object-anchored tracker's start poses …)
    keys = list(dict.fromkeys([*keys, *(k for p in plan for k in p[2].actor.in_keys)]))
    steps = config.window - 1
    total = sum(len(p[3]) for p in plan) * episodes_per_reference
    per_ref: dict[int, dict] = {}
    teacher_info = []
    bar = progress_bar(total=total * steps, unit="frame", desc="teacher rollouts", disable=not progress)
    with output_folder(out, KIND, force=force) as tmp:
        staging = ReplayBuffer(storage=LazyMemmapStorage(total * steps, scratch_dir=tmp / ".staging"))
        chunk_index, episode, kept_frames = 0, 0, 0
        for ti, (name, path, tracker, refs) in enumerate(plan):
            tried_t = kept_t = 0
            for c in chunked_rollouts(tracker.actor, ds, _episode_list(refs, episodes_per_reference),
                                      max_worlds=max_worlds, seed=seed + chunk_index, derive_seed=_consecutive_seeds,
                                      config=config, bar=bar, randomize=randomize, nthread=nthread,
                                      backend=backend):
                chunk, td = c.references, c.rollout
                chunk_index += 1
                metrics = from_rollout(td, lengths=torch.full((len(chunk),), steps), thresholds=thresholds)
                ok = succeeded(metrics)
                B, T = td.batch_size
                done = td.get(("next", "done")).reshape(B, T)
                valid = ~(torch.cumsum(done.int(), 1) - done.int() > 0)
                rows = td.select(*keys, "action")
                rows.set("reference", torch.tensor(chunk).unsqueeze(1).expand(B, T).clone())
                rows.set("t", torch.arange(T).expand(B, T).clone())
                rows.set("teacher", torch.full((B, T), ti, dtype=torch.int64))
                rows.set("episode", (episode + torch.arange(B)).unsqueeze(1).expand(B, T).clone())
                keep = ok[:, None] & valid
                if keep.any():
                    staging.extend(rows[keep])
                    kept_frames += int(keep.sum())
                episode += B
                tried_t += B
                kept_t += int(ok.sum())
                for b, r in enumerate(chunk):
                    e = per_ref.setdefault(r, {"name": ds.entries[r]["name"], "teachers": [], "tried": 0, "kept": 0,
                                               "frames": 0, "_completion": []})
                    if name not in e["teachers"]:
                        e["teachers"].append(name)
                    e["tried"] += 1
                    e["kept"] += int(ok[b])
                    e["frames"] += int(keep[b].sum())
                    e["_completion"].append(float(metrics["completion"][b]))
                del c, td, rows        # the next chunk's rollout runs without this one held
            teacher_info.append({"name": name, "path": path, "config": dict(tracker.config), "references": refs,
                                 "episodes_tried": tried_t, "episodes_kept": kept_t})
        bar.close()
        tried = sum(e["tried"] for e in per_ref.values())
        kept = sum(e["kept"] for e in per_ref.values())
        if kept_frames == 0:
            raise NoSuccessfulRollouts(
                f"teacher rollouts: none of the {tried} episodes succeeded by criterion {criterion!r}, so there is "
                f"nothing to imitate; train the specialists longer, or loosen the criterion (e.g. 'completion>=0.5')")
        _compact(staging, kept_frames, tmp / BUFFER)
        shutil.rmtree(tmp / ".staging", ignore_errors=True)
        for e in per_ref.values():
            c = e.pop("_completion")
            e["success_pct"] = 100.0 * e["kept"] / e["tried"]
            e["completion_mean"] = sum(c) / len(c)
        info = {"kind": KIND, "dataset": str(ds.path), "num_references": len(ds), "window": config.window,
                "steps": steps, "criterion": criterion, "episodes_per_reference": episodes_per_reference,
                "randomize": randomize is not None, "seed": seed, "max_worlds": max_worlds,
                "keys": [k if isinstance(k, str) else list(k) for k in keys],
                "episodes_tried": tried, "episodes_kept": kept, "success_pct": 100.0 * kept / max(tried, 1),
                "frames": kept_frames, "teachers": teacher_info,
                "per_reference": {str(r): per_ref[r] for r in sorted(per_ref)}}
        atomic_write_text(tmp / INFO, json.dumps(info, indent=1))
    return info


def _new_buffer(storage: LazyMemmapStorage) -> TensorDictReplayBuffer:
    return TensorDictReplayBuffer(storage=storage, sampler=SamplerWithoutReplacement())


def _compact(staging: ReplayBuffer, n: int, folder: Path, piece: int = 65536) -> None:
    """Copy the first ``n`` staged rows into an exactly sized memmap buffer and dump it to ``folder``."""
    buffer = _new_buffer(LazyMemmapStorage(n, scratch_dir=folder / "storage"))
    for i in range(0, n, piece):
        buffer.extend(staging.storage[i:min(n, i + piece)].clone())
    buffer.dumps(folder)


def rollouts_info(path) -> dict:
    """The ``rollouts.json`` of a rollouts folder (see the module docstring)."""
    path = Path(path)
    if not path.is_dir():
        raise RolloutsError(f"{path}: no teacher rollouts there (make them with recipes/teacher_rollouts.py)")
    try:
        info = json.loads((path / INFO).read_text(encoding="utf-8"))
    except (OSError, ValueError) as e:
        raise RolloutsError(f"{path}: not a teacher-rollouts folder ({INFO} unreadable: {e})") from None
    if not isinstance(info, dict) or info.get("kind") != KIND:
        raise RolloutsError(f"{path}: {INFO} does not describe teacher rollouts")
    return info


def load_rollouts(path) -> TensorDictReplayBuffer:
    """The buffer of a rollouts folder, memory-mapped in place (nothing is copied; treat it as read-only),
    with a sampler without replacement: ``buffer.sample(batch_size)``.

    Args:
        path: the rollouts folder written by :func:`teacher_rollouts`.

    Raises:
        RolloutsError: a missing, incomplete or damaged buffer.
    """
    path = Path(path)
    info = rollouts_info(path)
    folder = path / BUFFER
    if not (folder / "storage" / "storage_metadata.json").is_file():
        raise RolloutsError(f"{path}: the replay buffer ({folder}) is missing or incomplete")
    buffer = _new_buffer(LazyMemmapStorage(max(1, info["frames"]), scratch_dir=folder / "storage"))
    try:
        buffer.loads(folder)
    except Exception as e:  # torchrl raises several types for a damaged dump
        raise RolloutsError(f"{path}: cannot read the replay buffer ({type(e).__name__}: {e})") from e
    if len(buffer) != info["frames"] or len(buffer) == 0:
        raise RolloutsError(f"{path}: the buffer holds {len(buffer)} steps, {INFO} says {info['frames']}")
    return buffer


def teacher_action_table(buffer, num_references: int | None = None, window: int | None = None,
                         piece: int = 65536) -> tuple[torch.Tensor, torch.Tensor]:
    """(reference, t) → the mean teacher action over the kept episodes: ``(table, mask)`` with
    ``table`` of shape ``[num_references, window, 22]`` (NaN where no episode was kept) and ``mask``
    ``[num_references, window]`` (True where an action is known).

    ``num_references`` is the dataset's size (default: the largest stored index + 1), ``window`` the
    episode window (default: the largest stored t + 1); the last frame of a window has no action."""
    n = len(buffer)
    if n == 0:
        raise RolloutsError("teacher_action_table: the buffer is empty")
    data = [buffer[i:min(n, i + piece)] for i in range(0, n, piece)]
    refs = torch.cat([d["reference"] for d in data]).long()
    ts = torch.cat([d["t"] for d in data]).long()
    R = int(refs.max()) + 1 if num_references is None else int(num_references)
    W = int(ts.max()) + 1 if window is None else int(window)
    if int(refs.max()) >= R or int(ts.max()) >= W:
        raise RolloutsError(f"teacher_action_table: stored (reference, t) up to ({int(refs.max())}, {int(ts.max())}) "
                            f"do not fit a table of {R} references × {W} frames")
    flat = refs * W + ts
    total = torch.zeros(R * W, NUM_JOINTS, dtype=torch.float64)
    count = torch.zeros(R * W, dtype=torch.float64)
    total.index_add_(0, flat, torch.cat([d["action"] for d in data]).to(torch.float64))
    count.index_add_(0, flat, torch.ones_like(flat, dtype=torch.float64))
    mask = count > 0
    table = torch.full((R * W, NUM_JOINTS), torch.nan, dtype=torch.float64)
    table[mask] = total[mask] / count[mask, None]
    return table.to(torch.float32).reshape(R, W, NUM_JOINTS), mask.reshape(R, W)


def specialist_teachers(runs_dir, dataset, *, window: int | None = None) -> dict[str, list[int]]:
    """Specialist runs → teachers: every sub-folder of ``runs_dir`` with a ``tracker.pt`` and a
    ``checkpoint.pt`` whose config names a ``group`` maps to that group's training references (as the
    run trained on them, :func:`adadex.train.ppo.training_references`, on ``dataset``)."""
    from adadex.train.checkpoint import load_checkpoint
    from adadex.train.config import TrainConfig
    from adadex.train.ppo import training_references

    runs = Path(runs_dir)
    if not runs.is_dir():
        raise RolloutsError(f"{runs}: no folder of specialist runs there")
    ds = dataset if isinstance(dataset, ReferenceDataset) else ReferenceDataset(dataset)
    window = TrackingConfig().window if window is None else window
    out: dict[str, list[int]] = {}
    skipped = []
    for run in sorted(p for p in runs.iterdir() if p.is_dir()):
        blob = load_checkpoint(run) if (run / TRACKER_FILE).is_file() else None
        if blob is None:
            skipped.append(run.name)
            continue
        cfg = dict(blob["config"])
        if cfg.get("group") is None and cfg.get("references") is None:
            raise RolloutsError(f"{run}: not a specialist run (its config has no group)")
        cfg["dataset"] = str(ds.path)
        out[str(run / TRACKER_FILE)] = training_references(TrainConfig.from_dict(cfg), ds, window)
    if not out:
        raise RolloutsError(f"{runs}: no specialist run there (a run folder holds {TRACKER_FILE} and checkpoint.pt); "
                            f"sub-folders seen: {skipped[:10]}")
    return out
