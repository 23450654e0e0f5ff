"""Do the Table 1 pipeline's specialists beat kinematic replay where they train, and does a setting change that?

The distilled generalist keeps about what its specialists learned on their references (the pipeline's
teacher check), so what a specialist gains over replay there bounds what the tracker row can gain on
unseen ones. For each ``--rows`` setting this trains the pipeline's specialist for block ``--block``
(the pipeline's own stage: :class:`adadex.train.pipeline.Pipeline`'s training config, that block's
references, seed ``seed + 101·block``) and evaluates it and kinematic replay on the block's references
under Table 3, ``--repeats`` draws a reference, the same draws for every row (environment seed
``--eval-seed`` + training seed, the pipeline teacher check's), so every row pairs with replay episode by
episode. With several ``--seeds`` the rows pool over seeds (bootstrap over references within seeds).

A row is ``default`` or changes ``section.field=value,…`` from the pipeline's specialist, with section
``ppo`` (:class:`~adadex.train.config.PPOConfig`), ``policy`` (:class:`~adadex.train.config.PolicyConfig`),
``collector`` (:class:`~adadex.train.config.CollectorConfig`) or ``reward``
(:class:`~adadex.envs.reward.RewardConfig`), e.g. ``ppo.desired_kl=0.016``,
``collector.group_size=8,ppo.advantage=group``, ``reward.w_success=2``, ``ppo.total_frames=1000000``.
``--randomization k=v,…`` changes Table 3 for the evaluation only (``object_xy_std=0,object_yaw_std=0``:
the object where the reference expects it).

Prints per row completion and object completion and their paired difference to replay with 95 %
intervals; writes ``--out`` (default ``benchmarks/results/specialist_floor.json``). Each specialist is
kept under ``--runs`` (``<row tag>_s<seed>/``, a pipeline stage: rerun, a finished one is reused, a killed
one resumes, one with other settings is refused).

    python benchmarks/specialist_floor.py --dataset data/small_pg --rows default ppo.desired_kl=0.016
"""

from __future__ import annotations

import argparse
import dataclasses
import re
import time
from pathlib import Path

import numpy as np

from _data import check_result, refuse, settings, write_result

NAME = "specialist_floor"
RESULTS = Path(__file__).resolve().parent / "results"
SECTIONS = ("ppo", "policy", "collector", "reward")


def parse_row(row: str) -> dict[str, dict]:
    """``"default"`` or ``"ppo.lr=1e-4,reward.w_success=2"`` → ``{section: {field: value}}``, each value
    of its field's type; anything else ends the benchmark naming the row."""
    from adadex.envs.reward import RewardConfig
    from adadex.train.config import CollectorConfig, PolicyConfig, PPOConfig

    defaults = {"ppo": PPOConfig(), "policy": PolicyConfig(), "collector": CollectorConfig(), "reward": RewardConfig()}
    out: dict[str, dict] = {s: {} for s in SECTIONS}
    if row == "default":
        return out
    for kv in row.split(","):
        section, dot, rest = kv.partition(".")
        if not dot or section not in SECTIONS:
            raise refuse(NAME, f"--rows {row!r}: {kv!r} is not section.field=value with section one of {SECTIONS}")
        out[section] |= settings(rest, defaults[section], f"--rows {row!r}", NAME)
    return out


def tag(row: str) -> str:
    """A folder name for the row: ``ppo.desired_kl=0.016`` → ``ppo.desired_kl-0.016``."""
    return re.sub(r"[^A-Za-z0-9_.-]", "-", row.replace("=", "-").replace(",", "_"))


def train_row(dataset: str, runs: Path, row: str, changes: dict, block: int, seed: int,
              specialists: int = 4) -> tuple[str, list[int], float]:
    """The pipeline's specialist for ``block`` (of ``specialists``, the pipeline's ``specialist.count``) and
    training ``seed`` with ``changes``: (tracker path, its references, wall seconds of this call)."""
    from adadex.train.pipeline import Pipeline, PipelineConfig, specialist_blocks

    t0 = time.perf_counter()
    cfg = PipelineConfig(out=str(runs / "_pipeline"), dataset=dataset, reward=changes["reward"], wandb=False,
                         progress=False, specialist={"count": specialists})
    p = Pipeline(cfg)
    p.ds = p.dataset()
    blocks = specialist_blocks(p.ds, cfg.specialist.count, p.env_config.window)
    if not 0 <= block < len(blocks):
        raise refuse(NAME, f"--block {block}: the pipeline has {len(blocks)} specialist blocks")
    s = cfg.specialist
    collector = dict(changes["collector"])
    tc = p._train_config(runs / f"{tag(row)}_s{seed}", seed + 101 * block, dataclasses.replace(s.ppo, **changes["ppo"]),
                         dataclasses.replace(s.policy, **changes["policy"]), group_size=collector.pop("group_size", None),
                         split=None, references=blocks[block])
    tc = dataclasses.replace(tc, collector=dataclasses.replace(tc.collector, **collector))
    r = p._ppo(tc, f"specialist {block} ({row}), seed {seed}")
    return r["policy"], blocks[block], time.perf_counter() - t0


