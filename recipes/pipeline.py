"""The paper's Table 1 in one command — see pipeline.yaml and adadex.train.pipeline.

    python recipes/pipeline.py preset=small out=runs/table1     # 2 seeds; wall time measured in README
    python recipes/pipeline.py preset=tiny out=/tmp/t1          # every stage at toy size, minutes

Runs specialists → teacher rollouts → distillation → modulators (R, R+T, R+O+T, O) → baselines
(vanilla PPO, IL+RL) → evaluation on both splits, nominal and randomized, once per training seed, and
writes ``out/table1.md``, ``out/table1.json`` and ``out/figures/``. Run it again to resume: finished
stages are skipped, a killed one continues from its checkpoint. Bad input (a missing dataset, a bad
setting, a stage run with other settings) is one line on stderr and exit code 2.
"""

from __future__ import annotations

import sys

import hydra
from omegaconf import DictConfig, OmegaConf

from adadex.errors import AdadexError


@hydra.main(config_path=".", config_name="pipeline", version_base="1.3")
def main(cfg: DictConfig) -> dict:
    from adadex.train.pipeline import PipelineConfig, run_pipeline

    try:
        settings = OmegaConf.to_container(cfg, resolve=True)
        settings.pop("preset", None)
        result = run_pipeline(PipelineConfig.from_dict(settings))
    except (AdadexError, FileNotFoundError) as e:     # input errors; anything else keeps its traceback
        print(f"recipes/pipeline.py: error: {e}", file=sys.stderr)
        sys.exit(2)
    print(open(f"{cfg.out}/table1.md", encoding="utf-8").read())
    print(f"wrote {cfg.out}/table1.md, table1.json and figures/ in {result['wall_s']:.0f} s")
    return result["table"]


if __name__ == "__main__":
    main()
