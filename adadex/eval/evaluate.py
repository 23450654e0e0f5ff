"""Evaluate a policy on every reference of a split, with the paper's metrics.

:func:`evaluate` runs each reference of the split once, in chunks of at most ``max_worlds``
worlds stepped together (world ``w`` of a chunk tracks its ``w``-th reference), for the full
episode window, deterministically (``ExplorationType.DETERMINISTIC``), and reads the per-frame
errors the environment writes — no physics is recomputed. The loop is
:func:`~adadex.envs.chunked.chunked_rollouts`, the one teacher rollouts run too. A trajectory that
ends early (object or palm beyond the termination errors, unstable physics) counts its missing
frames as failures. Each chunk's environment draws with its own seed (the first with ``seed``,
chunk k with one derived from ``(seed, k)``, :func:`~adadex.envs.chunked.chunk_seed`), so a
reference listed again beyond ``max_worlds`` meets new randomization draws, not a copy of its first
episode. Two policies evaluated on the same ``references`` list with the same ``seed`` and
``max_worlds`` meet the same draws in every episode (the env draws start states from one stream and
per-step noise from another, neither depending on the actions), so their per-episode results pair
up (:mod:`adadex.eval.paired`).

Besides the summary, the result keeps every episode (``per_episode``: the reference's dataset index
and name, its repeat — how many times the reference appeared before it in the list —, completion,
mean-error success, object completion, carried, whether it ended early and with the palm beyond its
termination error or with the physics unstable, whether the reference lifts its object and the object rose, the mean errors, the
return: :func:`~adadex.eval.metrics.trajectory_metrics`) and, when the rollouts
hold rewards, ``return_completion_spearman``: the per-episode rank correlation of the return with
completion and object completion (:mod:`adadex.eval.reward_check`). ``carried`` is measured against
the reference object's motion as the dataset gives it (:func:`reference_motion`; a modulated
rollout's reference entries show the edited reference).

Example::

    from adadex.envs.replay import replay_policy
    result = evaluate(replay_policy(), "data/small", split=("unseen_trajectory", "test"))
    result["summary"]["success_mean_error_pct"], result["summary"]["completion_pct"]

For a modulated policy pass ``env_transform=policy.primer`` (a factory: one transform per env).
"""

from __future__ import annotations

import time
from collections.abc import Callable

import torch
from torchrl.envs.utils import ExplorationType

from adadex.data.reference import ReferenceDataset
# chunk_seed was defined here first; it stays importable from this module
from adadex.envs.chunked import chunk_seed, chunked_rollouts  # noqa: F401
from adadex.envs.tracking import TrackingConfig, episode_references
from adadex.errors import ConfigError
from adadex.eval.metrics import ERROR_NAMES, Thresholds, from_rollout, summarize
from adadex.eval.reward_check import episode_returns, spearman_by_episode

#: per-episode values kept in ``per_episode`` (besides reference, name, repeat and return)
EPISODE_FIELDS = ("completion", "success_mean_error", "object_completion", "carried", "frames", "ended_early",
                  "ended_palm", "ended_unstable", "reference_lifts", "lifted", *ERROR_NAMES)


