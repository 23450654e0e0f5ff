"""The recipes' config schema, made from the config dataclasses: one set of keys, one default per setting.

A recipe's YAML file lists only what the recipe changes; every key and every default comes from a
config dataclass (:class:`~adadex.train.config.TrainConfig`, :class:`~adadex.train.pipeline.PipelineConfig`,
:class:`~adadex.train.distill.DistillConfig` and the configs nested in them), stored in Hydra's
``ConfigStore`` by :func:`register` under the names of :data:`NODES`, and named first in the recipe's
``defaults`` list::

    defaults:
      - adadex_train        # TrainConfig's fields, their defaults
      - _self_
    ppo:
      total_frames: 250000

So a YAML key is a field name (``ppo.total_frames``, ``modulator.channels``, ``env.window``,
``reward.w_prox``), any field of the tree can be set on the command line without ``+``, and a key that
is not a field is refused (:func:`keys_of` is the strict-key schema :func:`adadex.train.recipe.recipe_main`
checks). The node is built from the dataclasses' own defaults (:func:`defaults_of`) and the composed
config goes back through them (``TrainConfig.from_dict``), so their checks — one line naming the
setting — validate it. OmegaConf's typed structured configs are not used as the node itself: they cannot
express fields such as ``ModulatorSettings.init_scale`` (a number, a per-channel mapping or null).

Settings that are mappings of changes (``reward``, ``randomization``, ``env``, ``modulation``) appear
in the node with every field of their class; the config keeps only the entries that differ from the
class default (:func:`changes`), so a run's stored settings name what it changed.

>>> from adadex.train.config import PPOConfig
>>> defaults_of(PPOConfig)["total_frames"], keys_of({"ppo": {"lr": 0.1}, "seed": 0})
(1000000, {'ppo': {'lr': None}, 'seed': None})
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Mapping

from adadex.errors import ConfigError

#: a required field in a node: OmegaConf's "missing value" (the recipe or the command line must set it)
MISSING = "???"


def _plain(v):
    """A default as YAML would write it: tuples as lists, dataclasses as mappings."""
    if dataclasses.is_dataclass(v) and not isinstance(v, type):
        return {f.name: _plain(getattr(v, f.name)) for f in dataclasses.fields(v)}
    if isinstance(v, (tuple, list)):
        return [_plain(x) for x in v]
    if isinstance(v, Mapping):
        return {k: _plain(x) for k, x in v.items()}
    return v


def defaults_of(cls, *, drop=(), expand: Mapping | None = None, **values) -> dict:
    """The node of dataclass ``cls``: ``{field: default}``, a nested dataclass's default as its own
    mapping, a required field as :data:`MISSING`; fields in ``drop`` left out; ``expand`` maps a field
    to the node that stands for it (a mapping-of-changes field shown with its class's fields);
    ``values`` replace defaults."""
    node = {}
    for f in dataclasses.fields(cls):
        if f.name in drop:
            continue
        if f.default is not dataclasses.MISSING:
            v = f.default
        elif f.default_factory is not dataclasses.MISSING:
            v = f.default_factory()
        else:
            v = MISSING
        node[f.name] = _plain(v)
    node.update(expand or {})
    unknown = set(values) - set(node)
    if unknown:
        raise ConfigError(f"{cls.__name__}: no field {sorted(unknown)}")
    node.update({k: _plain(v) for k, v in values.items()})
    return node


def keys_of(node: Mapping) -> dict:
    """The strict-key schema of a node: ``{key: None}`` for a value, a nested schema for a non-empty
    mapping (an empty one, or ``None``, takes any mapping: its class checks it where it is used)."""
    return {k: keys_of(v) if isinstance(v, Mapping) and v else None for k, v in node.items()}


def changes(cls, values: Mapping | None, where: str, *, drop=()) -> dict:
    """The entries of ``values`` that differ from dataclass ``cls``'s defaults (lists and tuples alike);
    a key that is not a field of ``cls`` (or is in ``drop``) is refused naming ``where``."""
    values = dict(values or {})
    base = defaults_of(cls, drop=drop)
    unknown = sorted(set(values) - set(base))
    if unknown:
        raise ConfigError(f"{where}: unknown setting{'s' if len(unknown) > 1 else ''} {', '.join(map(repr, unknown))} "
                          f"(known: {', '.join(sorted(base))})")
    return {k: v for k, v in values.items() if _plain(v) != base[k]}


# ----------------------------------------------------------------------------------------------
# The nodes

def train_node() -> dict:
    """The PPO recipes' node (``adadex_train``): :class:`TrainConfig`'s fields — ``ppo``, ``collector``,
    ``sim``, ``policy``, ``modulator`` (with ``modulation``), ``env``, ``reward``, ``randomization`` with
    all their fields — and the recipe's own ``force`` (replace what ``out`` holds) and ``build_preset``
    (build a missing ``dataset`` from this preset)."""
    from adadex.train.config import ModulatorSettings, TrainConfig

    node = defaults_of(TrainConfig, expand={
        **change_nodes(),
        "modulator": defaults_of(ModulatorSettings, expand={"modulation": modulation_node()}, tracker=None),
    })
    return {**node, "force": False, "build_preset": None}


def modulation_node() -> dict:
    """:class:`~adadex.modules.channels.ModulationConfig`'s fields and defaults."""
    from adadex.modules.channels import ModulationConfig

    return defaults_of(ModulationConfig)


def change_nodes() -> dict:
    """``env`` (:class:`~adadex.envs.tracking.TrackingConfig` but its reward), ``reward``
    (:class:`~adadex.envs.reward.RewardConfig`) and ``randomization`` (Table 3's
    :class:`~adadex.envs.randomization.Randomization`, but the per-joint effects and patches set in code)."""
    from adadex.envs.randomization import Randomization
    from adadex.envs.reward import RewardConfig
    from adadex.envs.tracking import TrackingConfig

    return {"env": defaults_of(TrackingConfig, drop=ENV_CODE_ONLY),
            "reward": defaults_of(RewardConfig),
            "randomization": defaults_of(Randomization, drop=RANDOMIZATION_CODE_ONLY)}


#: TrackingConfig fields not set through ``env`` (the reward has its own node)
ENV_CODE_ONLY = ("reward",)
#: Randomization fields set in code only (per-joint effect ranges, a patch to randomize around)
RANDOMIZATION_CODE_ONLY = ("effects", "patch")


def pipeline_node() -> dict:
    """The pipeline recipe's node (``adadex_pipeline``): :class:`~adadex.train.pipeline.PipelineConfig`'s
    fields and its stage groups, and the recipe's ``force``."""
    from adadex.train.pipeline import PipelineConfig

    return {**PipelineConfig.node(), "force": False}


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


def env_settings(env: Mapping | None, reward: Mapping | None, where: str):
    """The :class:`~adadex.envs.tracking.TrackingConfig` with ``env`` and ``reward`` changes (an evaluation
    recipe's ``env`` and ``reward`` nodes); a bad key or value is one :class:`ConfigError` naming
    ``where``."""
    from adadex.envs.reward import RewardConfig
    from adadex.envs.tracking import TrackingConfig

    env = changes(TrackingConfig, env, f"{where}.env", drop=ENV_CODE_ONLY)
    reward = changes(RewardConfig, reward, f"{where}.reward")
    try:
        return TrackingConfig(**env, reward=RewardConfig(**reward))
    except (TypeError, ValueError) as e:
        raise ConfigError(f"{where}: {e}") from None


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
