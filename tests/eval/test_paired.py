"""The paired bootstrap over references, stratified by training seed."""

import numpy as np
import pytest

from adadex.eval.paired import RESAMPLES, bootstrap_mean, pair_episodes, paired_bootstrap, pooled_episodes


def _design(refs=47, repeats=4, seeds=3):
    """Reference and seed ids of a pipeline-like evaluation: every seed, every reference × repeats."""
    ref_ids = np.tile(np.repeat(np.arange(refs), repeats), seeds)
    seed_ids = np.repeat(np.arange(seeds), refs * repeats)
    return ref_ids, seed_ids


def test_a_known_paired_shift_is_resolved():
    """Per-episode completion spread like the real one (SD ≈ 28 points, a per-reference part shared by
    both rows); row A is the tracker plus 3 points plus small per-episode noise: the paired interval
    holds 3 and excludes 0, while the rows' own intervals overlap."""
    rng = np.random.default_rng(1)
    refs, seeds = _design()
    level = rng.uniform(10, 90, 47)[refs] + rng.normal(0, 10, len(refs))
    tracker = np.clip(level, 0, 100)
    row = tracker + 3.0 + rng.normal(0, 3, len(refs))
    d = paired_bootstrap(row, tracker, refs, seeds)
    lo, hi = d["ci95"]
    assert 0 < lo < 3.0 < hi and hi - lo < 1.5
    assert d["estimate"] == pytest.approx(3.0, abs=0.4)
    assert d["episodes"] == 3 * 47 * 4 and d["references"] == [47, 47, 47] and d["seeds"] == 3
    assert d["resamples"] == RESAMPLES >= 2000
    a, b = bootstrap_mean(row, refs, seeds), bootstrap_mean(tracker, refs, seeds)
    assert a["ci95"][0] < b["ci95"][1]                     # unpaired, the rows cannot be told apart


def test_identical_rows_give_zero_with_a_degenerate_interval():
    refs, seeds = _design(refs=10, repeats=2, seeds=2)
    x = np.random.default_rng(0).uniform(0, 100, len(refs))
    d = paired_bootstrap(x, x.copy(), refs, seeds)
    assert d["estimate"] == 0.0 and d["ci95"] == [0.0, 0.0]


def test_deterministic_for_a_seed():
    refs, seeds = _design(refs=12, repeats=2, seeds=2)
    rng = np.random.default_rng(3)
    a, b = rng.normal(size=len(refs)), rng.normal(size=len(refs))
    one = paired_bootstrap(a, b, refs, seeds, seed=7)
    assert paired_bootstrap(a, b, refs, seeds, seed=7) == one
    assert paired_bootstrap(a, b, refs, seeds, seed=8)["ci95"] != one["ci95"]
    assert paired_bootstrap(a, b, refs, seeds, seed=8)["estimate"] == one["estimate"]


def test_resampling_is_stratified_by_seed():
    """Seed 0's episodes are all 0 and seed 1's all 10: resampling references *within* each seed never
    changes a seed's mean, so the interval is the single value 5 (pooled resampling would mix the
    seeds and spread it). The statistic is the mean of the seeds' means, whatever their sizes."""
    refs = np.concatenate([np.arange(10), np.arange(30)])
    seeds = np.repeat([0, 1], [10, 30])
    values = np.where(seeds == 0, 0.0, 10.0)
    d = bootstrap_mean(values, refs, seeds)
    assert d["estimate"] == pytest.approx(5.0) and d["ci95"] == pytest.approx([5.0, 5.0])
    assert d["references"] == [10, 30]
    # as one seed, the same numbers spread (SE of 40 values, three quarters at 10: ≈ 0.68)
    lo, hi = bootstrap_mean(values, np.arange(40), None)["ci95"]
    assert hi - lo > 2.0


def test_references_are_resampled_whole():
    """Repeats that copy their reference's value add no information: the interval over 40 references
    × 4 identical repeats is the interval over the 40 references alone (same draws: same seed)."""
    x = np.random.default_rng(2).normal(size=40)
    alone = bootstrap_mean(x, np.arange(40), seed=5)
    repeated = bootstrap_mean(np.repeat(x, 4), np.repeat(np.arange(40), 4), seed=5)
    assert repeated["ci95"] == pytest.approx(alone["ci95"]) and repeated["episodes"] == 160


def test_interval_width_matches_the_standard_error():
    """200 references with N(0, 1) values: the 95 % interval is about ±1.96/√200."""
    x = np.random.default_rng(4).normal(size=200)
    lo, hi = bootstrap_mean(x, np.arange(200), resamples=4000)["ci95"]
    assert (hi - lo) / 2 == pytest.approx(1.96 / np.sqrt(200), rel=0.15)


def test_nan_episodes_are_left_out_and_bad_input_refused():
    d = bootstrap_mean([1.0, np.nan, 3.0], [0, 1, 2])
    assert d["episodes"] == 2 and d["estimate"] == 2.0
    assert bootstrap_mean([np.nan], [0])["ci95"] is None
    with pytest.raises(ValueError, match="equally long"):
        bootstrap_mean([1.0, 2.0], [0])
    with pytest.raises(ValueError, match="same episodes"):
        paired_bootstrap([1.0, 2.0], [1.0], [0, 1])
    with pytest.raises(ValueError, match="resamples"):
        bootstrap_mean([1.0], [0], resamples=0)


def test_pair_episodes_lines_up_reference_and_repeat():
    """Two rows' per-episode records in different orders pair by (reference, repeat), seed by seed;
    an episode one row left empty is dropped from both."""
    a = [{"reference": [5, 5, 7], "repeat": [0, 1, 0], "completion": [0.1, 0.2, 0.3], "frames": [9, 9, 9]}]
    b = [{"reference": [7, 5, 5], "repeat": [0, 1, 0], "completion": [0.6, 0.5, 0.4], "frames": [9, 0, 9]}]
    va, vb, refs, seeds = pair_episodes(a, b, "completion", scale=100.0)
    assert va.tolist() == pytest.approx([10.0, 30.0]) and vb.tolist() == pytest.approx([40.0, 60.0])
    assert refs.tolist() == [5, 7] and seeds.tolist() == [0, 0]
    vals, refs, seeds = pooled_episodes(a + b, "completion")
    assert vals.tolist() == pytest.approx([0.1, 0.2, 0.3, 0.6, 0.4]) and seeds.tolist() == [0, 0, 0, 1, 1]
    with pytest.raises(ValueError, match="seeds"):
        pair_episodes(a, b + b, "completion")
