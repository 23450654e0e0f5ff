"""Distil the generalist tracker from teacher rollouts by behaviour cloning — see distill.yaml.

    python recipes/distill.py rollouts=runs/rollouts out=runs/generalist steps=5000 seed=0 resume=false

Writes ``out/tracker.pt`` (loads with ``Tracker.load``), ``out/checkpoint.pt`` and ``out/metrics.csv``.
A missing rollouts folder or a bad setting is one line on stderr and exit code 2 (no traceback).
"""

from __future__ import annotations

import sys

import hydra
from omegaconf import DictConfig, OmegaConf

from adadex.errors import AdadexError
from adadex.train.distill import DistillConfig, distill


@hydra.main(config_path=".", config_name="distill", version_base="1.3")
def main(cfg: DictConfig) -> dict:
    try:
        result = distill(DistillConfig.from_dict(OmegaConf.to_container(cfg, resolve=True)))
    except AdadexError as e:     # input errors; anything else keeps its traceback
        print(f"recipes/distill.py: error: {e}", file=sys.stderr)
        sys.exit(2)
    print(f"distill: {result['steps']} steps on {result['frames']} teacher steps -> {result['tracker']}")
    return {k: str(v) for k, v in result.items()}


if __name__ == "__main__":
    main()
