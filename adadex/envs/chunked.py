"""The one rollout loop of evaluation and teacher rollouts: a policy over a list of references, in
chunks of batched worlds, each reference once for its full episode window.

:func:`adadex.eval.evaluate.evaluate` and :func:`adadex.train.rollouts.teacher_rollouts` both run
this loop (:func:`chunked_rollouts`): the references are split into chunks of at most
``max_worlds``; each chunk gets its own :class:`~adadex.envs.tracking.TrackingEnv` (world ``w``
tracks the chunk's ``w``-th reference, ``draw="cycle"``) with its own seed, optionally a transform
appended (a modulated policy's primer), one reset, and ``config.window - 1`` steps of
``env.rollout`` without auto-reset and without stopping at a world that is done (a world that ends
early keeps stepping; metrics count its frames after the end as failures), under one exploration
type (deterministic unless asked) and ``torch.no_grad()``.

Chunk ``k``'s env seed is ``derive_seed(seed, k)``, :func:`chunk_seed` by default: ``seed`` itself
for the first chunk (a list that fits one chunk draws as one env seeded ``seed`` does), independent
seeds after it, so a reference listed again beyond ``max_worlds`` meets new randomization draws, not
a copy of its first episode. The env draws start states and per-step noise from streams the actions
do not touch, so two policies run on the same references with the same ``seed`` and ``max_worlds``
meet the same draws in every episode (their results pair up, :mod:`adadex.eval.paired`).

Example::

    from adadex.envs.replay import replay_policy
    for chunk in chunked_rollouts(replay_policy(), "data/small", [0, 1, 2], max_worlds=2):
        chunk.references, chunk.rollout.batch_size      # [0, 1] (2, 299), then [2] (1, 299)
"""

from __future__ import annotations

import copy
from collections.abc import Callable, Iterator, Sequence
from typing import NamedTuple

import numpy as np
import torch
from tensordict import TensorDictBase
from torchrl.envs import EnvBase, TransformedEnv
from torchrl.envs.utils import ExplorationType, set_exploration_type

from adadex.data.reference import ReferenceDataset
from adadex.envs.tracking import TrackingConfig, TrackingEnv
from adadex.errors import ConfigError, check_number
from adadex.progress import progress_bar

#: TrackingEnv arguments the loop sets itself (per chunk), refused in ``env_kwargs``
_SET_PER_CHUNK = ("num_worlds", "split", "references", "draw", "seed")


class RolloutChunk(NamedTuple):
    """One chunk of :func:`chunked_rollouts`: which references it ran, with which seed, and its rollout.

    Attributes:
        index: the chunk's number within the call, from 0.
        references: the dataset indices its worlds tracked (world ``w`` tracked ``references[w]``).
        seed: the seed its env was made with (:func:`chunk_seed`; None: fresh entropy).
        rollout: the rollout, batch ``[len(references), config.window - 1]``.
        env: the chunk's env (with the appended transform, if any); closed when the next chunk is
            asked for.
    """

    #: the chunk's number within the call, from 0
    index: int
    #: the dataset indices its worlds tracked (world ``w`` tracked ``references[w]``)
    references: list[int]
    #: the seed its env was made with
    seed: int | None
    #: the rollout, batch ``[len(references), config.window - 1]``
    rollout: TensorDictBase
    #: the chunk's env (with the appended transform, if any); closed when the next chunk is asked for
    env: EnvBase


def chunk_seed(seed: int | None, chunk: int) -> int | None:
    """The env seed of chunk ``chunk`` of a run seeded ``seed``: ``seed`` itself for the first (a run
    that fits one chunk draws as it always did), independent ones after it; ``None`` (fresh
    entropy) stays ``None``.

    Args:
        seed: the run's seed, or None.
        chunk: the chunk's number, from 0.

    Returns:
        the chunk's env seed (derived from ``(seed, chunk)`` by ``numpy.random.SeedSequence``), or None.

    Examples:
        >>> chunk_seed(7, 0), chunk_seed(None, 3)
        (7, None)
        >>> chunk_seed(7, 1) == chunk_seed(7, 1) != chunk_seed(7, 2)
        True
    """
    if seed is None or chunk == 0:
        return seed
    return int(np.random.SeedSequence([int(seed), chunk]).generate_state(1)[0])


