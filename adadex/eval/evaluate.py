"""Evaluate a policy on every reference of a split, with the paper's metrics.

:func:`evaluate` runs each reference of the split once, in chunks of at most ``max_worlds``
worlds stepped together (world ``w`` of a chunk tracks its ``w``-th reference), for the full
episode window, deterministically (``ExplorationType.DETERMINISTIC``), and reads the per-frame
errors the environment writes — no physics is recomputed. A trajectory that ends early (object
or palm beyond the termination errors, unstable physics) counts its missing frames as failures.
Each chunk's environment draws with its own seed (the first with ``seed``, chunk k with one derived
from ``(seed, k)``), so a reference listed again beyond ``max_worlds`` meets new randomization
draws, not a copy of its first episode.

Example::

    from adadex.envs.replay import replay_policy
    result = evaluate(replay_policy(), "data/small", split=("unseen_trajectory", "test"))
    result["summary"]["success_mean_error_pct"], result["summary"]["completion_pct"]

For a modulated policy pass ``env_transform=policy.primer`` (a factory: one transform per env).
"""

from __future__ import annotations

import time
from collections.abc import Callable

import numpy as np
import torch
from torchrl.envs import TransformedEnv
from torchrl.envs.utils import ExplorationType, set_exploration_type
from tqdm.auto import tqdm

from adadex.data.reference import ReferenceDataset
from adadex.envs.tracking import TrackingConfig, TrackingEnv, episode_references
from adadex.eval.metrics import ERROR_NAMES, Thresholds, from_rollout, summarize


def evaluate(policy, dataset, split: tuple[str, str] | None = ("unseen_trajectory", "test"), *,
             references=None, max_worlds: int = 64, env_transform: Callable | None = None,
             config: TrackingConfig = TrackingConfig(), thresholds: Thresholds = Thresholds(),
             progress: bool = True, keep_rollouts: bool = False, **env_kwargs) -> dict:
    """Metrics of ``policy`` over every reference of ``split`` (see the module docstring).

    Args:
        policy: a TensorDictModule writing ``"action"`` (tracker, replay policy, make_policy graph).
        references: dataset indices to evaluate instead of ``split`` (each must have an episode window).
        env_transform: called once per chunk, returns a transform to append to the env (a primer …).
        env_kwargs: passed to :class:`TrackingEnv` (``randomize``, ``patch``, ``latent_fn``, ``seed`` …).

    Returns ``{"summary": {…}, "per_reference": {name: {…}}, "references": n, "wall_s": s}`` and,
    with ``keep_rollouts``, the rollouts (one TensorDict per chunk) under ``"rollouts"``.
    """
    if max_worlds < 1:
        raise ValueError(f"max_worlds must be ≥ 1, got {max_worlds}")
    ds = dataset if isinstance(dataset, ReferenceDataset) else ReferenceDataset(dataset)
    if references is not None:
        refs = [int(i) for i in references]
        usable = set(episode_references(ds, None, config.window))
        bad = [i for i in refs if i not in usable]
        if bad or not refs:
            raise ValueError(f"{ds.path}: references must be a non-empty list of dataset indices with a "
                             f"{config.window}-frame episode window; not usable: {bad[:10]}")
        split = None
    else:
        refs = episode_references(ds, split, config.window)
    if not refs:
        raise ValueError(f"{ds.path}: no reference in split {split} has a {config.window}-frame episode window")
    steps = config.window - 1
    chunks = [refs[i:i + max_worlds] for i in range(0, len(refs), max_worlds)]
    per_chunks, names, rollouts = [], [], []
    seed = env_kwargs.pop("seed", 0)
    bar = tqdm(total=len(refs) * steps, unit="frame", desc="evaluate", disable=not progress)
    t0 = time.perf_counter()
    for k, chunk in enumerate(chunks):
        env = TrackingEnv(ds, num_worlds=len(chunk), split=None, references=chunk, draw="cycle", config=config,
                          seed=chunk_seed(seed, k), **env_kwargs)
        if env_transform is not None:
            env = TransformedEnv(env, env_transform())
        with torch.no_grad(), set_exploration_type(ExplorationType.DETERMINISTIC):
            td = env.reset()
            names += [ds.entries[i]["name"] for i in chunk]
            td = env.rollout(steps, policy, tensordict=td, auto_reset=False, break_when_any_done=False,
                             callback=lambda *_: bar.update(len(chunk)))
        per_chunks.append(from_rollout(td, lengths=torch.full((len(chunk),), steps), thresholds=thresholds))
        if keep_rollouts:
            rollouts.append(td)
        env.close()
    bar.close()
    per = {k: torch.cat([p[k] for p in per_chunks]) for k in per_chunks[0]}
    out = {"split": list(split) if split else None, "references": len(refs), "steps": steps,
           "wall_s": time.perf_counter() - t0, "summary": summarize(per),
           "per_reference": {name: {"success_mean_error": bool(per["success_mean_error"][i]),
                                    "completion": float(per["completion"][i]), "frames": int(per["frames"][i]),
                                    **{k: float(per[k][i]) for k in ERROR_NAMES}}
                             for i, name in enumerate(names)}}
    if keep_rollouts:
        out["rollouts"] = rollouts
    return out


def chunk_seed(seed: int | None, chunk: int) -> int | None:
    """The env seed of chunk ``chunk`` of an evaluation seeded ``seed``: ``seed`` itself for the
    first (an evaluation that fits one chunk draws as it always did), independent ones after it;
    ``None`` (fresh entropy) stays ``None``."""
    if seed is None or chunk == 0:
        return seed
    return int(np.random.SeedSequence([int(seed), chunk]).generate_state(1)[0])


def format_summary(summary: dict) -> str:
    """Two lines for a terminal: success both ways and the mean errors."""
    return (f"success: mean-error {summary['success_mean_error_pct']:.1f} %, completion {summary['completion_pct']:.1f} %"
            f"\nT_o {summary['T_o']:.1f} cm, R_o {summary['R_o']:.2f} rad, T_h {summary['T_h']:.1f} cm, "
            f"R_h {summary['R_h']:.2f} rad, E_finger {summary['E_finger']:.3f} rad")
