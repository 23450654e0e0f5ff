"""Train a specialist tracker on one semantic group — see train_specialist.yaml.

    python recipes/train_specialist.py dataset=data/small group=3 out=runs/specialist_3 total_frames=1000000

Writes ``out/tracker.pt`` (loads with ``Tracker.load``), ``out/checkpoint.pt`` and ``out/metrics.csv``.
"""

import hydra
from omegaconf import DictConfig

from adadex.train.recipe import run


@hydra.main(config_path=".", config_name="train_specialist", version_base="1.3")
def main(cfg: DictConfig) -> dict:
    return run(cfg, name=f"specialist_{cfg.group}")


if __name__ == "__main__":
    main()
