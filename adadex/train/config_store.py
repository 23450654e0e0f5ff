"""The recipes' config nodes in Hydra's ConfigStore: each recipe's keys and defaults, made from the config
dataclasses by :mod:`adadex.train.schema`.

A recipe's YAML file names its node first in its ``defaults`` list and lists only what the recipe
changes; :func:`register` (called by :func:`adadex.train.recipe.recipe_main` before Hydra composes)
stores every node of :data:`NODES`, and :func:`keys` is a node's strict-key schema::

    defaults:
      - adadex_train        # TrainConfig's fields, their defaults
      - _self_
    ppo:
      total_frames: 250000

>>> sorted(keys("adadex_distill"))[:3]
['batch_size', 'checkpoint_every', 'force']
"""

from __future__ import annotations

from collections.abc import Callable, Mapping

from adadex.train.schema import (MISSING, RANDOMIZATION_CODE_ONLY, change_nodes, changes, defaults_of, env_settings,
                                 keys_of, modulation_node)

def train_node() -> dict:
    """The PPO recipes' node (``adadex_train``): :class:`TrainConfig`'s fields — ``ppo``, ``collector``,
    ``sim``, ``policy``, ``modulator`` (with ``modulation``), ``env``, ``reward``, ``randomization`` with
    all their fields — and the recipe's own ``force`` (replace what ``out`` holds) and ``build_preset``
    (build a missing ``dataset`` from this preset)."""
    from adadex.train.config import ModulatorSettings, TrainConfig
    from adadex.train.paired_choice import PairedChoiceConfig

    node = defaults_of(TrainConfig, expand={
        **change_nodes(),
        "modulator": defaults_of(ModulatorSettings, expand={"modulation": modulation_node(),
                                                            "paired": defaults_of(PairedChoiceConfig)}, tracker=None),
    })
    return {**node, "force": False, "build_preset": None}


def pipeline_node() -> dict:
    """The pipeline recipe's node (``adadex_pipeline``): :class:`~adadex.train.pipeline.PipelineConfig`'s
    fields and its stage groups, and the recipe's ``force`` and ``table_so_far`` (write the table of what
    ``out`` has evaluated so far, :mod:`adadex.train.table_so_far`, and train nothing)."""
    from adadex.train.pipeline import PipelineConfig

    return {**PipelineConfig.node(), "force": False, "table_so_far": False}


def distill_node() -> dict:
    """The distillation recipe's node (``adadex_distill``): :class:`~adadex.train.distill.DistillConfig`'s
    fields and the recipe's ``force``."""
    from adadex.train.distill import DistillConfig

    return {**defaults_of(DistillConfig), "force": False}


def encoder_node() -> dict:
    """The encoder recipe's node (``adadex_encoder``): :class:`~adadex.train.encoder.TrainSettings`' fields,
    ``threads`` (torch threads; null: torch's default), ``out`` and ``force``."""
    from adadex.train.encoder import TrainSettings

    return {**defaults_of(TrainSettings), "threads": None, "out": MISSING, "force": False}


def episode_settings(cfg: Mapping, where: str):
    """(the :class:`~adadex.envs.tracking.TrackingConfig`, the Table 3 randomization or ``None``) of a
    recipe with the ``env``, ``reward`` and ``randomization`` groups and a ``randomize`` switch
    (``evaluate.py``, ``teacher_rollouts.py``); a bad key or value is one :class:`ConfigError` naming
    ``where``."""
    from adadex.envs.randomization import Randomization
    from adadex.train.config import randomization_with

    env = env_settings(cfg.get("env"), cfg.get("reward"), where)
    rnd = randomization_with(changes(Randomization, cfg.get("randomization"), f"{where}.randomization",
                                     drop=RANDOMIZATION_CODE_ONLY), f"{where}.randomization")
    return env, (rnd if cfg.get("randomize") else None)


#: the nodes :func:`register` stores: name → what builds it. ``adadex_env``, ``adadex_reward``,
#: ``adadex_randomization`` and ``adadex_modulation`` are single groups for recipes that are not a
#: config dataclass themselves (``defaults: [adadex_env@env, …]`` in ``evaluate.yaml``).
NODES: dict[str, Callable[[], dict]] = {
    "adadex_train": train_node, "adadex_pipeline": pipeline_node, "adadex_distill": distill_node,
    "adadex_encoder": encoder_node,
    "adadex_env": lambda: change_nodes()["env"], "adadex_reward": lambda: change_nodes()["reward"],
    "adadex_randomization": lambda: change_nodes()["randomization"], "adadex_modulation": modulation_node}


def register() -> None:
    """Store every node of :data:`NODES` in Hydra's ``ConfigStore`` (a recipe names one first in its
    ``defaults``). Idempotent."""
    from hydra.core.config_store import ConfigStore

    cs = ConfigStore.instance()
    for name, build in NODES.items():
        cs.store(name=name, node=build())


def keys(name: str) -> dict:
    """The strict-key schema of node ``name`` (:data:`NODES`)."""
    return keys_of(NODES[name]())
