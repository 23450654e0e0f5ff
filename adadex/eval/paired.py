"""Bootstrap intervals over references, stratified by training seed, for one row and for the paired
difference of two rows evaluated on the same draws.

Why: Table 1's rows differ by a few completion points, while one episode's completion has an SD of
≈ 28 points and a Student-t interval over two training seeds is 6.35 × the gap between them. The
rows of a table are evaluated on the *same* draws (the same references, repeats and env seed for
every row of a training seed, :meth:`adadex.train.pipeline.Pipeline.evaluations`), so the
difference of two rows can be taken episode by episode, which removes what the references and
draws have in common.

The procedure (:func:`bootstrap_mean`, :func:`paired_bootstrap`):

* an episode's value is the metric (or, paired, row A − row B on the same reference and the same
  draw index, i.e. repeat);
* the statistic is the mean over training seeds of each seed's mean over its episodes (the table's
  headline: the mean of the per-seed summaries);
* one resample draws, *within each seed*, that seed's references with replacement (as many as it
  has), each bringing all its episodes (its repeats), and recomputes the statistic;
* the interval is the 2.5 and 97.5 percentiles of ``resamples`` (≥ 2000 by default) resamples,
  drawn from ``numpy.random.default_rng(seed)``: the same inputs and seed give the same interval.

The interval covers the spread over test references and the draws they met, for the trained seeds
as they are; it does not model how another training seed would have come out beyond what the
pooled seeds show. Episodes with a NaN value (an empty trajectory's mean errors) are left out.

Example
-------
>>> import numpy as np
>>> rng = np.random.default_rng(0)
>>> refs = np.tile(np.arange(40), 2); seeds = np.repeat([0, 1], 40)
>>> tracker = rng.uniform(0, 100, 80)                   # per-episode completion, very spread
>>> row = tracker + 3.0 + rng.normal(0, 2, 80)         # the same episodes, 3 points better
>>> d = paired_bootstrap(row, tracker, refs, seeds)
>>> round(d["estimate"], 1), d["ci95"][0] > 0, d["episodes"], d["references"]
(3.0, True, 80, [40, 40])
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence

import numpy as np

from adadex.errors import ArrayError, ConfigError

RESAMPLES = 2000
CONFIDENCE = 0.95


def _strata(values, reference_ids, seed_ids) -> tuple[np.ndarray, list[tuple[np.ndarray, np.ndarray]]]:
    """(the seeds, [(per-reference sums, per-reference episode counts) per seed]) of the finite values."""
    v = np.asarray(values, dtype=np.float64).reshape(-1)
    refs = np.asarray(reference_ids).reshape(-1)
    seeds = np.zeros(len(v), dtype=np.int64) if seed_ids is None else np.asarray(seed_ids).reshape(-1)
    if not (len(v) == len(refs) == len(seeds)):
        raise ArrayError(f"values, reference_ids and seed_ids must be equally long; got {len(v)}, {len(refs)}, "
                         f"{len(seeds)}")
    keep = np.isfinite(v)
    v, refs, seeds = v[keep], refs[keep], seeds[keep]
    out = []
    for s in np.unique(seeds):                     # sorted: a fixed order of draws
        m = seeds == s
        _, inv = np.unique(refs[m], return_inverse=True)
        out.append((np.bincount(inv, weights=v[m]), np.bincount(inv).astype(np.float64)))
    return np.unique(seeds), out


def bootstrap_mean(values, reference_ids, seed_ids=None, *, resamples: int = RESAMPLES,
                   confidence: float = CONFIDENCE, seed: int = 0) -> dict:
    """The mean over seeds of each seed's episode mean, and its percentile bootstrap interval
    resampling references within each seed (module docstring).

    Args:
        values: (N,) one value per episode.
        reference_ids: (N,) which reference each episode tracked (any hashable numbers or strings).
        seed_ids: (N,) which training seed it belongs to (the strata); ``None``: one seed.
        resamples: bootstrap resamples (≥ 1; default :data:`RESAMPLES`, 2000).
        confidence: the interval's coverage, in (0, 1) (default :data:`CONFIDENCE`, 0.95).
        seed: the resampling's random seed.

    Returns ``{"estimate", "ci95": [lo, hi], "episodes", "references": [per seed], "seeds",
    "resamples"}``; the estimate and interval are NaN (interval ``None``) without a finite value.
    """
    if int(resamples) < 1:
        raise ConfigError(f"resamples must be ≥ 1, got {resamples}")
    if not 0 < confidence < 1:
        raise ConfigError(f"confidence must be in (0, 1), got {confidence}")
    seeds, strata = _strata(values, reference_ids, seed_ids)
    out = {"episodes": int(sum(c.sum() for _, c in strata)), "references": [len(c) for _, c in strata],
           "seeds": len(strata), "resamples": int(resamples)}
    if not strata:
        return out | {"estimate": math.nan, "ci95": None}
    rng = np.random.default_rng(seed)
    estimate = float(np.mean([s.sum() / c.sum() for s, c in strata]))
    stats = np.zeros(int(resamples))
    for sums, counts in strata:
        n = len(sums)
        draws = rng.multinomial(n, np.full(n, 1.0 / n), size=int(resamples)).astype(np.float64)   # (R, n) picks
        stats += (draws @ sums) / (draws @ counts)
    stats /= len(strata)
    alpha = (1.0 - confidence) / 2
    lo, hi = np.quantile(stats, [alpha, 1.0 - alpha])
    # a mean's percentile interval holds its estimate; only rounding (identical values summed in
    # another order) can put it a few ulps outside, which is not information
    lo, hi = min(float(lo), estimate), max(float(hi), estimate)
    return out | {"estimate": estimate, "ci95": [lo, hi]}


def paired_bootstrap(per_episode_a, per_episode_b, reference_ids, seed_ids=None, *, resamples: int = RESAMPLES,
                     confidence: float = CONFIDENCE, seed: int = 0) -> dict:
    """A − B, episode by episode, with :func:`bootstrap_mean`'s interval: ``per_episode_a[i]`` and
    ``per_episode_b[i]`` must be the same reference (``reference_ids[i]``), seed and draw
    (:func:`pair_episodes` lines two rows' ``per_episode`` records up).

    Args:
        per_episode_a: (N,) one value per episode of A.
        per_episode_b: (N,) the same episodes' values of B (another shape raises
            :class:`~adadex.errors.ArrayError`).
        reference_ids: (N,) which reference each episode tracked.
        seed_ids: (N,) which training seed it belongs to; ``None``: one seed.
        resamples: bootstrap resamples (default 2000).
        confidence: the interval's coverage, in (0, 1) (default 0.95).
        seed: the resampling's random seed.

    Returns:
        :func:`bootstrap_mean`'s dict for the differences A − B.
    """
    a, b = np.asarray(per_episode_a, dtype=np.float64), np.asarray(per_episode_b, dtype=np.float64)
    if a.shape != b.shape:
        raise ArrayError(f"paired_bootstrap: A and B must hold the same episodes, got shapes {a.shape} and {b.shape}")
    return bootstrap_mean(a - b, reference_ids, seed_ids, resamples=resamples, confidence=confidence, seed=seed)


def episode_keys(per_episode: Mapping) -> list[tuple]:
    """(reference, repeat) of each episode of an evaluation's ``per_episode`` record (the draw it met,
    given the evaluation's seed and reference list)."""
    refs = per_episode["reference"]
    repeats = per_episode.get("repeat", [0] * len(refs))
    return [(r, int(k)) for r, k in zip(refs, repeats)]


