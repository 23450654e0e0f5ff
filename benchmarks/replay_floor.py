"""The floor every learned tracker must beat: kinematic replay of the reference on TrackingEnv.

Runs :func:`adadex.envs.replay.replay_policy` over every reference of a split (default: the
``small`` dataset's unseen-trajectory test part), with the paper's metrics: mean errors and both
success rates (mean-error and completion), and the object-centric ones beside them.

    python benchmarks/replay_floor.py [--dataset DIR] [--split unseen_trajectory] [--part test] [--out FILE]
    python benchmarks/replay_floor.py --randomize [--action-noise-scale 10] [--repeats 4] [--seed 20000]
    python benchmarks/replay_floor.py --randomize --repeats 4 --seed 20000 \
        --feed-forward anchor=0.05,anchor_reach=0.10,anchor_lookahead=4        # the anchored feed-forward
    python benchmarks/replay_floor.py --randomize --repeats 4 --seed 20000 --randomization object_xy_std=0,object_yaw_std=0
    python benchmarks/replay_floor.py --randomize --repeats 4 --seed 777 --part train --channel-c 0,0,0,1,1,1,1
    python benchmarks/replay_floor.py --randomize --repeats 4 --seed 20000 \
        --tracker runs/table1/seed_0/generalist/tracker.pt \
        --from-off --randomization action_noise_correlated=0.02,action_noise_uncorrelated=0.05   # one factor

``--action-noise-scale`` multiplies Table 3's action-noise standard deviations (the env adds them in units
of the action bound, 0.1 rad; 10 gives the radian reading used before 2026-11-25). ``--randomization
k=v,…`` changes Table 3's fields (:class:`adadex.envs.randomization.Randomization`), e.g. the object's
displacement off: how much of a floor the displacement costs (a range is ``lo:hi``, ``robot_mass=1:1``);
with ``--from-off`` they change everything-off instead of Table 3, so the run draws only the factors
named. ``--feed-forward k=v,…`` evaluates, instead of replay, the untrained residual tracker with those
feed-forward settings (:class:`adadex.modules.tracker.Tracker`'s ``anchor``, ``anchor_reach``,
``anchor_iterations``, ``anchor_lookahead``: the object-anchored feed-forward) and also replay on the same
draws, and prints the paired differences with 95 % bootstrap intervals over references; ``--tracker PATH``
does the same for a saved tracker (e.g. a pipeline's distilled generalist) — which of Table 3's factors
costs it what it costs replay. ``--channel-c a,…`` does the same for replay under a constant edit of channel C
(:class:`adadex.transforms.modulation.CompactModulation`; 7 numbers: the palm's offset x, y, z in units of
``lambda_palm``, within ±2, then the index, middle, ring and thumb flexion in units of ``lambda_grip``, within ±1),
e.g. ``0,0,0,1,1,1,1``: every finger closed 0.3 rad past the reference — a firmer grip. Beside replay, the
paired completion difference is also printed by how far the reference object travels from its start within
the episode window (``travel_m`` per episode in the JSON), with the policy taken only where it travels at
least 15, 17 or 20 cm and replay elsewhere — the rule "reach only for objects the reference carries past
what the paper's test tolerates" (docs/modulation.md). For replay and the policy beside it, how often
episodes end early per reference verb (``ended_by_verb``). ``--repeats`` lists every reference that many times (one Table 3 draw
each), ``--seed`` is the env seed (the evaluation's draws).

Without ``--dataset`` the ``small`` preset is built into ``data/small`` first (a few minutes).
"""

from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path

import numpy as np

from _data import check_result, refuse, settings, write_result

NAME = "replay_floor"
RESULTS = Path(__file__).resolve().parent / "results"
ROOT = Path(__file__).resolve().parents[1]


