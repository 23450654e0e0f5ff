"""The paper's Table 1 in one command — see pipeline.yaml and adadex.train.pipeline.

    python recipes/pipeline.py preset=small out=runs/table1     # 3 seeds; wall time in docs/table1.md
    python recipes/pipeline.py preset=tiny out=/tmp/t1          # every stage at toy size, minutes
    python recipes/pipeline.py preset=small out=runs/t1 modulator.ppo.total_frames=500000 env.window=120

Runs specialists → teacher rollouts → distillation → modulators (R, R+T, R+O+T, O) → baselines
(vanilla PPO, IL+RL) → evaluation on both splits, nominal and randomized, once per training seed, and
writes ``out/table1.md``, ``out/table1.json`` and ``out/figures/``. Run it again to resume: finished
stages are skipped, a killed one continues from its checkpoint. ``table_so_far=true`` (with ``out``) writes
``out/table1_so_far.md`` / ``.json`` from the evaluations stored so far — while the run goes on, or after it
was stopped — and trains nothing (:mod:`adadex.train.table_so_far`). An ``out`` holding anything but an
earlier pipeline's output is refused before any work (``force=true`` writes into it). Bad input (a
missing dataset, an unknown key, a bad setting, a stage run with other settings) is one line on stderr
and exit code 2.
"""

from __future__ import annotations

import hydra
from omegaconf import DictConfig, OmegaConf

from adadex.errors import exit_on_error
from adadex.train import config_store
from adadex.train.recipe import check_keys, hydra_files, recipe_main

config_store.register()                    # the adadex_pipeline node that pipeline.yaml's defaults list names


def keys() -> dict:
    """What the recipe accepts: PipelineConfig's fields and its groups' (the ``adadex_pipeline`` node's
    keys, ``force`` and ``table_so_far`` among them) and ``preset``."""
    return {**config_store.keys("adadex_pipeline"), "preset": None}


def _config(cfg):
    from adadex.train.pipeline import PipelineConfig

    settings = OmegaConf.to_container(cfg, resolve=True)
    settings.pop("preset", None)
    settings.pop("table_so_far", None)
    force = bool(settings.pop("force", False))
    return PipelineConfig.from_dict(settings), force


def guard(cfg) -> None:
    """The output guard, before any work (nothing written when refused)."""
    from adadex.train.pipeline import check_pipeline_out

    if cfg.get("table_so_far"):              # writes only its own two files, into a pipeline's out
        from adadex.train.table_so_far import check_run_folder

        check_run_folder(cfg.out)
        return

    pc, force = _config(cfg)
    check_pipeline_out(pc.out, force=force, ignore=hydra_files(pc.out))


def _table_so_far(out) -> dict:
    from adadex.train.table_so_far import SO_FAR, table_so_far

    result = table_so_far(out)
    print(open(f"{out}/{SO_FAR}.md", encoding="utf-8").read())
    print(f"wrote {out}/{SO_FAR}.md and {SO_FAR}.json")
    return result["table"]


@hydra.main(config_path=".", config_name="pipeline", version_base="1.3")
def main(cfg: DictConfig) -> dict:
    from adadex.io import mark_output_dir
    from adadex.train.pipeline import PIPELINE_RUN, run_pipeline

    with exit_on_error("recipes/pipeline.py"):
        check_keys(cfg, keys())
        if cfg.get("table_so_far"):
            return _table_so_far(cfg.out)
        pc, _ = _config(cfg)
        guard(cfg)
        mark_output_dir(pc.out, PIPELINE_RUN)      # force=true: the folder is the pipeline's from now on
        result = run_pipeline(pc)
    print(open(f"{cfg.out}/table1.md", encoding="utf-8").read())
    print(f"wrote {cfg.out}/table1.md, table1.json and figures/ in {result['wall_s']:.0f} s")
    return result["table"]


if __name__ == "__main__":
    recipe_main(main, schema=keys(), guard=guard)
