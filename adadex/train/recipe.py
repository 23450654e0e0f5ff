"""From a Hydra recipe's config (``recipes/train_*.yaml``) to a training run.

The recipes stay thin: :func:`train_config` maps the recipe keys onto :class:`TrainConfig`
(``total_frames`` → ``ppo.total_frames``, ``ray.address`` → ``collector.ray_address``,
``split``/``part`` → ``split``, ``tracker``/``channels``/``modulator``/``modulation`` → a modulator run),
:func:`run` builds the dataset if asked and trains.
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from pathlib import Path

from omegaconf import OmegaConf

from adadex.train.config import CollectorConfig, ModulatorSettings, PolicyConfig, PPOConfig, TrainConfig

_TOP = ("seed", "resume", "group", "randomize", "checkpoint_every", "eval_every", "eval_split",
        "eval_max_references", "wandb", "progress", "reward", "randomization")


def train_config(cfg: Mapping) -> TrainConfig:
    """:class:`TrainConfig` from a recipe config (a plain mapping or an OmegaConf ``DictConfig``)."""
    if OmegaConf.is_config(cfg):
        cfg = OmegaConf.to_container(cfg, resolve=True)
    ppo = dict(cfg.get("ppo") or {})
    if "total_frames" in cfg:
        ppo["total_frames"] = cfg["total_frames"]
    collector = dict(cfg.get("collector") or {})
    collector["ray_address"] = (cfg.get("ray") or {}).get("address")
    split = (cfg["split"], cfg.get("part", "train")) if cfg.get("split") else None
    modulator = None
    if cfg.get("tracker") is not None:
        modulator = ModulatorSettings(tracker=str(cfg["tracker"]), channels=str(cfg.get("channels", "R+O+T")),
                                      modulation=dict(cfg.get("modulation") or {}), **(cfg.get("modulator") or {}))
    return TrainConfig(dataset=str(cfg["dataset"]), out=str(cfg["out"]), split=split,
                       ppo=PPOConfig(**ppo), collector=CollectorConfig(**collector),
                       policy=PolicyConfig(**(cfg.get("policy") or {})), modulator=modulator,
                       **{k: cfg[k] for k in _TOP if k in cfg})


def run(cfg: Mapping, *, name: str) -> dict:
    """Build the dataset if missing (``build_preset``), train, print and return the final evaluation.

    Bad input — a missing dataset or checkpoint, a bad setting, an unknown group — is one line on
    stderr and exit code 2, no traceback (anything else is a bug and keeps its traceback)."""
    import sys

    from adadex.errors import AdadexError

    try:
        return _run(cfg, name)
    except (AdadexError, FileNotFoundError) as e:
        print(f"{name}: error: {e}", file=sys.stderr)
        sys.exit(2)


def _run(cfg: Mapping, name: str) -> dict:
    from adadex.train.ppo import train

    tc = train_config(cfg)
    dataset = Path(tc.dataset)
    if not (dataset / "index.json").exists():
        preset = cfg.get("build_preset")
        if preset is None:
            raise FileNotFoundError(f"{dataset}: no reference dataset there (set build_preset to build one)")
        from adadex.data.build import build_dataset

        build_dataset(preset, dataset, seed=tc.seed)
    result = train(tc, run_name=name)
    print(f"{name}: {result['frames']} frames, {result['iterations']} iterations -> {result['policy']}")
    print(json.dumps(result["eval"], indent=1))
    return result["eval"]
