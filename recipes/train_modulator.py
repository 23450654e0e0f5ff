"""Train a modulator around a frozen generalist tracker — see train_modulator.yaml.

    python recipes/train_modulator.py modulator.tracker=runs/generalist/tracker.pt modulator.channels=R+O+T out=runs/mod_ROT

Writes ``out/modulator.pt`` (loads with ``Modulator.load``), ``out/checkpoint.pt`` and ``out/metrics.csv``.
An ``out`` holding other files, or a run, is refused before any work (one line, exit code 2):
``resume=true`` continues the run there (with the settings it was started with; a larger
``ppo.total_frames`` trains on), ``force=true`` starts over. Unknown keys are refused.
"""

import hydra
from omegaconf import DictConfig

from adadex.train.recipe import run, train_recipe


@hydra.main(config_path=".", config_name="train_modulator", version_base="1.3")
def main(cfg: DictConfig) -> dict:
    return run(cfg, name=f"modulator_{cfg.modulator.channels}", modulator=True)


if __name__ == "__main__":
    train_recipe(main, modulator=True)
