"""Distil the generalist tracker from teacher rollouts by behaviour cloning — see distill.yaml.

    python recipes/distill.py rollouts=runs/rollouts out=runs/generalist steps=5000 seed=0 resume=false

Writes ``out/tracker.pt`` (loads with ``Tracker.load``), ``out/checkpoint.pt`` and ``out/metrics.csv``.
An ``out`` holding other files, or a run, is refused before any work: ``resume=true`` continues the run
there (with the settings it was started with; more ``steps`` train on), ``force=true`` starts over. A
missing rollouts folder, an unknown key or a bad setting is one line on stderr and exit code 2 (no
traceback).
"""

from __future__ import annotations

import hydra
from omegaconf import DictConfig, OmegaConf

from adadex.errors import exit_on_error
from adadex.train.checkpoint import DISTILLATION_RUN, check_run, start_run
from adadex.train.distill import DistillConfig, distill
from adadex.train.recipe import check_keys, hydra_files, recipe_main
from adadex.train.config_store import keys

KEYS = keys("adadex_distill")      # DistillConfig's fields and force


def _config(cfg) -> tuple[DistillConfig, bool]:
    settings = OmegaConf.to_container(cfg, resolve=True)
    force = bool(settings.pop("force", False))
    return DistillConfig.from_dict(settings), force


def guard(cfg) -> dict | None:
    """The output guard: the checkpoint to continue from, or None for a fresh run (nothing written)."""
    dc, force = _config(cfg)
    return check_run(dc.out, DISTILLATION_RUN, dc.to_dict(), resume=dc.resume, force=force,
                     ignore=hydra_files(dc.out))


@hydra.main(config_path=".", config_name="distill", version_base="1.3")
def main(cfg: DictConfig) -> dict:
    with exit_on_error("recipes/distill.py"):
        check_keys(cfg, KEYS)
        dc, _ = _config(cfg)
        blob = guard(cfg)
        if blob is not None and blob["iteration"] >= dc.steps:
            print(f"distill: {dc.out} holds the finished run ({blob['iteration']} of {dc.steps} steps): nothing to "
                  f"do (more steps train on)")
            return {}
        start_run(dc.out, DISTILLATION_RUN, fresh=blob is None)
        result = distill(dc)
    print(f"distill: {result['steps']} steps on {result['frames']} teacher steps -> {result['tracker']}")
    return {k: str(v) for k, v in result.items()}


if __name__ == "__main__":
    recipe_main(main, schema=KEYS, guard=guard)