def evaluate(policy, dataset, split: tuple[str, str] | None = ("unseen_trajectory", "test"), *,
             references=None, max_worlds: int = 64, env_transform: Callable | None = None,
             config: TrackingConfig = TrackingConfig(), thresholds: Thresholds = Thresholds(),
             progress: bool = True, keep_rollouts: bool = False, sample: bool = False, **env_kwargs) -> dict:
    """Metrics of ``policy`` over every reference of ``split`` (see the module docstring).

    Args:
        policy: a TensorDictModule writing ``"action"`` (tracker, replay policy, make_policy graph).
        dataset: a :class:`~adadex.data.reference.ReferenceDataset` or its folder.
        split: ``(split name, part)`` whose references are evaluated, e.g. ``("unseen_object", "test")``.
        references: dataset indices to evaluate instead of ``split`` (each must have an episode window).
        max_worlds: worlds stepped together; more references are evaluated in chunks of this many.
        env_transform: called once per chunk, returns a transform to append to the env (a primer …).
        config: the episode settings (:class:`~adadex.envs.tracking.TrackingConfig`).
        thresholds: the success thresholds (:class:`~adadex.envs.frame_errors.Thresholds`).
        progress: show a progress bar.
        keep_rollouts: also return the rollouts (below).
        sample: run the policy as collectors do (``ExplorationType.RANDOM``: a modulator or tracker
            samples its distribution; a frozen tracker inside a modulated policy stays deterministic)
            instead of its deterministic action — what exploration costs, e.g. at initialization.
        env_kwargs: passed to :class:`TrackingEnv` (``randomize``, ``patch``, ``latent_fn``, ``seed`` …).

    Returns:
        ``{"summary": {…}, "per_reference": {name: {…}}, "per_episode": {field: [one value per
        episode]}, "return_completion_spearman": {…} | None, "references": n, "wall_s": s}`` and, with
        ``keep_rollouts``, the rollouts (one TensorDict per chunk) under ``"rollouts"``.
        ``per_reference`` holds one entry per reference *name*: a reference listed several times shows
        its last episode there; ``per_episode`` holds them all, in the order of the references list
        (fields: ``reference``, ``name``, ``repeat`` and :data:`EPISODE_FIELDS`, plus ``return``).
    """
    if max_worlds < 1:
        raise ConfigError(f"max_worlds must be ≥ 1, got {max_worlds}")
    ds = dataset if isinstance(dataset, ReferenceDataset) else ReferenceDataset(dataset)
    if references is not None:
        refs = [int(i) for i in references]
        usable = set(episode_references(ds, None, config.window))
        bad = [i for i in refs if i not in usable]
        if bad or not refs:
            raise ConfigError(f"{ds.path}: references must be a non-empty list of dataset indices with a "
                              f"{config.window}-frame episode window; not usable: {bad[:10]}")
        split = None
    else:
        refs = episode_references(ds, split, config.window)
    if not refs:
        raise ConfigError(f"{ds.path}: no reference in split {split} has a {config.window}-frame episode window")
    steps = config.window - 1
    per_chunks, names, rollouts, returns = [], [], [], []
    seed = env_kwargs.pop("seed", 0)
    palm_limit = config.terminate_palm_error if config.terminate_palm_error > 0 else None
    t0 = time.perf_counter()
    for chunk in chunked_rollouts(policy, ds, refs, max_worlds=max_worlds, seed=seed, config=config,
                                  env_transform=env_transform,
                                  exploration=ExplorationType.RANDOM if sample else ExplorationType.DETERMINISTIC,
                                  progress=progress, desc="evaluate", **env_kwargs):
        td, chunk_refs = chunk.rollout, chunk.references
        names += [ds.entries[i]["name"] for i in chunk_refs]
        offset = reference_offset(ds, chunk_refs, steps)
        per_chunks.append(from_rollout(td, lengths=torch.full((len(chunk_refs),), steps), thresholds=thresholds,
                                       reference_motion=torch.linalg.vector_norm(offset, dim=-1),
                                       reference_rise=offset[..., 2], palm_limit=palm_limit))
        returns.append(episode_returns(td))
        if keep_rollouts:
            rollouts.append(td)
        del chunk, td          # the next chunk's rollout runs without this one held
    per = {k: torch.cat([p[k] for p in per_chunks]) for k in per_chunks[0]}
    out = {"split": list(split) if split else None, "references": len(refs), "steps": steps,
           "wall_s": time.perf_counter() - t0, "summary": summarize(per),
           "per_reference": {name: {"success_mean_error": bool(per["success_mean_error"][i]),
                                    "completion": float(per["completion"][i]), "frames": int(per["frames"][i]),
                                    **{k: float(per[k][i]) for k in ERROR_NAMES}}
                             for i, name in enumerate(names)}}
    seen: dict[int, int] = {}
    repeat = []
    for r in refs:                      # the how-manieth time this reference is tracked
        repeat.append(seen.get(r, 0))
        seen[r] = repeat[-1] + 1
    episodes = {"reference": list(refs), "name": names, "repeat": repeat}
    for k in (k for k in EPISODE_FIELDS if k in per):
        v = per[k]
        episodes[k] = [bool(x) for x in v.tolist()] if v.dtype == torch.bool else \
            [int(x) for x in v.tolist()] if not v.is_floating_point() else [float(x) for x in v.tolist()]
    spearman = None
    if all(r is not None for r in returns):
        episodes["return"] = [float(x) for x in torch.cat(returns).tolist()]
        spearman = spearman_by_episode(episodes["return"], episodes)
    out["per_episode"] = episodes
    out["return_completion_spearman"] = spearman
    if keep_rollouts:
        out["rollouts"] = rollouts
    return out


