"""Table 1 from what a pipeline run has evaluated so far, while it runs or after it was stopped.

The pipeline writes ``table1.json`` once every seed has finished every stage, the data-scaling study and
the teacher checks included — on 2 cores hours after the first seeds' rows are in. :func:`table_so_far`
aggregates the evaluations already stored under ``out/seed_<s>/eval/`` the way the finished run will
(:func:`adadex.eval.table1.aggregate`: bootstrap over references pooled across seeds, each row paired
with the tracker on the same draws): per split and condition, each row over the seeds that have evaluated
it and the tracker there — the pipeline evaluates replay and the tracker first, so their comparison pools
every seed that has reached it while later rows pool fewer. It trains and evaluates nothing, and writes
``table1_so_far.json`` / ``.md`` beside the run's stages (``recipes/pipeline.py out=… table_so_far=true``).

>>> from adadex.train.table_so_far import table_so_far
>>> table = table_so_far("runs/table1")                            # doctest: +SKIP
>>> table["unseen_trajectory"]["randomized"]["ROT"]["diff_vs_tracker"]["completion_pct"]   # doctest: +SKIP
"""

from __future__ import annotations

import json
import re
from pathlib import Path

from adadex.errors import ConfigError
from adadex.eval.table1 import BASE_ROW, CONDITIONS, ROW_LABELS, ROWS, SPLITS, aggregate, table_markdown
from adadex.io import atomic_write_text, output_kind
from adadex.train.stages import PIPELINE_RUN, STAGE, earlier_pipeline

#: what :func:`table_so_far` writes in the run's folder (``.json`` and ``.md``)
SO_FAR = "table1_so_far"


def collect(results_by_seed: list[dict]) -> tuple[dict, dict]:
    """``[{(split, condition, row): stage result} per seed]`` → :func:`~adadex.eval.table1.aggregate`'s
    ``summaries`` and ``episodes`` (one entry per seed, in the order given; ``None`` where a stage kept
    no per-episode results)."""
    summaries: dict = {}
    episodes: dict = {}
    for results in results_by_seed:
        for key, r in results.items():
            summaries.setdefault(key, []).append(r["summary"])
            episodes.setdefault(key, []).append(r.get("per_episode"))
    return summaries, episodes


def _seed_folders(out: Path) -> list[tuple[int, Path]]:
    found = [(int(m.group(1)), p) for p in out.glob("seed_*") if p.is_dir()
             and (m := re.fullmatch(r"seed_(\d+)", p.name))]
    return sorted(found)


def _stage(path: Path) -> dict:
    try:
        stored = json.loads(path.read_text(encoding="utf-8"))
        return {"settings": stored["settings"], "result": stored["result"]}
    except (OSError, ValueError, KeyError, TypeError) as e:
        raise ConfigError(f"{path}: not a finished stage's record ({type(e).__name__}: {e})") from e


def stored_evaluations(out) -> dict[tuple[str, str], dict[int, dict]]:
    """``{(split, condition): {seed: {row: stage result}}}`` for the seeds whose tracker has a stored
    evaluation on that split and condition (each with the rows it has evaluated there); the evaluation
    settings (repeats, draws) must agree across those seeds, or the table would pool different draws."""
    out = Path(out)
    found: dict = {}
    for split in SPLITS:
        for condition in CONDITIONS:
            by_seed, repeats = {}, {}
            for seed, folder in _seed_folders(out):
                paths = {row: folder / "eval" / split / condition / row / STAGE for row in ROWS}
                if not paths[BASE_ROW].is_file():
                    continue
                stages = {row: _stage(p) for row, p in paths.items() if p.is_file()}
                by_seed[seed] = {row: s["result"] for row, s in stages.items()}
                repeats[seed] = stages[BASE_ROW]["settings"].get("repeats")
            if len(set(repeats.values())) > 1:
                raise ConfigError(f"{out}: the {split}, {condition} evaluations were run with different "
                                  f"repeats across seeds ({repeats}); they cannot be pooled into one table")
            if by_seed:
                found[(split, condition)] = by_seed
    return found


