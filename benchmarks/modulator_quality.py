"""Does modulation pay? Modulators trained around a frozen tracker, each paired with the tracker alone.

For every row (a channel set and its settings) and training seed: PPO trains a modulator around the
frozen tracker (kinematic replay by default, ``Tracker.replay()``; or ``--tracker PATH``) on the
unseen-trajectory training references under Table 3, then the modulated policy and the tracker
alone are evaluated on the unseen-trajectory test references under Table 3, ``--repeats`` draws
each, on the same draws (the same env seed for every row and seed). Printed per row: completion
and object completion (the object within 5 cm: :func:`adadex.envs.frame_errors.object_success`),
carried, T_o, and the paired difference to the tracker with its bootstrap interval over references,
pooled across the seeds (:func:`adadex.eval.paired.paired_bootstrap`), and the same against the
modulator as the trainer initialised it (edits ≈ 0): under Table 3 any perturbation reshuffles which
episodes succeed (an untrained modulator moved replay's completion by up to 3.4 points), so the
difference to the untrained modulator is what training learned.

A row is ``CHANNELS[:inputs[:init_scale]]``: ``C+T`` (the defaults: the view, each channel's own
scale), ``R+O+T:observation:0.5`` (the modulator as it was before 2026-11-27), ``C+T:prior=anchor``
(channel C's palm around the object anchor's shift), ``C+T:hold=10:hold_C=0.5`` (C's exploration
noise held for 10 steps at scale 0.5; :class:`~adadex.modules.modulator.Modulator`), ``A`` (channel A,
the object-anchor reach chosen once per episode; rows with A, L or K also report what the trained and
the untrained modulator latch at the first step — reach, lead, gains — by the object's start offset),
``A:focus_A=start_offset:learner=paired`` (A fitted to paired rollouts of the ``--arms`` instead of PPO,
:mod:`adadex.train.paired_choice`; ``--frames`` and ``--ppo`` unused, ``--paired repeats=8`` sets the
draws). Every run is kept
under ``--runs`` and resumes (training from its checkpoint, evaluations from their JSON), so a
killed benchmark continues where it stopped::

    python benchmarks/modulator_quality.py --dataset data/small_pg --rows C+T,R+T,R+O+T:observation:0.5
        [--seeds 0,1,2] [--frames 250000] [--repeats 4] [--reward w_object_success=3]
        [--ppo advantage=group --collector group_size=4] [--modulation reach_smooth=true] [--runs DIR] [--out FILE]
        [--arms=-1,1] [--paired repeats=4,steps=2000]
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
import torch

from _data import check_result, refuse, settings, write_result

NAME = "modulator_quality"
from adadex.io import atomic_write_text

RESULTS = Path(__file__).resolve().parent / "results"
METRICS = ("completion_pct", "object_completion_pct", "carried_pct", "success_mean_error_pct", "T_o")
#: per-episode field → its summary name (as % where the summary gives %)
PAIRED = {"completion": "completion_pct", "object_completion": "object_completion_pct", "carried": "carried_pct"}


def parse_row(text: str) -> dict:
    """``CHANNELS[:inputs[:init_scale]][:option=value …]``; options: ``prior=anchor`` (with
    ``prior_reach=M``: objects displaced M m or farther left where they lie; its lookahead is
    ``--modulation reach_lookahead``), ``hold=K`` (steps the exploration noise is held), ``hold_X=scale``
    (channel X's held-noise scale) and
    ``focus_X=part+part`` (channel X's head reads only those view parts), the
    :class:`~adadex.modules.modulator.Modulator` settings ``prior``, ``hold_steps``, ``hold_scale``, ``focus``;
    ``learner=paired`` (fit latched channels to paired rollouts, :mod:`adadex.train.paired_choice`,
    instead of PPO); ``history=N`` (previous frames in the view, ``ModulatorSettings.history``);
    ``core=gru`` (a recurrent core, ``Modulator(core=…)``); and ``decide=K`` (a decision every K control
    steps, held in between, ``Modulator(decide_every=…)``)."""
    parts = text.split(":")
    options = [p for p in parts[1:] if "=" in p]
    parts = [p for p in parts if "=" not in p]
    if not 1 <= len(parts) <= 3:
        raise refuse(NAME, f"--rows: {text!r} is not CHANNELS[:inputs[:init_scale]][:option=value …]")
    try:
        row = {"channels": parts[0], "inputs": parts[1] if len(parts) > 1 else "view",
               "init_scale": float(parts[2]) if len(parts) > 2 and parts[2] != "default" else None, "modulator": {}}
        for option in options:
            _row_option(row, option, text)
    except ValueError:
        raise refuse(NAME, f"--rows: {text!r} has a setting that needs a number") from None
    row["name"] = text.replace("+", "").replace(":", "_").replace(".", "").replace("=", "")
    return row


def _row_option(row: dict, option: str, text: str) -> None:
    """One ``key=value`` of a ``--rows`` entry into ``row`` (see :func:`parse_row`)."""
    key, value = option.split("=", 1)
    if key == "prior":
        row["modulator"]["prior"] = value
    elif key == "prior_reach":
        row["modulator"]["prior_reach"] = float(value)
    elif key == "hold":
        row["modulator"]["hold_steps"] = int(value)
    elif key.startswith("hold_"):
        row["modulator"].setdefault("hold_scale", {})[key[5:]] = float(value)
    elif key.startswith("focus_"):
        row["modulator"].setdefault("focus", {})[key[6:]] = value.split("+")
    elif key == "learner" and value in ("ppo", "paired"):
        row["learner"] = value
    elif key == "history" and value.isdigit():
        row["history"] = int(value)
    elif key == "core":
        row["modulator"]["core"] = value
    elif key == "decide" and value.isdigit():
        row["modulator"]["decide_every"] = int(value)
    else:
        raise refuse(NAME, f"--rows: unknown option {key!r} in {text!r} (prior=, prior_reach=, hold=, hold_X=, "
                           "focus_X=, learner=ppo|paired, history=N, core=gru, decide=K)")


#: the object's horizontal start offset |Δ| (m): bins of the latched-choice report (channels A, L and K)
OFFSET_BINS = (0.0, 0.02, 0.04, 0.06, 0.08, 0.10, float("inf"))


def first_step(policy, ds, episodes, config, seed: int = 20_000, max_worlds: int = 64):
    """Each episode's first step, deterministic, on the evaluation's own draws (the same references,
    chunks and env seeds as ``evaluate``): ``({name: (episodes,) latched value}, (episodes,) the object's
    horizontal start offset in m)`` — channel A's reach (``"reach"``), L's lead in control steps
    (``"lead_arm"``, ``"lead_hand"``) and K's gains (``"gain_arm"``, ``"gain_hand"``), those the policy has."""
    from adadex.envs.chunked import chunked_rollouts
    from adadex.envs.observation import OBJECT_START, REF_OBJECT_START
    from adadex.envs.randomization import Randomization
    from adadex.modules.channels import GAIN_STATE, LEAD_STATE, REACH_STATE

    picks = {"reach": (REACH_STATE, 0), "lead_arm": (LEAD_STATE, 0), "lead_hand": (LEAD_STATE, 1),
             "gain_arm": (GAIN_STATE, 0), "gain_hand": (GAIN_STATE, 1)}
    values, offset = {}, []
    for part in chunked_rollouts(policy, ds, episodes, max_worlds=max_worlds, seed=seed, config=config,
                                 env_transform=policy.primer, steps=1, progress=False,
                                 randomize=Randomization(), nthread=2):
        td = part.rollout
        for name, (key, i) in picks.items():
            if key in td["next"].keys(True):
                values.setdefault(name, []).append(td["next", key][:, 0, i])
        offset.append(torch.linalg.vector_norm(td[OBJECT_START][:, 0, :2] - td[REF_OBJECT_START][:, 0, :2], dim=-1))
    return {name: torch.cat(parts).numpy() for name, parts in values.items()}, torch.cat(offset).numpy()


def latched_by_offset(policy, ds, episodes, config, seed: int = 20_000, max_worlds: int = 64) -> dict:
    """What a modulator latched at each evaluation episode's first step (:func:`first_step`), overall
    and by the object's horizontal start offset: what it learned to choose, on the evaluation's draws."""
    values, offset = first_step(policy, ds, episodes, config, seed, max_worlds)
    out = {}
    for name, v in values.items():
        bins = []
        for lo, hi in zip(OFFSET_BINS[:-1], OFFSET_BINS[1:]):
            m = (offset >= lo) & (offset < hi)
            bins.append({"offset_cm": [100 * lo, None if hi == float("inf") else 100 * hi], "episodes": int(m.sum()),
                         "mean": float(v[m].mean()) if m.any() else None})
        out[name] = {"mean": float(v.mean()), "by_offset": bins}
    return out


def main(argv=None) -> dict:
    from adadex.data.reference import ReferenceDataset
    from adadex.envs.randomization import Randomization
    from adadex.envs.tracking import TrackingConfig, episode_references
    from adadex.eval.evaluate import evaluate
    from adadex.eval.paired import paired_bootstrap
    from adadex.modules.modulator import Modulator
    from adadex.modules.tracker import Tracker
    from adadex.train.config import CollectorConfig, ModulatorSettings, PPOConfig, TrainConfig
    from adadex.errors import ConfigError
    from adadex.train.paired_choice import PairedChoiceConfig, fit_paired_choice
    from adadex.train.ppo import PPOTrainer, training_references
    from adadex.transforms.policy import make_policy

    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--dataset", type=Path, required=True)
    p.add_argument("--rows", default="C+T,R+T,R+O+T:observation:0.5")
    p.add_argument("--seeds", default="0,1,2")
    p.add_argument("--frames", type=int, default=250_000)
    p.add_argument("--repeats", type=int, default=4)
    p.add_argument("--tracker", default=None, help="a tracker checkpoint (default: kinematic replay)")
    p.add_argument("--runs", type=Path, default=Path("runs/modulator_quality"))
    p.add_argument("--ppo", default="", help="PPOConfig settings, e.g. 'lr=1e-4,desired_kl=0'")
    p.add_argument("--reward", default="", help="RewardConfig changes for training, e.g. 'w_object_success=3'")
    p.add_argument("--modulation", default="", help="ModulationConfig settings for training and evaluation, "
                   "e.g. 'reach_smooth=true'")
    p.add_argument("--collector", default="", help="CollectorConfig settings, e.g. 'group_size=4' "
                   "(with --ppo advantage=group: worlds in groups on common random numbers)")
    p.add_argument("--paired", default="", help="PairedChoiceConfig settings for rows with learner=paired, "
                   "e.g. 'repeats=8,steps=2000' (arms: --arms)")
    p.add_argument("--arms", default="-1,1", help="the arms of rows with learner=paired: numbers, or "
                   "values per action entry joined by '/' (default -1,1: channel A's no reach and full reach)")
    p.add_argument("--out", type=Path, default=RESULTS / "modulator_quality.json")
    p.add_argument("--force", action="store_true",
                   help="replace --out even if it is not an earlier result of this benchmark")
    a = p.parse_args(argv)
    check_result(a.out, name="modulator_quality", force=a.force)      # before any work: refuse a file not ours
    rows = [parse_row(r) for r in a.rows.split(",")]
    seeds = [int(s) for s in a.seeds.split(",")]
    from adadex.modules.channels import ModulationConfig

    # as the pipeline trains its modulators
    ppo = {"desired_kl": 0.0, "update_threads": 1, **settings(a.ppo, PPOConfig(), "--ppo", NAME)}
    reward = {k: float(v) for k, v in (kv.split("=") for kv in filter(None, a.reward.split(",")))}
    modulation = settings(a.modulation, ModulationConfig(), "--modulation", NAME)
    try:
        mconfig = ModulationConfig(**modulation)
    except ConfigError as e:
        raise refuse(NAME, f"--modulation: {e}") from None
    for row in rows:                 # a C prior reads the reference as far ahead as the env's reach does
        if row["modulator"].get("prior") is not None and mconfig.reach_lookahead != 1:
            row["modulator"]["prior_lookahead"] = mconfig.reach_lookahead
    collector = settings(a.collector, CollectorConfig(), "--collector", NAME)
    try:
        arms = tuple(float(v) if "/" not in v else tuple(float(x) for x in v.split("/")) for v in a.arms.split(","))
        fit_settings = settings(a.paired, PairedChoiceConfig(), "--paired", NAME)
        if "arms" in fit_settings:
            raise refuse(NAME, "--paired: give the arms with --arms")
        fit_config = PairedChoiceConfig(**fit_settings, arms=arms)
    except ConfigError as e:
        raise refuse(NAME, f"--arms/--paired: {e}") from None
    except ValueError:
        raise refuse(NAME, f"--arms: numbers, or values joined by '/', got {a.arms!r}") from None
    a.runs.mkdir(parents=True, exist_ok=True)
    tracker_path = a.tracker
    if tracker_path is None:
        tracker_path = str(a.runs / "replay_tracker.pt")
        if not Path(tracker_path).is_file():
            Tracker.replay().save(tracker_path)
    ds = ReferenceDataset(a.dataset)
    config = TrackingConfig()
    episodes = episode_references(ds, ("unseen_trajectory", "test"), config.window) * a.repeats
    t_start = time.perf_counter()

    def evaluated(folder: Path, policy) -> dict:
        path = folder / "eval.json"
        if path.is_file():
            return json.loads(path.read_text(encoding="utf-8"))
        res = evaluate(policy, ds, split=None, references=episodes, max_worlds=64, env_transform=policy.primer,
                       config=config, randomize=Randomization(), seed=20_000, progress=False, nthread=2)
        out = {"summary": res["summary"], "per_episode": res["per_episode"], "wall_s": res["wall_s"]}
        folder.mkdir(parents=True, exist_ok=True)
        atomic_write_text(path, json.dumps(out))
        return out

    tracker = Tracker.load(tracker_path).freeze()

    def paired_fit(folder: Path, tc, seed: int):
        """A learner=paired row's modulator, fitted once (kept as policy.pt with its report)."""
        path, report = folder / "policy.pt", folder / "paired_fit.json"
        if not (path.is_file() and report.is_file()):
            torch.manual_seed(seed)
            m = tc.modulator
            mod = Modulator(m.channels, hidden=m.hidden, init_scale=m.init_scale, loc_bound=m.loc_bound,
                            inputs=m.inputs, history=m.history, **row["modulator"])
            fit = fit_paired_choice(mod, tracker, ds, training_references(tc, ds, config.window), fit_config, seed=seed,
                                    config=tc.env_config(config), modulation=mconfig,
                                    randomize=tc.randomization_config(), progress=False)
            folder.mkdir(parents=True, exist_ok=True)
            mod.save(path)
            atomic_write_text(report, json.dumps(fit))
        return Modulator.load(path), json.loads(report.read_text(encoding="utf-8"))

    base = evaluated(a.runs / "tracker_alone", make_policy(tracker, None, channels="none"))
    result = {"benchmark": "modulator_quality", "dataset": str(a.dataset), "tracker": a.tracker or "replay",
              "frames": a.frames, "seeds": seeds, "episodes": len(episodes), "ppo": ppo, "reward": reward,
              "collector": collector, "modulation": modulation,
              "condition": "unseen_trajectory test, Table 3", "tracker_alone": {k: base["summary"][k] for k in METRICS},
              "rows": {}}
    for row in rows:
        per_seed = []
        for seed in seeds:
            folder = a.runs / f"{row['name']}_s{seed}"
            m = ModulatorSettings(tracker=tracker_path, channels=row["channels"], inputs=row["inputs"],
                                  init_scale=row["init_scale"], history=row.get("history", 3), modulation=modulation)
            tc = TrainConfig(dataset=str(a.dataset), out=str(folder), seed=seed,
                             resume=(folder / "checkpoint.pt").is_file(),
                             ppo=PPOConfig(**{**ppo, "total_frames": a.frames}), collector=CollectorConfig(**collector),
                             modulator=m, reward=reward, eval_max_references=0, wandb=False, progress=False)
            # settings ModulatorSettings does not hold (prior, held noise): the trainer gets the modulator
            # built as it would build it (seeded the same), and the control below is that modulator again
            torch.manual_seed(seed)
            policy = Modulator(row["channels"], hidden=m.hidden, init_scale=m.init_scale, loc_bound=m.loc_bound,
                               inputs=m.inputs, history=m.history, **row["modulator"]) if row["modulator"] else None
            t0 = time.perf_counter()
            if row.get("learner") == "paired":
                mod, fit = paired_fit(folder, tc, seed)
                train_s = fit["wall_s"]
            else:
                trained = PPOTrainer(tc, run_name=f"{row['name']} seed {seed}", policy=policy).train()
                train_s = time.perf_counter() - t0
                mod, fit = Modulator.load(trained["policy"]), None
            ev = evaluated(folder, make_policy(tracker, mod, config=mconfig))
            # the control: the same modulator as the trainer initialised it (its edits ≈ 0). Under Table 3
            # any perturbation reshuffles which episodes succeed, so "trained − tracker alone" mixes what
            # training learned with that reshuffle; "trained − untrained" does not
            torch.manual_seed(seed)
            fresh = Modulator(row["channels"], hidden=m.hidden, init_scale=m.init_scale, loc_bound=m.loc_bound,
                              inputs=m.inputs, history=m.history, **row["modulator"])
            ctl = evaluated(folder / "untrained", make_policy(tracker, fresh, config=mconfig))
            latched = {} if not {"A", "L", "K"} & set(mod.layout.channels) else \
                {"latched": latched_by_offset(make_policy(tracker, mod, config=mconfig), ds, episodes, config),
                 "untrained_latched": latched_by_offset(make_policy(tracker, fresh, config=mconfig), ds, episodes,
                                                        config)}
            per_seed.append({"seed": seed, "train_s": train_s, **{k: ev["summary"][k] for k in METRICS}, **latched,
                             **({"paired_fit": {k: v for k, v in fit.items() if k != "per_episode"}} if fit else {}),
                             "untrained": {k: ctl["summary"][k] for k in METRICS},
                             "per_episode": ev["per_episode"], "untrained_episodes": ctl["per_episode"]})
        refs = np.concatenate([s["per_episode"]["reference"] for s in per_seed])
        sid = np.concatenate([[s["seed"]] * len(s["per_episode"]["reference"]) for s in per_seed])

        def paired(field, other):
            a_ = np.concatenate([100.0 * np.asarray(s["per_episode"][field], float) for s in per_seed])
            b_ = np.concatenate([100.0 * np.asarray(other(s)[field], float) for s in per_seed])
            d = paired_bootstrap(a_, b_, refs, sid)
            return {"diff": d["estimate"], "ci95": d["ci95"]}

        diffs = {name: paired(field, lambda s: base["per_episode"]) for field, name in PAIRED.items()}
        learned = {name: paired(field, lambda s: s["untrained_episodes"]) for field, name in PAIRED.items()}
        bulky = ("per_episode", "untrained_episodes")
        entry = {**row, "per_seed": [{k: v for k, v in s.items() if k not in bulky} for s in per_seed],
                 **{k: float(np.mean([s[k] for s in per_seed])) for k in METRICS}, "vs_tracker": diffs,
                 "vs_untrained": learned}
        result["rows"][row["name"]] = entry
        c, o = diffs["completion_pct"], diffs["object_completion_pct"]
        print(f"{row['name']:24s} completion {entry['completion_pct']:5.1f} % ({c['diff']:+.1f} [{c['ci95'][0]:+.1f}, "
              f"{c['ci95'][1]:+.1f}])  object {entry['object_completion_pct']:5.1f} % ({o['diff']:+.1f} "
              f"[{o['ci95'][0]:+.1f}, {o['ci95'][1]:+.1f}])  carried {entry['carried_pct']:5.1f} %  "
              f"T_o {entry['T_o']:.2f} cm  per seed completion "
              + " / ".join(f"{s['completion_pct']:.1f}" for s in per_seed), flush=True)
        u, uo = learned["completion_pct"], learned["object_completion_pct"]
        print(f"{'':24s} vs the same modulator untrained (completion "
              + " / ".join(f"{s['untrained']['completion_pct']:.1f}" for s in per_seed)
              + f"): completion {u['diff']:+.1f} [{u['ci95'][0]:+.1f}, {u['ci95'][1]:+.1f}], object "
              f"{uo['diff']:+.1f} [{uo['ci95'][0]:+.1f}, {uo['ci95'][1]:+.1f}]", flush=True)
        for name in per_seed[0].get("latched", {}):
            cells = []
            for i, b in enumerate(per_seed[0]["latched"][name]["by_offset"]):
                lo, hi = b["offset_cm"]
                means = [s["latched"][name]["by_offset"][i]["mean"] for s in per_seed]
                cells.append(f"{lo:.0f}–{'' if hi is None else f'{hi:.0f}'} cm "
                             + "/".join("—" if v is None else f"{v:.2f}" for v in means))
            print(f"{'':24s} latched {name} per seed: "
                  + " / ".join(f"{s['latched'][name]['mean']:.2f}" for s in per_seed)
                  + f" (untrained {per_seed[0]['untrained_latched'][name]['mean']:.2f}); by the object's start "
                  "offset: " + ", ".join(cells), flush=True)
        for s in per_seed:
            if "paired_fit" in s:
                f, h = s["paired_fit"], s["paired_fit"]["holdout"]

                def cell(d):
                    return f"return {d['return']:.0f} completion {d['completion']:.1f} object {d['object_completion']:.1f}"
                print(f"{'':24s} paired fit seed {s['seed']}: {f['episodes']} episodes × {len(f['arms'])} arms "
                      f"({f['frames']:,} frames, {f['wall_s'] / 60:.1f} min), step {f['step']}; on {h['episodes']} "
                      f"held-out episodes: fitted ({h['arm_fraction']}) {cell(h['fitted'])}; "
                      + "; ".join(f"arm {arm} {cell(d)}" for arm, d in zip(f["arms"], h["arms"]))
                      + f"; hindsight {cell(h['hindsight'])}", flush=True)
    result["wall_s"] = time.perf_counter() - t_start
    b = result["tracker_alone"]
    print(f"{'tracker alone':24s} completion {b['completion_pct']:5.1f} %  object {b['object_completion_pct']:5.1f} %  "
          f"carried {b['carried_pct']:5.1f} %  T_o {b['T_o']:.2f} cm ({len(episodes)} episodes per seed)")
    a.out.parent.mkdir(parents=True, exist_ok=True)
    write_result(a.out, result, name="modulator_quality", force=a.force, indent=1)
    print(f"wrote {a.out}")
    return result


if __name__ == "__main__":
    main()
