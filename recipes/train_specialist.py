"""Train a specialist tracker on one semantic group — see train_specialist.yaml.

    python recipes/train_specialist.py dataset=data/small group=3 out=runs/specialist_3 ppo.total_frames=1000000

Writes ``out/tracker.pt`` (loads with ``Tracker.load``), ``out/checkpoint.pt`` and ``out/metrics.csv``.
An ``out`` holding other files, or a run, is refused before any work (one line, exit code 2):
``resume=true`` continues the run there (with the settings it was started with; a larger
``ppo.total_frames`` trains on), ``force=true`` starts over. Unknown keys are refused.
"""

import hydra
from omegaconf import DictConfig

from adadex.train.recipe import run, train_recipe


@hydra.main(config_path=".", config_name="train_specialist", version_base="1.3")
def main(cfg: DictConfig) -> dict:
    return run(cfg, name=f"specialist_{cfg.group}")


if __name__ == "__main__":
    train_recipe(main)
