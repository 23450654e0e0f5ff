"""Table 1's aggregation: bootstrap intervals and paired differences to the tracker from per-episode
results, and the Student-t fallback for evaluations stored without them."""

import json
import math

import numpy as np
import pytest

from adadex.eval.table1 import EPISODE_FIELDS, METRICS, NOMINAL_NOTE, aggregate, table_markdown

KEY = ("unseen_trajectory", "randomized")


def _episodes(completion, rng, refs=20, repeats=3, object_off=0.02):
    """A per_episode record as evaluate writes it: ``completion`` per episode (refs × repeats)."""
    n = refs * repeats
    return {"reference": [int(r) for r in np.repeat(np.arange(refs), repeats)],
            "repeat": [int(k) for k in np.tile(np.arange(repeats), refs)],
            "completion": [float(c) for c in completion], "success_mean_error": [bool(c > 0.5) for c in completion],
            "object_completion": [float(c) * 0.8 for c in completion], "carried": [bool(c > 0.6) for c in completion],
            "frames": [59] * n, "ended_early": [False] * n,
            "T_o": list(rng.uniform(0.01, 0.03, n) + object_off), "R_o": list(rng.uniform(0.1, 0.3, n)),
            "T_h": list(rng.uniform(0.005, 0.01, n)), "R_h": list(rng.uniform(0.02, 0.05, n)),
            "E_finger": list(rng.uniform(0.01, 0.03, n))}


def _summary(e):
    """What summarize gives for the same episodes."""
    mean = lambda k: float(np.mean(np.asarray(e[k], dtype=float)))        # noqa: E731
    return {"trajectories": len(e["reference"]), "empty": 0, "T_o": 100 * mean("T_o"), "R_o": mean("R_o"),
            "T_h": 100 * mean("T_h"), "R_h": mean("R_h"), "E_finger": mean("E_finger"),
            "success_mean_error_pct": 100 * mean("success_mean_error"), "completion_pct": 100 * mean("completion"),
            "object_completion_pct": 100 * mean("object_completion"), "carried_pct": 100 * mean("carried")}


def _inputs(shift=0.05, seeds=2):
    rng = np.random.default_rng(0)
    summaries, episodes = {}, {}
    for _ in range(seeds):
        level = np.repeat(rng.uniform(0.2, 0.9, 20), 3)         # per-reference difficulty, shared by the rows
        tracker = np.clip(level + rng.normal(0, 0.05, 60), 0, 1)
        rows = {"tracker": tracker, "ROT": np.clip(tracker + shift, 0, 1), "replay": tracker}
        for row, c in rows.items():
            e = _episodes(c, np.random.default_rng(1), object_off=0.0 if row != "ROT" else -0.005)
            summaries.setdefault((*KEY, row), []).append(_summary(e))
            episodes.setdefault((*KEY, row), []).append(e)
    return summaries, episodes


def test_per_episode_inputs_give_bootstrap_intervals_and_paired_differences():
    summaries, episodes = _inputs()
    table = aggregate(summaries, episodes)
    rows = table["unseen_trajectory"]["randomized"]
    tracker, rot, replay = rows["tracker"], rows["ROT"], rows["replay"]
    assert "diff_vs_tracker" not in tracker and "diff_vs_tracker_ci95" not in tracker
    for entry in rows.values():
        assert entry["ci"] == "bootstrap" and entry["seeds"] == 2 and entry["episodes"] == 120
        for m in METRICS:
            lo, hi = entry[f"{m}_ci95"]
            assert lo <= entry[m] <= hi
    for m, key in METRICS.items():     # the value is still the mean over seeds of the seeds' summaries
        assert tracker[m] == pytest.approx(np.mean([s[key] for s in summaries[(*KEY, "tracker")]]))
    assert set(rot["diff_vs_tracker"]) == set(METRICS) == set(rot["diff_vs_tracker_ci95"])
    d, (lo, hi) = rot["diff_vs_tracker"]["completion_pct"], rot["diff_vs_tracker_ci95"]["completion_pct"]
    assert d == pytest.approx(rot["completion_pct"] - tracker["completion_pct"])
    assert 0 < lo <= d <= hi and hi - lo < 3.0        # ≈ 5 points, resolved
    assert rot["diff_vs_tracker"]["T_o"] == pytest.approx(-0.5)        # cm: the same episodes, 5 mm closer
    # a row on the very same episodes as the tracker: difference 0, degenerate interval
    assert replay["diff_vs_tracker"]["completion_pct"] == 0.0
    assert replay["diff_vs_tracker_ci95"]["completion_pct"] == [0.0, 0.0]
    # the paired interval is far narrower than the row's own interval over references
    assert hi - lo < (rot["completion_pct_ci95"][1] - rot["completion_pct_ci95"][0]) / 3
    assert aggregate(summaries, episodes) == table                    # seeded: the same table
    json.loads(json.dumps(table))
    md = table_markdown(table)
    assert "Difference to the tracker" in md and "object completion %" in md and "carried %" in md
    line = next(ln for ln in md.splitlines() if ln.startswith("| +R+O+T") and "[" in ln)
    assert f"{d:+.1f} [{lo:+.1f}, {hi:+.1f}]" in line
    assert NOMINAL_NOTE not in md                                     # only a nominal block carries it
    nominal = table_markdown({KEY[0]: {"nominal": table[KEY[0]][KEY[1]]}})
    assert nominal.index("nominal") < nominal.index(NOMINAL_NOTE) < nominal.index("| method")


