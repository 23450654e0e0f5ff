"""Train the vanilla-PPO baseline on all training references of a split — see train_ppo.yaml.

    python recipes/train_ppo.py dataset=data/small split=[unseen_trajectory,train] out=runs/ppo ppo.total_frames=1000000

Writes ``out/tracker.pt`` (loads with ``Tracker.load``), ``out/checkpoint.pt`` and ``out/metrics.csv``.
An ``out`` holding other files, or a run, is refused before any work (one line, exit code 2):
``resume=true`` continues the run there (with the settings it was started with; a larger
``ppo.total_frames`` trains on), ``force=true`` starts over. Unknown keys are refused.
"""

import hydra
from omegaconf import DictConfig

from adadex.train.recipe import run, train_recipe


@hydra.main(config_path=".", config_name="train_ppo", version_base="1.3")
def main(cfg: DictConfig) -> dict:
    return run(cfg, name="ppo")


if __name__ == "__main__":
    train_recipe(main)