def _pooled(split: str, condition: str, by_seed: dict) -> tuple[dict, dict]:
    """The table's block for one split and condition — every row over the seeds that evaluated it (and
    the tracker), paired with the tracker on those seeds — and ``{row: seeds pooled}``."""
    block, seeds = {}, {}
    for row in ROWS:
        have = sorted(seed for seed, rows in by_seed.items() if row in rows)
        if not have:
            continue
        pair = (BASE_ROW,) if row == BASE_ROW else (BASE_ROW, row)
        s, e = collect([{(split, condition, r): by_seed[seed][r] for r in pair} for seed in have])
        block[row] = aggregate(s, e)[split][condition][row]
        seeds[row] = have
    return block, seeds


def check_run_folder(out) -> Path:
    """``out`` as a Path if it is a pipeline run's folder, else :class:`ConfigError` (nothing written)."""
    out = Path(out)
    if output_kind(out, earlier_pipeline, PIPELINE_RUN) != PIPELINE_RUN:
        raise ConfigError(f"{out}: not a pipeline run's folder (recipes/pipeline.py out=… writes one)")
    return out


def table_so_far(out, *, write: bool = True) -> dict:
    """Table 1 over the evaluations the pipeline run ``out`` has stored so far: per split and condition,
    each row over the seeds that have evaluated it and the tracker, paired with the tracker on those
    seeds, aggregated as the finished run's ``table1.json`` (identical to it once every seed is done).

    Args:
        out: a pipeline run's folder (``recipes/pipeline.py out=…``).
        write: write ``out/table1_so_far.json`` and ``.md`` (atomically; each replaces only this
            function's earlier output).

    Returns:
        ``{"table": the table1.json structure over the rows evaluated so far, "seeds": {"<split>/<condition>":
        the seeds whose tracker is evaluated there}, "row_seeds": {"<split>/<condition>": {row: seeds pooled}}}``.

    Raises:
        ConfigError: ``out`` is not a pipeline run's folder, no seed has its tracker evaluated on any split
            and condition yet, a stored stage is unreadable, or seeds were evaluated with different repeats.
    """
    out = check_run_folder(out)
    found = stored_evaluations(out)
    if not found:
        raise ConfigError(f"{out}: no seed has its tracker evaluated on any split and condition yet")
    table: dict = {}
    row_seeds: dict = {}
    for (split, condition), by_seed in found.items():
        block, pooled = _pooled(split, condition, by_seed)
        table.setdefault(split, {})[condition] = block
        row_seeds[f"{split}/{condition}"] = pooled
    seeds = {key: pooled[BASE_ROW] for key, pooled in row_seeds.items()}
    if write:
        atomic_write_text(out / f"{SO_FAR}.json",
                          json.dumps({"table": table, "seeds": seeds, "row_seeds": row_seeds}, indent=1))
        atomic_write_text(out / f"{SO_FAR}.md", table_markdown(table, title=f"Table 1 so far ({out.name})")
                          + f"\n\nPooled so far — {_pooled_note(row_seeds)}.\n")
    return {"table": table, "seeds": seeds, "row_seeds": row_seeds}


def _pooled_note(row_seeds: dict) -> str:
    """``unseen_trajectory/randomized: seeds 0, 1 (+R, +R+T: seed 0)``, one clause per split and condition."""
    parts = []
    for key, pooled in row_seeds.items():
        base = pooled[BASE_ROW]
        fewer: dict = {}
        for row, have in pooled.items():
            if have != base:
                fewer.setdefault(tuple(have), []).append(ROW_LABELS.get(row, row))
        waiting = [ROW_LABELS[r] for r in ROWS if r not in pooled]
        extra = "; ".join(f"{', '.join(rows)}: seed{'s' if len(h) > 1 else ''} {', '.join(map(str, h))}"
                          for h, rows in fewer.items())
        if waiting:
            extra = "; ".join(x for x in (extra, f"not yet evaluated: {', '.join(waiting)}") if x)
        parts.append(f"{key}: seeds {', '.join(map(str, base))}" + (f" ({extra})" if extra else ""))
    return "; ".join(parts)