def reference_offset(dataset: ReferenceDataset, references, steps: int) -> torch.Tensor:
    """(len(references), steps, 3) float64: the reference object's position minus its start position (m)
    at each frame an episode of ``steps`` steps records — step k (k = 1 … steps) tracks frame k of
    the episode window, frame 0 being its start — as the dataset gives it (the unedited reference)."""
    pose = dataset.frames["object_pose"]
    base = torch.as_tensor([dataset.entries[r]["offset"] + dataset.entries[r]["window_start"] for r in references])
    frames = base[:, None] + torch.arange(steps + 1)[None]
    pos = torch.as_tensor(pose[frames.reshape(-1)])[..., :3].to(torch.float64).reshape(len(references), steps + 1, 3)
    return pos[:, 1:] - pos[:, :1]


def reference_motion(dataset: ReferenceDataset, references, steps: int) -> torch.Tensor:
    """(len(references), steps) float64: the reference object's distance from its start position (m)
    at each frame (:func:`reference_offset`'s length): what ``carried`` is measured against."""
    return torch.linalg.vector_norm(reference_offset(dataset, references, steps), dim=-1)


def _why_ended(summary: dict) -> str:
    """`` (the palm beyond its termination error: x %, the physics unstable: y %)`` for the reasons the summary has."""
    why = [f"{text}: {summary[key]:.1f} %" for key, text in (("ended_palm_pct", "the palm beyond its termination error"),
                                                               ("ended_unstable_pct", "the physics unstable"))
           if key in summary]
    return f" ({', '.join(why)})" if why else ""


def format_summary(summary: dict) -> str:
    """Three lines for a terminal: success both ways, the object-centric measures and the mean errors;
    a fourth, where the summary has them, with where the frames that did not pass were lost
    (:data:`adadex.eval.metrics.LOST`), and a fifth, where it has them, with how many episodes ended
    early, how many of all with the palm beyond its termination error or with the physics unstable, and how
    many of those whose
    reference lifts its object raised it (:func:`~adadex.eval.metrics.summarize`).

    Args:
        summary: a :func:`~adadex.eval.metrics.summarize` result (positions in cm, rotations in rad,
            rates in %); the object-centric entries may be missing (shown as nan).

    Examples:
        >>> s = {"success_mean_error_pct": 50.0, "completion_pct": 62.5, "T_o": 4.0, "R_o": 0.3,
        ...      "T_h": 3.0, "R_h": 0.2, "E_finger": 0.1}
        >>> print(format_summary(s))
        success: mean-error 50.0 %, completion 62.5 %
        object-centric: object completion nan %, carried nan %
        T_o 4.0 cm, R_o 0.30 rad, T_h 3.0 cm, R_h 0.20 rad, E_finger 0.100 rad
    """
    return (f"success: mean-error {summary['success_mean_error_pct']:.1f} %, completion {summary['completion_pct']:.1f} %"
            f"\nobject-centric: object completion {summary.get('object_completion_pct', float('nan')):.1f} %, "
            f"carried {summary.get('carried_pct', float('nan')):.1f} %"
            f"\nT_o {summary['T_o']:.1f} cm, R_o {summary['R_o']:.2f} rad, T_h {summary['T_h']:.1f} cm, "
            f"R_h {summary['R_h']:.2f} rad, E_finger {summary['E_finger']:.3f} rad"
            + ("" if "lost_position_pct" not in summary else
               f"\nframes lost: position test {summary['lost_position_pct']:.1f} %, rotation "
               f"{summary['lost_rotation_pct']:.1f} %, fingers {summary['lost_finger_pct']:.1f} %, after the "
               f"episode ended {summary['lost_after_end_pct']:.1f} %")
            + ("" if "ended_pct" not in summary else
               f"\nepisodes ended early {summary['ended_pct']:.1f} %"
               + _why_ended(summary)
               + ("" if "lifted_pct" not in summary else
                  f"; objects the reference lifts, lifted {summary['lifted_pct']:.1f} %")))