def pair_episodes(a: Sequence[Mapping], b: Sequence[Mapping], field: str, *, scale: float = 1.0,
                  keep_field: str | None = "frames") -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Line up two rows' episodes, seed by seed: ``a[s]`` and ``b[s]`` are the ``per_episode`` records
    of seed ``s`` (in the same seed order). Returns (values of A, values of B, reference ids, seed
    indices) over the episodes both rows have — (reference, repeat) in both — times ``scale``;
    episodes either row left empty (``keep_field`` 0: no frame tracked) are dropped, as
    :func:`adadex.eval.metrics.summarize` drops them.
    """
    if len(a) != len(b):
        raise ArrayError(f"pair_episodes: {len(a)} seeds of A against {len(b)} of B")
    va, vb, refs, seeds = [], [], [], []
    for s, (ea, eb) in enumerate(zip(a, b)):
        index_b = {k: i for i, k in enumerate(episode_keys(eb))}
        for i, k in enumerate(episode_keys(ea)):
            j = index_b.get(k)
            if j is None:
                continue
            if keep_field is not None and keep_field in ea and (ea[keep_field][i] == 0 or eb[keep_field][j] == 0):
                continue
            va.append(float(ea[field][i]) * scale)
            vb.append(float(eb[field][j]) * scale)
            refs.append(k[0])
            seeds.append(s)
    return np.asarray(va), np.asarray(vb), np.asarray(refs), np.asarray(seeds, dtype=np.int64)


def pooled_episodes(rows: Sequence[Mapping], field: str, *, scale: float = 1.0,
                    keep_field: str | None = "frames") -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(values, reference ids, seed indices) of one row's episodes over its seeds (``rows[s]`` the
    ``per_episode`` record of seed ``s``), times ``scale``, empty episodes dropped."""
    vals, refs, seeds = [], [], []
    for s, e in enumerate(rows):
        for i, (r, _) in enumerate(episode_keys(e)):
            if keep_field is not None and keep_field in e and e[keep_field][i] == 0:
                continue
            vals.append(float(e[field][i]) * scale)
            refs.append(r)
            seeds.append(s)
    return np.asarray(vals), np.asarray(refs), np.asarray(seeds, dtype=np.int64)
