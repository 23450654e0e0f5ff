"""Roll out trained specialists and keep their successful trajectories — see teacher_rollouts.yaml.

    python recipes/teacher_rollouts.py dataset=data/small teachers=runs/specialists out=runs/rollouts

Writes ``out/buffer/`` (a TorchRL replay buffer, memmap storage; ``adadex.train.rollouts.load_rollouts``)
and ``out/rollouts.json`` (per reference: episodes tried and kept, success rate, frames stored). A
missing folder or a bad setting is one line on stderr and exit code 2 (no traceback).
"""

from __future__ import annotations

from pathlib import Path

import hydra
from omegaconf import DictConfig, OmegaConf

from adadex.errors import exit_on_error
from adadex.train.recipe import check_keys, recipe_main, yaml_keys
from adadex.train.rollouts import specialist_teachers, teacher_rollouts


def keys() -> dict:
    """What the recipe accepts: teacher_rollouts.yaml's keys and the fields of its groups (``env``,
    ``reward``, ``randomization``)."""
    from adadex.train.config_store import keys as node_keys

    return yaml_keys(Path(__file__).with_name("teacher_rollouts.yaml"),
                     **{g: node_keys(f"adadex_{g}") for g in ("env", "reward", "randomization")})


@hydra.main(config_path=".", config_name="teacher_rollouts", version_base="1.3")
def main(cfg: DictConfig) -> dict:
    with exit_on_error("recipes/teacher_rollouts.py"):       # input errors: one line, exit code 2
        check_keys(cfg, keys())
        from adadex.train.config_store import episode_settings

        env, randomize = episode_settings(OmegaConf.to_container(cfg, resolve=True), "teacher_rollouts")
        teachers = specialist_teachers(cfg.teachers, cfg.dataset)
        info = teacher_rollouts(teachers, cfg.dataset, cfg.out, episodes_per_reference=int(cfg.episodes_per_reference),
                                randomize=randomize, config=env, seed=int(cfg.seed), max_worlds=int(cfg.max_worlds),
                                criterion=str(cfg.criterion), nthread=int(cfg.env_threads), force=bool(cfg.force),
                                progress=bool(cfg.progress))
    print(f"{len(info['teachers'])} teachers: kept {info['episodes_kept']} of {info['episodes_tried']} episodes "
          f"({info['success_pct']:.1f} %), {info['frames']} steps -> {cfg.out}")
    return {k: v for k, v in info.items() if k != "per_reference"}


if __name__ == "__main__":
    recipe_main(main, schema=keys())
