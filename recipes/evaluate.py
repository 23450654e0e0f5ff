"""Evaluate a policy graph (tracker, optional modulator, channel set) on a split — see evaluate.yaml.

    python recipes/evaluate.py                                          # kinematic replay, data/small
    python recipes/evaluate.py tracker=t.pt modulator=m.pt channels=R+O+T
    python recipes/evaluate.py -m channels=none,R,R+T,R+O+T modulator=untrained   # an ablation

Writes ``result.json`` (config, summary, per-reference results) to ``out``. An ``out`` holding anything
but an earlier ``evaluate.py`` output (its marker) is refused before any work, nothing written, not even
Hydra's ``.hydra/`` (``force=true`` writes into it); an earlier output is replaced. A missing checkpoint or
dataset, a file that is not a checkpoint, or a bad setting (``channels``, ``split``/``part``,
``max_worlds``) is one line on stderr and exit code 2 (no traceback), checked before any work.
"""

from __future__ import annotations

import json
from pathlib import Path

import hydra
import torch
from omegaconf import DictConfig, OmegaConf

from adadex.data.reference import ReferenceDataset, SplitError
from adadex.errors import AdadexError, ConfigError, check_number, exit_on_error
from adadex.envs.replay import replay_policy
from adadex.eval.evaluate import evaluate, format_summary
from adadex.eval.latent_smoothness import latent_smoothness, plot_latent_smoothness
from adadex.io import atomic_write_text, output_kind
from adadex.modules.channels import ModulationConfig, parse_channels
from adadex.modules.modulator import Modulator
from adadex.modules.tracker import Tracker
from adadex.train.recipe import (
    EVALUATION,
    check_keys,
    check_recipe_out,
    claim_recipe_out,
    recipe_main,
    yaml_keys,
)
from adadex.transforms.policy import make_policy


def _dataset(cfg) -> Path:
    from adadex.data.build import dataset_at

    return dataset_at(cfg.dataset, preset=cfg.build_preset, setting="dataset", seed=int(cfg.seed),
                      hint="set build_preset to build one")


def _checkpoint(path, key: str) -> str:
    """``path`` if it is a file: a mistyped checkpoint is one clear line, not a traceback from torch.load."""
    if not Path(str(path)).is_file():
        raise FileNotFoundError(f"{key}={path}: no such checkpoint file")
    return str(path)


def _load(cls, path, key: str):
    """``cls.load`` of the checkpoint ``key=path``; a file that is not one is one line naming the setting."""
    try:
        return cls.load(_checkpoint(path, key))
    except (FileNotFoundError, AdadexError):
        raise
    except ValueError as e:             # the loaders' "not a readable … checkpoint" (torch's long reason cut)
        raise ConfigError(f"{key}={path}: {str(e).split(' (')[0].removeprefix(f'{path}: ')}") from None


#: The splits and parts a built dataset has (adadex.data.build)
SPLITS, PARTS = ("unseen_trajectory", "unseen_object"), ("train", "test")


def check_settings(cfg) -> None:
    """The settings checked before any work (a dataset build, a checkpoint load), each error one line
    naming the key: ``channels``, ``max_worlds``, ``split``/``part`` (against the dataset's own splits
    when it exists)."""
    try:
        parse_channels(cfg.channels)
    except ValueError as e:
        raise ConfigError(f"channels={cfg.channels}: {e}") from None
    check_number("max_worlds", cfg.max_worlds, low=1, integer=True)
    _env(cfg)                                   # env, reward, randomization
    if (Path(str(cfg.dataset)) / "index.json").is_file():
        try:
            ReferenceDataset(cfg.dataset).split(str(cfg.split), str(cfg.part))
        except SplitError as e:
            raise ConfigError(f"split={cfg.split} part={cfg.part}: {e}") from None
    elif cfg.split not in SPLITS or cfg.part not in PARTS:
        key, value, known = ("split", cfg.split, SPLITS) if cfg.split not in SPLITS else ("part", cfg.part, PARTS)
        raise ConfigError(f"{key}={value}: no such {key}; known: {', '.join(known)}")


def _modules(cfg):
    tracker = replay_policy() if cfg.tracker == "replay" else _load(Tracker, cfg.tracker, "tracker")
    channels = parse_channels(cfg.channels)
    if not channels:
        return tracker, None
    if cfg.modulator is None:
        raise ConfigError(f"channels={cfg.channels} needs a modulator (a checkpoint, or 'untrained')")
    if cfg.modulator == "untrained":
        torch.manual_seed(int(cfg.seed))
        return tracker, Modulator(channels)
    return tracker, _load(Modulator, cfg.modulator, "modulator")


def _env(cfg):
    """The episodes' :class:`TrackingConfig` (``env``, ``reward``) and the randomization (Table 3 with the
    ``randomization`` changes when ``randomize``, else None); a bad setting is a :class:`ConfigError`."""
    from adadex.train.config_store import episode_settings

    return episode_settings(OmegaConf.to_container(cfg, resolve=True), "evaluate")


def guard(cfg) -> None:
    """What is checked before Hydra starts: the settings (:func:`check_settings`), then ``out``."""
    check_settings(cfg)
    check_recipe_out(cfg, EVALUATION)


def keys() -> dict:
    """What the recipe accepts: evaluate.yaml's keys and the fields of its groups (``modulation``,
    ``env``, ``reward``, ``randomization``)."""
    from adadex.train.config_store import keys as node_keys

    return yaml_keys(Path(__file__).with_name("evaluate.yaml"),
                     **{g: node_keys(f"adadex_{g}") for g in ("modulation", "env", "reward", "randomization")})


@hydra.main(config_path=".", config_name="evaluate", version_base="1.3")
def main(cfg: DictConfig) -> dict:
    with exit_on_error("recipes/evaluate.py"):      # input errors: one line, exit code 2
        check_keys(cfg, keys())
        check_settings(cfg)
        check_recipe_out(cfg, EVALUATION)              # someone else's folder: refused, before any work
        return _evaluate(cfg)


def _evaluate(cfg: DictConfig) -> dict:
    tracker, modulator = _modules(cfg)          # before a dataset build: a bad checkpoint is found at once
    earlier = output_kind(Path(str(cfg.out))) == EVALUATION
    claim_recipe_out(cfg, EVALUATION)           # marked only once the inputs loaded: a refusal writes nothing
    if earlier and not cfg.smoothness:          # an earlier output's figure would not match the result
        (Path(str(cfg.out)) / "smoothness.png").unlink(missing_ok=True)
    dataset = _dataset(cfg)
    policy = make_policy(tracker, modulator, channels=cfg.channels,
                         config=ModulationConfig(**OmegaConf.to_container(cfg.modulation)))
    env, randomize = _env(cfg)
    res = evaluate(policy, dataset, split=(cfg.split, cfg.part), max_worlds=int(cfg.max_worlds),
                   env_transform=policy.primer, randomize=randomize, config=env,
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
    recipe_main(main, schema=keys(), guard=guard)
