"""Evaluate a policy graph (tracker, optional modulator, channel set) on a split — see evaluate.yaml.

    python recipes/evaluate.py                                          # kinematic replay, data/small
    python recipes/evaluate.py tracker=t.pt modulator=m.pt channels=R+O+T
    python recipes/evaluate.py -m channels=none,R,R+T,R+O+T modulator=untrained   # an ablation

Writes ``result.json`` (config, summary, per-reference results) to ``out``. A missing checkpoint or
dataset, or a bad setting, is one line on stderr and exit code 2 (no traceback).
"""

from __future__ import annotations

import json
from pathlib import Path

import hydra
import torch
from omegaconf import DictConfig, OmegaConf

from adadex.errors import ConfigError, exit_on_error
from adadex.envs.replay import replay_policy
from adadex.envs.randomization import Randomization
from adadex.eval.evaluate import evaluate, format_summary
from adadex.eval.latent_smoothness import latent_smoothness, plot_latent_smoothness
from adadex.io import atomic_write_text
from adadex.modules.channels import ModulationConfig, parse_channels
from adadex.modules.modulator import Modulator
from adadex.modules.tracker import Tracker
from adadex.train.recipe import check_keys, modulation_keys, recipe_main, yaml_keys
from adadex.transforms.policy import make_policy


def _dataset(cfg) -> Path:
    path = Path(cfg.dataset)
    if not (path / "index.json").exists():
        if cfg.build_preset is None:
            raise FileNotFoundError(f"{path}: no reference dataset there (set build_preset to build one)")
        from adadex.data.build import build_dataset

        build_dataset(cfg.build_preset, path, seed=int(cfg.seed))
    return path


def _checkpoint(path, key: str) -> str:
    """``path`` if it is a file: a mistyped checkpoint is one clear line, not a traceback from torch.load."""
    if not Path(str(path)).is_file():
        raise FileNotFoundError(f"{key}={path}: no such checkpoint file")
    return str(path)


def _modules(cfg):
    tracker = replay_policy() if cfg.tracker == "replay" else Tracker.load(_checkpoint(cfg.tracker, "tracker"))
    channels = parse_channels(cfg.channels)
    if not channels:
        return tracker, None
    if cfg.modulator is None:
        raise ConfigError(f"channels={cfg.channels} needs a modulator (a checkpoint, or 'untrained')")
    if cfg.modulator == "untrained":
        torch.manual_seed(int(cfg.seed))
        return tracker, Modulator(channels)
    return tracker, Modulator.load(_checkpoint(cfg.modulator, "modulator"))


def keys() -> dict:
    """What the recipe accepts: evaluate.yaml's keys, ModulationConfig's fields under ``modulation``."""
    return yaml_keys(Path(__file__).with_name("evaluate.yaml"), modulation=modulation_keys())


@hydra.main(config_path=".", config_name="evaluate", version_base="1.3")
def main(cfg: DictConfig) -> dict:
    with exit_on_error("recipes/evaluate.py"):      # input errors: one line, exit code 2
        check_keys(cfg, keys())
        return _evaluate(cfg)


def _evaluate(cfg: DictConfig) -> dict:
    dataset = _dataset(cfg)
    tracker, modulator = _modules(cfg)
    policy = make_policy(tracker, modulator, channels=cfg.channels,
                         config=ModulationConfig(**OmegaConf.to_container(cfg.modulation)))
    res = evaluate(policy, dataset, split=(cfg.split, cfg.part), max_worlds=int(cfg.max_worlds),
                   env_transform=policy.primer, randomize=Randomization() if cfg.randomize else None,
                   seed=int(cfg.seed), keep_rollouts=bool(cfg.smoothness))
    out = Path(cfg.out)
    result = {"config": OmegaConf.to_container(cfg, resolve=True), "summary": res["summary"],
              "references": res["references"], "wall_s": res["wall_s"], "per_reference": res["per_reference"]}
    if cfg.smoothness and isinstance(tracker, Tracker):
        obs = torch.cat([td.reshape(-1).select("observation") for td in res["rollouts"]])
        pick = torch.randperm(obs.shape[0], generator=torch.Generator().manual_seed(int(cfg.seed)))[:512]
        rho = latent_smoothness(tracker.actor, obs[pick], seed=int(cfg.seed))
        plot_latent_smoothness({"tracker": rho}, out / "smoothness.png")
        result["latent_smoothness"] = {k: v for k, v in rho.items() if k != "rho"}
    atomic_write_text(out / "result.json", json.dumps(result, indent=1))
    print(f"{cfg.channels} on {res['references']} references of {cfg.split}/{cfg.part} ({res['wall_s']:.0f} s):")
    print(format_summary(res["summary"]))
    print(f"wrote {out / 'result.json'}")
    return res["summary"]


if __name__ == "__main__":
    recipe_main(main, schema=keys())