def chunked_rollouts(policy, dataset, references: Sequence[int], *, max_worlds: int = 64, seed: int | None = 0,
                     derive_seed: Callable[[int | None, int], int | None] = chunk_seed,
                     config: TrackingConfig = TrackingConfig(), env_transform: Callable | None = None,
                     exploration: ExplorationType = ExplorationType.DETERMINISTIC, progress: bool = True,
                     desc: str = "rollouts", bar=None, steps: int | None = None,
                     **env_kwargs) -> Iterator[RolloutChunk]:
    """Roll ``policy`` out once on each of ``references``, ``max_worlds`` worlds at a time; yield each
    chunk as it is done (see the module docstring).

    The arguments are checked here, before the first chunk is asked for; the chunks are rolled out
    lazily, one at a time, so only one chunk's env and rollout need be held (drop a chunk before
    asking for the next to keep it so). Each env is closed when the next chunk is asked for, or when
    the iteration stops or is abandoned.

    Args:
        policy: a TensorDictModule writing ``"action"`` (a tracker's actor, the replay policy, a
            ``make_policy`` graph).
        dataset: a :class:`~adadex.data.reference.ReferenceDataset` or its folder.
        references: dataset indices, one episode each, in this order (a reference may repeat); each
            must have an episode window of ``config.window`` frames (the env checks).
        max_worlds: worlds stepped together: chunk ``k`` runs ``references[k·max_worlds : (k+1)·max_worlds]``.
        seed: the run's seed; chunk ``k``'s env is seeded ``derive_seed(seed, k)``.
        derive_seed: ``(seed, k) → env seed of chunk k``; :func:`chunk_seed` by default (evaluation);
            teacher rollouts number their seeds consecutively.
        config: the episode settings (:class:`~adadex.envs.tracking.TrackingConfig`); each episode
            runs ``config.window - 1`` steps.
        env_transform: called once per chunk; returns a transform appended to that chunk's env (a
            modulated policy's ``primer``).
        exploration: how the policy acts: ``ExplorationType.DETERMINISTIC`` (its deterministic action)
            or ``RANDOM`` (it samples, as in a collector).
        progress: show a progress bar (counting frames) when no ``bar`` is given.
        desc: that progress bar's label.
        bar: a progress bar (anything with ``update(n)``) to advance instead of making one, for a
            caller whose bar spans several calls; it is not closed here.
        steps: steps per episode; ``None`` (default): the whole episode, ``config.window - 1``. Fewer
            roll out the same draws' first steps (e.g. what a policy chooses at an episode's start).
        env_kwargs: passed to every :class:`~adadex.envs.tracking.TrackingEnv` (``randomize``,
            ``patch``, ``latent_fn``, ``nthread`` …), except what the loop sets per chunk
            (``num_worlds``, ``split``, ``references``, ``draw``, ``seed``).

    Returns:
        an iterator of :class:`RolloutChunk`, one per chunk, in order.
    """
    max_worlds = int(check_number("max_worlds", max_worlds, low=1, integer=True))
    steps = config.window - 1 if steps is None else int(check_number("steps", steps, low=1, integer=True))
    refs = [int(r) for r in references]
    if not refs:
        raise ConfigError("references must be a non-empty list of dataset indices, got none")
    clash = [k for k in _SET_PER_CHUNK if k in env_kwargs]
    if clash:
        raise ConfigError(f"{', '.join(clash)}: set per chunk by chunked_rollouts itself, not an env setting to pass "
                          f"(each chunk's worlds, references and seed follow from references, max_worlds and seed)")
    ds = dataset if isinstance(dataset, ReferenceDataset) else ReferenceDataset(dataset)
    return _chunks(policy, ds, refs, max_worlds, seed, derive_seed, config, env_transform, exploration,
                   progress, desc, bar, steps, env_kwargs)


def _chunks(policy, ds, refs, max_worlds, seed, derive_seed, config, env_transform, exploration, progress, desc,
            bar, steps, env_kwargs) -> Iterator[RolloutChunk]:
    own_bar = bar is None
    moved = {}            # the policy on each env device it met (a GPU env's, when it lives on the host)
    if own_bar:
        bar = progress_bar(total=len(refs) * steps, unit="frame", desc=desc, disable=not progress)
    try:
        for k, start in enumerate(range(0, len(refs), max_worlds)):
            chunk = refs[start:start + max_worlds]
            chunk_env_seed = derive_seed(seed, k)
            env = TrackingEnv(ds, num_worlds=len(chunk), split=None, references=chunk, draw="cycle", config=config,
                              seed=chunk_env_seed, **env_kwargs)
            try:
                if env_transform is not None:
                    env = TransformedEnv(env, env_transform())
                with torch.no_grad(), set_exploration_type(exploration):
                    td = env.reset()
                    td = env.rollout(steps, _on_device(policy, env.device, moved), tensordict=td, auto_reset=False,
                                     break_when_any_done=False, callback=lambda *_: bar.update(len(chunk)))
                    if td.device is not None and td.device.type != "cpu":
                        td = td.to("cpu")      # what callers read (metrics, teacher tables) is on the host
                bar.update(len(chunk))       # the rollout calls back after every step but its last
                # yielded outside no_grad and the exploration type: the caller's code runs in its own modes
                item = RolloutChunk(k, chunk, chunk_env_seed, td, env)
                del td
                yield item
                del item           # the caller may drop its chunk before the next one is rolled out
            finally:
                env.close()
    finally:
        if own_bar:
            bar.close()


def _on_device(policy, device: torch.device, moved: dict):
    """``policy``, or a copy of it on ``device`` when its parameters live elsewhere (an env on the GPU,
    a policy trained on the host): the caller's policy is never moved."""
    tensors = [*policy.parameters(), *policy.buffers()] if isinstance(policy, torch.nn.Module) else []
    if not tensors or all(t.device == device for t in tensors):
        return policy
    if device not in moved:
        moved[device] = copy.deepcopy(policy).to(device)
    return moved[device]
