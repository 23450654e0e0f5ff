"""Train the vanilla-PPO baseline on all training references of a split — see train_ppo.yaml.

    python recipes/train_ppo.py dataset=data/small split=unseen_trajectory out=runs/ppo total_frames=1000000

Writes ``out/tracker.pt`` (loads with ``Tracker.load``), ``out/checkpoint.pt`` and ``out/metrics.csv``.
"""

import hydra
from omegaconf import DictConfig

from adadex.train.recipe import run


@hydra.main(config_path=".", config_name="train_ppo", version_base="1.3")
def main(cfg: DictConfig) -> dict:
    return run(cfg, name="ppo")


if __name__ == "__main__":
    main()