def main(argv=None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--dataset", type=Path, default=None)
    p.add_argument("--split", default="unseen_trajectory")
    p.add_argument("--part", default="test")
    p.add_argument("--randomize", action="store_true", help="with Table 3 domain randomization")
    p.add_argument("--action-noise-scale", type=float, default=1.0,
                   help="with --randomize: multiply Table 3's action-noise stds by this (default 1)")
    p.add_argument("--max-worlds", type=int, default=64, help="worlds stepped together (default 64)")
    p.add_argument("--repeats", type=int, default=1, help="episodes per reference, one draw each (default 1)")
    p.add_argument("--seed", type=int, default=None, help="the env seed (default: the env's)")
    p.add_argument("--randomization", default="", help="with --randomize: Table 3 fields k=v,… to change")
    p.add_argument("--from-off", action="store_true",
                   help="with --randomize: --randomization changes everything-off, not Table 3 (the factors named)")
    p.add_argument("--tracker", type=Path, default=None, help="a saved tracker to evaluate beside replay, paired")
    p.add_argument("--feed-forward", default="", help="Tracker feed-forward settings k=v,… (anchor, anchor_reach, "
                                                      "anchor_iterations, anchor_lookahead) to evaluate beside replay")
    p.add_argument("--channel-c", default="", help="7 numbers: replay under this constant channel-C edit (palm "
                                                   "x, y, z within ±2; index, middle, ring, thumb grip within ±1) "
                                                   "beside replay")
    p.add_argument("--out", type=Path, default=RESULTS / "replay_floor.json")
    p.add_argument("--force", action="store_true",
                   help="replace --out even if it is not an earlier result of this benchmark")
    a = p.parse_args(argv)
    check_result(a.out, name=NAME, force=a.force)      # before any work: refuse a file not ours
    if a.repeats < 1:
        raise refuse(NAME, f"--repeats must be ≥ 1, got {a.repeats}")
    if (a.randomization or a.from_off) and not a.randomize:
        raise refuse(NAME, "--randomization/--from-off change Table 3: give --randomize too")
    if sum(map(bool, (a.tracker is not None, a.feed_forward, a.channel_c))) > 1:
        raise refuse(NAME, "--tracker, --feed-forward and --channel-c each give the policy beside replay: give one")
    edit = _channel_c(a.channel_c) if a.channel_c else None

    from adadex.data.build import build_dataset
    from adadex.envs.randomization import Randomization
    from adadex.envs.replay import replay_policy
    from adadex.envs.tracking import TrackingConfig, episode_references
    from adadex.errors import AdadexError, ConfigError
    from adadex.eval.evaluate import evaluate, format_summary
    from adadex.eval.paired import paired_bootstrap
    from adadex.modules.tracker import Tracker
    from adadex.transforms.policy import make_policy

    feed_forward = settings(a.feed_forward, _FeedForward(), "--feed-forward", NAME)
    changes = settings(a.randomization, Randomization(), "--randomization", NAME)
    try:
        table3 = dataclasses.replace(Randomization.off() if a.from_off else Randomization(), **changes)
        anchored = Tracker(hidden=(16,), residual=0.25, **feed_forward).zero_mean().freeze() if feed_forward else None
    except ConfigError as e:
        raise refuse(NAME, f"--randomization/--feed-forward: {e}") from None
    if a.tracker is not None:
        try:
            beside = make_policy(Tracker.load(a.tracker).freeze(), None, channels="none")
        except (AdadexError, OSError) as e:
            raise refuse(NAME, f"--tracker: {e}") from None
    elif anchored is not None:
        beside = make_policy(anchored, None, channels="none")
    elif edit is not None:
        beside = edit
    else:
        beside = None

    dataset = a.dataset
    if dataset is None:
        dataset = ROOT / "data" / "small"
        if not (dataset / "index.json").exists():
            build_dataset("small", dataset, seed=0)
    scale = a.action_noise_scale
    randomize = dataclasses.replace(table3, action_noise_correlated=scale * table3.action_noise_correlated,
                                    action_noise_uncorrelated=scale * table3.action_noise_uncorrelated)
    split = (a.split, a.part)
    if a.repeats > 1:          # every reference listed `repeats` times: the same episodes for every policy
        from adadex.data.reference import ReferenceDataset

        split = None
        references = episode_references(ReferenceDataset(dataset), (a.split, a.part), TrackingConfig().window)
    kw = dict(split=split, max_worlds=a.max_worlds, randomize=randomize if a.randomize else None,
              **({"references": references * a.repeats} if split is None else {}),
              **({"seed": a.seed} if a.seed is not None else {}))
    res = evaluate(replay_policy(), dataset, **kw)
    summary = res["summary"]
    result = {"dataset": str(dataset), "split": [a.split, a.part], "references": res["references"],
              "randomize": a.randomize, "action_noise_scale": a.action_noise_scale if a.randomize else None,
              "randomization": changes, "from_off": a.from_off,
              "repeats": a.repeats, "seed": a.seed,
              "steps": res["steps"], "wall_s": res["wall_s"], **summary,
              "per_reference": res["per_reference"]}
    noise = f", action noise × {a.action_noise_scale:g}" if a.randomize and a.action_noise_scale != 1 else ""
    changed = f" (changed: {a.randomization})" if a.randomization else ""
    print(f"kinematic replay on {res['references']} episodes of {a.split}/{a.part}"
          f"{' with randomization' if a.randomize else ''}{changed}{noise} ({res['wall_s']:.0f} s):")
    print(format_summary(summary))
    verbs = reference_verbs(dataset, res["per_episode"]["reference"])
    result["ended_by_verb"] = ended_by_verb(res["per_episode"]["ended_early"], verbs)
    print("  episodes ended, by the reference's verb: " + _ended_line(result["ended_by_verb"]))
    if beside is not None:
        ff = evaluate(beside, dataset, env_transform=beside.primer, **kw)
        refs = ff["per_episode"]["reference"]
        diffs = {}
        for field in ("completion", "object_completion", "carried"):
            d = paired_bootstrap(100 * np.asarray(ff["per_episode"][field], float),
                                 100 * np.asarray(res["per_episode"][field], float), np.asarray(refs))
            diffs[f"{field}_pct"] = {"diff": d["estimate"], "ci95": d["ci95"]}
        key, what, given = (("tracker", f"the tracker {a.tracker}", str(a.tracker)) if a.tracker is not None else
                            ("feed_forward", f"the untrained residual tracker with {a.feed_forward}", feed_forward)
                            if edit is None else
                            ("channel_c", f"replay with channel C held at {a.channel_c}", a.channel_c))
        travel = reference_travel(dataset, refs, TrackingConfig().window)
        result[key] = {"settings": given, **ff["summary"], "vs_replay": diffs, "per_reference": ff["per_reference"],
                       "by_travel": by_travel(100 * np.asarray(ff["per_episode"]["completion"], float),
                                              100 * np.asarray(res["per_episode"]["completion"], float),
                                              np.asarray(refs), travel)}
        result["per_episode"] = {"reference": refs, "travel_m": travel.tolist(),
                                 **{f"{row}_{f}": p["per_episode"][f] for row, p in (("replay", res), (key, ff))
                                    for f in ("completion", "object_completion")}}
        result[key]["ended_by_verb"] = ended_by_verb(ff["per_episode"]["ended_early"], verbs)
        print(f"{what} ({ff['wall_s']:.0f} s):")
        print(format_summary(ff["summary"]))
        print("  episodes ended, by the reference's verb: " + _ended_line(result[key]["ended_by_verb"]))
        print("  against replay on the same episodes: " + ", ".join(
            f"{k.removesuffix('_pct').replace('_', ' ')} {v['diff']:+.1f} [{v['ci95'][0]:+.1f}, {v['ci95'][1]:+.1f}]"
            for k, v in diffs.items()))
        table = result[key]["by_travel"]
        print("  completion against replay by the reference object's travel: " + ", ".join(
            f"{_span(b['travel_cm'])} cm {b['diff']:+.1f} ({b['episodes']})" for b in table["bins"] if b["episodes"]))
        print("  the policy only where the reference object travels at least X, replay elsewhere: " + ", ".join(
            f"X = {r['travel_cm']:.0f} cm ({r['fraction']:.0%} of the episodes) {r['diff']:+.1f} "
            f"[{r['ci95'][0]:+.1f}, {r['ci95'][1]:+.1f}]" for r in table["rules"]))
    write_result(a.out, result, name=NAME, force=a.force, indent=1)
    print(f"wrote {a.out}")
    return result


#: bins (m) of the reference object's travel within the episode window, and the rules' thresholds (m)
TRAVEL_BINS = (0.0, 0.10, 0.15, 0.20, float("inf"))
TRAVEL_RULES = (0.15, 0.17, 0.20)


def reference_travel(dataset, references, window: int) -> np.ndarray:
    """(N,) the farthest the reference object gets from where it starts within each episode's window, m
    (the episode's frames ``window_start`` … ``window_start + window − 1`` of reference ``references[i]``)."""
    from adadex.data.reference import ReferenceDataset

    ds = dataset if isinstance(dataset, ReferenceDataset) else ReferenceDataset(dataset)
    out = {}
    for r in set(references):
        start = ds.entries[r]["window_start"]
        p = np.asarray(ds[r].object_pose[start:start + window, :3], float)
        out[r] = float(np.linalg.norm(p - p[0], axis=1).max())
    return np.array([out[r] for r in references])


def by_travel(policy: np.ndarray, replay: np.ndarray, references: np.ndarray, travel: np.ndarray) -> dict:
    """The paired difference policy − replay (per-episode %, same episodes) per bin of the reference object's
    travel (:data:`TRAVEL_BINS`), and for each rule of :data:`TRAVEL_RULES` (the policy where the travel
    reaches the threshold, replay elsewhere) with its bootstrap interval over references."""
    from adadex.eval.paired import paired_bootstrap

    bins = []
    for lo, hi in zip(TRAVEL_BINS[:-1], TRAVEL_BINS[1:]):
        m = (travel >= lo) & (travel < hi)
        bins.append({"travel_cm": [100 * lo, None if hi == float("inf") else 100 * hi], "episodes": int(m.sum()),
                     "diff": float((policy[m] - replay[m]).mean()) if m.any() else None})
    rules = []
    for x in TRAVEL_RULES:
        chosen = np.where(travel >= x, policy, replay)
        d = paired_bootstrap(chosen, replay, references)
        rules.append({"travel_cm": 100 * x, "fraction": float((travel >= x).mean()), "diff": d["estimate"],
                      "ci95": d["ci95"]})
    return {"bins": bins, "rules": rules}


def reference_verbs(dataset, references) -> list:
    """The verb each reference was synthesized from (its ``meta["verb"]``; ``"?"`` where it has none)."""
    from adadex.data.reference import ReferenceDataset

    ds = dataset if isinstance(dataset, ReferenceDataset) else ReferenceDataset(dataset)
    return [str((ds.entries[r].get("meta") or {}).get("verb", "?")) for r in references]


def ended_by_verb(ended, verbs) -> dict:
    """``{verb: {"episodes": n, "ended_pct": %}}``: how often episodes ended early, per reference verb."""
    out = {}
    for e, v in zip(ended, verbs):
        out.setdefault(v, []).append(bool(e))
    return {v: {"episodes": len(x), "ended_pct": 100.0 * sum(x) / len(x)} for v, x in sorted(out.items())}


def _ended_line(table: dict) -> str:
    return ", ".join(f"{v} {t['ended_pct']:.0f} % ({t['episodes']})" for v, t in table.items())


def _span(cm: list) -> str:
    lo, hi = cm
    return f"{lo:.0f}–" + ("" if hi is None else f"{hi:.0f}")


def _channel_c(text: str):
    """``--channel-c``'s 7 numbers → replay under a channel-C modulator forced to that action (one policy)."""
    import torch

    from adadex.modules.modulator import Modulator
    from adadex.modules.tracker import Tracker
    from adadex.train.paired_choice import forced
    from adadex.transforms.policy import make_policy

    try:
        values = [float(v) for v in text.split(",")]
    except ValueError:
        raise refuse(NAME, f"--channel-c: {text!r} is not 7 numbers separated by commas") from None
    if len(values) != 7:
        raise refuse(NAME, f"--channel-c: 7 numbers (palm x, y, z; index, middle, ring, thumb grip), got {len(values)}")
    bad = [i for i, v in enumerate(values) if not np.isfinite(v) or abs(v) > (2.0 if i < 3 else 1.0)]
    if bad:
        raise refuse(NAME, f"--channel-c: entry {bad[0]} = {values[bad[0]]:g} is outside "
                           f"{'±2 (palm)' if bad[0] < 3 else '±1 (grip)'}")
    return make_policy(Tracker.replay().freeze(),
                       forced(Modulator("C", hidden=(8,)), torch.tensor(values, dtype=torch.float32)))


class _FeedForward:
    """The Tracker settings ``--feed-forward`` takes, with their types (what :func:`settings` reads)."""

    anchor = 0.05
    anchor_reach = 0.0
    anchor_iterations = 3
    anchor_lookahead = 1


if __name__ == "__main__":
    main()