def main(argv=None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--dataset", type=Path, default=Path("data/small_pg"))
    p.add_argument("--rows", nargs="+", default=["default"], help="specialist settings, each `default` or k=v,…")
    p.add_argument("--block", type=int, default=0, help="which of the pipeline's specialist blocks (default 0)")
    p.add_argument("--specialists", type=int, default=4, help="the pipeline's specialist.count (default 4)")
    p.add_argument("--seeds", default="0", help="training seeds, comma-separated (default 0)")
    p.add_argument("--repeats", type=int, default=8, help="Table 3 draws per reference (default 8)")
    p.add_argument("--eval-seed", type=int, default=30_000, help="evaluation env seed, plus the training seed")
    p.add_argument("--randomization", default="", help="Table 3 changes k=v,… for the evaluation")
    p.add_argument("--runs", type=Path, default=Path("runs/specialist_floor"))
    p.add_argument("--out", type=Path, default=RESULTS / f"{NAME}.json")
    p.add_argument("--force", action="store_true", help="replace --out even if it is not this benchmark's")
    a = p.parse_args(argv)
    check_result(a.out, name=NAME, force=a.force)
    if a.repeats < 1:
        raise refuse(NAME, f"--repeats must be ≥ 1, got {a.repeats}")
    try:
        seeds = [int(s) for s in a.seeds.split(",")]
    except ValueError:
        raise refuse(NAME, f"--seeds: comma-separated integers, got {a.seeds!r}") from None
    if not (a.dataset / "index.json").is_file():
        raise refuse(NAME, f"--dataset {a.dataset}: no reference dataset there (adadex data build --preset small "
                           f"--planned-grasp --out {a.dataset})")
    if len(set(a.rows)) != len(a.rows):
        raise refuse(NAME, f"--rows: a row is listed twice ({a.rows})")
    rows = {row: parse_row(row) for row in a.rows}

    from adadex.envs.randomization import Randomization
    from adadex.errors import AdadexError
    from adadex.eval.paired import paired_bootstrap
    from adadex.train.pipeline import Pipeline, PipelineConfig

    table3 = settings(a.randomization, Randomization(), "--randomization", NAME)
    ev = Pipeline(PipelineConfig(out=str(a.runs / "_pipeline"), dataset=str(a.dataset), randomization=table3,
                                 wandb=False, progress=False))
    ev.ds = ev.dataset()
    episodes: dict[str, dict[str, list]] = {r: {} for r in ("replay", *rows)}
    trained: dict[str, list[float]] = {r: [] for r in rows}
    for seed in seeds:
        per_row = {}
        for row, changes in rows.items():
            try:      # a folder that is not this benchmark's run, or a run made with other settings: one line
                path, refs, wall = train_row(str(a.dataset), a.runs, row, changes, a.block, seed, a.specialists)
            except AdadexError as e:
                raise refuse(NAME, e) from None
            per_row[row] = path
            trained[row].append(wall / 60)
        for row in ("replay", *rows):
            policy = ev.policy("replay", {}) if row == "replay" else ev.policy("tracker", {"tracker": per_row[row]})
            r = ev.evaluate(policy, "unseen_trajectory", "randomized", a.eval_seed + seed, references=refs,
                            repeats=a.repeats)["per_episode"]
            for k in ("reference", "completion", "object_completion"):
                episodes[row].setdefault(k, []).extend(r[k])
            episodes[row].setdefault("seed", []).extend([seed] * len(r["reference"]))
    base = episodes["replay"]
    ids, seed_ids = np.asarray(base["reference"]), np.asarray(base["seed"])
    result = {"dataset": str(a.dataset), "block": a.block, "seeds": seeds, "repeats": a.repeats,
              "eval_seed": a.eval_seed, "randomization": table3, "episodes": len(ids), "rows": {}}
    print(f"specialist block {a.block}, {len(ids)} paired episodes ({len(seeds)} seed(s) × {a.repeats} Table 3 draws"
          f"{', changed: ' + a.randomization if a.randomization else ''}); points, 95 % over references")
    print(f"{'row':44s} {'completion':>10s} {'− replay':>22s} {'object compl.':>13s} {'− replay':>22s}")
    for row in ("replay", *rows):
        e = episodes[row]
        entry = {m: 100 * float(np.mean(e[m])) for m in ("completion", "object_completion")}
        line = f"{row:44s} {entry['completion']:9.1f}% {'':>22s} {entry['object_completion']:12.1f}% "
        if row != "replay":
            line = f"{row:44s} {entry['completion']:9.1f}% "
            for m in ("completion", "object_completion"):
                d = paired_bootstrap(100 * np.asarray(e[m], float), 100 * np.asarray(base[m], float), ids, seed_ids)
                entry[f"{m}_minus_replay"], entry[f"{m}_minus_replay_ci95"] = d["estimate"], d["ci95"]
                if m == "completion":
                    line += f"{d['estimate']:+6.1f} [{d['ci95'][0]:+5.1f}, {d['ci95'][1]:+5.1f}]  "
                    line += f"{entry['object_completion']:12.1f}% "
                else:
                    line += f"{d['estimate']:+6.1f} [{d['ci95'][0]:+5.1f}, {d['ci95'][1]:+5.1f}]"
            entry["changes"] = {k: v for k, v in rows[row].items() if v}
            entry["minutes_this_call"] = trained[row]
        entry["per_episode"] = {m: e[m] for m in ("completion", "object_completion")}
        result["rows"][row] = entry
        print(line)
    result["per_episode_reference"], result["per_episode_seed"] = base["reference"], base["seed"]
    write_result(a.out, result, name=NAME, force=a.force)
    return result


if __name__ == "__main__":
    main()