def test_old_style_summaries_without_per_episode_results_still_load():
    """Stages stored by older runs: no per_episode, no object-centric keys. Student-t over seeds, the
    differences by seed, the missing metrics NaN and shown as '—'."""
    summaries, _ = _inputs()
    old = {k: [{m: v for m, v in s.items() if m not in ("object_completion_pct", "carried_pct")} for s in per_seed]
           for k, per_seed in summaries.items()}
    table = aggregate(old)
    rot, tracker = table["unseen_trajectory"]["randomized"]["ROT"], table["unseen_trajectory"]["randomized"]["tracker"]
    assert rot["ci"] == "student-t" and rot["episodes"] == 120
    assert math.isnan(rot["object_completion_pct"]) and rot["object_completion_pct_ci95"] is None
    seeds = [s["completion_pct"] for s in old[(*KEY, "ROT")]]
    assert rot["completion_pct"] == pytest.approx(np.mean(seeds))
    assert rot["completion_pct_ci95"] is not None and rot["completion_pct_ci95"][0] < rot["completion_pct"]
    per_seed = [a["completion_pct"] - b["completion_pct"] for a, b in zip(old[(*KEY, "ROT")], old[(*KEY, "tracker")])]
    assert rot["diff_vs_tracker"]["completion_pct"] == pytest.approx(np.mean(per_seed))
    assert "diff_vs_tracker" not in tracker
    assert "—" in table_markdown(table)
    # a mix (the tracker re-evaluated with per-episode results, the row not): the row falls back
    _, episodes = _inputs()
    mixed = aggregate(summaries, {k: v for k, v in episodes.items() if k[2] == "tracker"})
    rows = mixed["unseen_trajectory"]["randomized"]
    assert rows["tracker"]["ci"] == "bootstrap" and rows["ROT"]["ci"] == "student-t"
    assert rows["ROT"]["diff_vs_tracker"]["completion_pct"] == pytest.approx(np.mean(per_seed))
    # a seed without per-episode results (None) makes the row fall back too
    partial = dict(episodes)
    partial[(*KEY, "ROT")] = [episodes[(*KEY, "ROT")][0], None]
    assert aggregate(summaries, partial)["unseen_trajectory"]["randomized"]["ROT"]["ci"] == "student-t"


def test_every_metric_has_a_per_episode_field():
    assert set(EPISODE_FIELDS) == set(METRICS)

def test_o_channel_note_says_whether_o_acts_and_how_far_it_reaches():
    from adadex.eval.table1 import o_channel_note

    table = {"unseen_trajectory": {"randomized": {"O": {"diff_vs_tracker": {"completion_pct": 0.4},
                                                        "diff_vs_tracker_ci95": {"completion_pct": [-1.0, 1.8]}}}}}
    note = o_channel_note(table, 0.05, lambda_latent=0.25)
    assert note["resolved"] is False and "no effect resolved" in note["text"]
    assert note["o_reach"] == pytest.approx(0.05 * 0.25 * 8) and note["t_reach"] == pytest.approx(0.05 * 22 ** 0.5)
    table["unseen_trajectory"]["randomized"]["O"]["diff_vs_tracker_ci95"]["completion_pct"] = [0.1, 0.9]
    assert o_channel_note(table, 0.05, lambda_latent=0.25)["resolved"] is True
    assert o_channel_note({}, 0.05, lambda_latent=0.25)["diff"] is None
